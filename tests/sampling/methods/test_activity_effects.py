"""Activity counts effects, not calls (assumptions §12.3): each mechanism reports 0 on a step
where it provably changed nothing that reaches the plant, and > 0 with controls that differ
from the same controller without it (common random numbers) when it acts.

Each case that would pass with an activity that counts calls (a law that reports activity
while its gains multiply x - x* = 0, a tube that resets to plain MPPI, a projection or repair
the box clips back, a backup control equal to the proposal) is checked to report 0."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from workbench.problem.models import double_integrator
from workbench.problem.obstacles import Circle
from workbench.sampling.feedback.base import Gains, NoFeedback
from workbench.sampling.feedback.effect import EFFECT_RTOL, differs
from workbench.sampling.methods.cbf_projection import CBFProjectionConfig, CBFProjectionMPPI
from workbench.sampling.methods.gatekeeper import Gatekeeper, GatekeeperConfig, braking_backup
from workbench.sampling.methods.sampler import SafeMPPIPlanner, SafeOptions
from workbench.sampling.methods.shield import ShieldMPPI
from workbench.sampling.methods.tube import TubeConfig, TubeMPPI
from workbench.sampling.mppi import MPPI, MPPIConfig
from workbench.sampling.problem import navigation_costs
from workbench.sampling.robust import RMPPIConfig, RobustMPPI
from workbench.sampling.threshold import ConstantThreshold
from workbench.scenarios.methods import feedback_law, method
from workbench.scenarios.navigation import navigation_setup
from workbench.sim import Disturbance, closed_loop

STEPS = 40
VARIANCE = 100.0  # velocity disturbance of the sampling-safety study's tiny profile


@pytest.fixture(scope="module")
def nav():
    base = navigation_setup()
    return navigation_setup(mppi=replace(base.mppi, n_samples=64, horizon=30,
                                         sigma=(5.0, 5.0), lam=10.0))


FAR = (Circle((40.0, 40.0), 0.5),)  # one obstacle, beyond the reach of any sample


def run(nav, ctrl, steps=STEPS, variance=VARIANCE, seed=0, x0=None, scene=None):
    """A disturbed closed loop with the controller stream ``seed`` and the plant stream
    ``seed + 1`` (the same streams for every controller: common random numbers)."""
    return closed_loop(ctrl, nav.plant, nav.x0 if x0 is None else x0, steps,
                       np.random.default_rng(seed), np.random.default_rng(seed + 1),
                       Disturbance(variance), scene=scene, check_episode=False)


def rushing_at_an_obstacle(nav) -> np.ndarray:
    """0.6 m off the map's first obstacle, on its side facing the goal, heading at its centre
    at 4 m/s: the nominal plans enter the obstacle, so both laws change their gains."""
    o = nav.scene.obstacles()[0]
    c = np.asarray(o.center, dtype=float)
    d = (c - nav.goal[:2]) / np.linalg.norm(c - nav.goal[:2])
    return np.concatenate([c + d * (o.radius + 0.6), -4.0 * d])


def activity(ep, key) -> np.ndarray:
    return np.array([i.stats.activity[key] for i in ep.infos])


def robust(nav, law, threshold):
    return RobustMPPI(nav.problem, nav.goal, nav.mppi, RMPPIConfig(), law, threshold)


class CountsCalls:
    """A feedback law that reports activity 1 on every call (a count of calls, not of
    effects), with the gains of ``law``."""

    name = "counts_calls"

    def __init__(self, law):
        self.law = law

    def gains(self, x_nom, U, previous, stride) -> Gains:
        g = self.law.gains(x_nom, U, previous, stride)
        return replace(g, activity={"calls": 1.0})

    def set_scene(self, scene) -> None:
        self.law.set_scene(scene)


# --- the feedback laws of Robust MPPI ---------------------------------------------------------


def test_a_law_counting_calls_reports_nothing_while_its_gains_multiply_zero(nav):
    """Selection off: x*_0 = x on every step, so K (x - x*) is 0 in every sample and in the
    applied control; a law that reports 1 per call must show 0, and the controls are those of
    K = 0 bit for bit."""
    off = ConstantThreshold.selection_off()
    ep = run(nav, robust(nav, CountsCalls(nav.feedback("ilqg")), off))
    ep0 = run(nav, robust(nav, NoFeedback(nav.problem.nx, nav.problem.nu), off))
    assert len(ep.U) == len(ep0.U) == STEPS
    np.testing.assert_array_equal(ep.U, ep0.U)
    assert all(i.gains_activity == {"calls": 1.0} for i in ep.infos)  # the law was called
    np.testing.assert_array_equal(activity(ep, "nominal_differs"), 0.0)
    np.testing.assert_array_equal(activity(ep, "calls"), 0.0)


def test_selection_activity_follows_the_nominal_state(nav):
    """SA-RMPPI's declared activity: 0 on every step with the selection off, positive with a
    threshold no candidate meets, and the controls then differ from those with it off."""
    key = method("sa_rmppi").activity
    off = run(nav, robust(nav, nav.feedback("bas_ilqg"), ConstantThreshold.selection_off()))
    on = run(nav, robust(nav, nav.feedback("bas_ilqg"), ConstantThreshold(0.0)))
    np.testing.assert_array_equal(activity(off, key), 0.0)
    act = activity(on, key)
    assert act[0] == 0.0 and np.all(act[1:] == 1.0)  # the first step starts at x
    np.testing.assert_array_equal(on.U[0], off.U[0])
    assert differs(on.U[1], off.U[1])


@pytest.mark.parametrize("kind", ["ecbf", "al_ilqg"])
def test_feedback_law_activity_is_zero_when_its_gains_cannot_reach_the_plant(nav, kind):
    """The ECBF law computes active rows on most steps of this episode (its own share, as it
    reported before), yet with the selection off its gains never reach the plant: the
    declared activity is 0 on every step and the controls equal those of K = 0."""
    off = ConstantThreshold.selection_off()
    key = method("sais_ecbf" if kind == "ecbf" else "sais_al").activity
    ep = run(nav, robust(nav, feedback_law(nav, kind), off))
    ep0 = run(nav, robust(nav, NoFeedback(nav.problem.nx, nav.problem.nu), off))
    np.testing.assert_array_equal(ep.U, ep0.U)
    np.testing.assert_array_equal(activity(ep, key), 0.0)
    if kind == "ecbf":  # the law did change its gains: they just multiplied zero
        raw = np.array([i.gains_activity[key] for i in ep.infos])
        assert np.mean(raw > 0) > 0.3, raw


@pytest.mark.parametrize("kind", ["ecbf", "al_ilqg"])
def test_feedback_law_activity_counts_steps_where_its_gains_reach_the_plant(nav, kind):
    """A threshold no candidate meets: the propagated nominal is taken, x*_0 != x under the
    disturbance; the law's activity is positive only on such steps, and its gains move the
    controls away from those of the plain tracking gains."""
    never = ConstantThreshold(0.0)  # free energies are > 0: no candidate is admissible
    key = method("sais_ecbf" if kind == "ecbf" else "sais_al").activity
    x0 = rushing_at_an_obstacle(nav)
    ep = run(nav, robust(nav, feedback_law(nav, kind), never), x0=x0)
    ep_ilqg = run(nav, robust(nav, nav.feedback("ilqg"), never), x0=x0)
    act, nominal = activity(ep, key), activity(ep, "nominal_differs")
    assert np.all(act[nominal == 0.0] == 0.0)
    assert np.any(act > 0), act
    n = min(len(ep.U), len(ep_ilqg.U))
    assert differs(ep.U[:n], ep_ilqg.U[:n])


# --- Tube-MPPI ----------------------------------------------------------------------------------


def tube(nav, threshold):
    return TubeMPPI(nav.physical_problem(), nav.goal, nav.mppi, TubeConfig(threshold=threshold))


def test_tube_that_resets_every_step_reports_no_activity_and_is_plain_mppi(nav):
    """A nominal reset on every step hands the plant MPPI's control from the measured state:
    the declared activity is 0 on every step, the controls are MPPI's bit for bit."""
    key = method("tube_mppi").activity
    ep = run(nav, tube(nav, -1e12))
    ep0 = run(nav, MPPI(nav.physical_problem(), nav.goal, nav.mppi))
    np.testing.assert_array_equal(ep.U, ep0.U)
    np.testing.assert_array_equal(activity(ep, "nominal_reset"), 1.0)  # an event, reported
    np.testing.assert_array_equal(activity(ep, key), 0.0)


def test_tube_that_tracks_its_nominal_reports_activity_and_other_controls(nav):
    key = method("tube_mppi").activity
    ep = run(nav, tube(nav, 1e12))
    ep0 = run(nav, MPPI(nav.physical_problem(), nav.goal, nav.mppi))
    act = activity(ep, key)
    assert np.mean(act) > 0.5, act
    n = min(len(ep.U), len(ep0.U))
    first = int(np.argmax(act > 0))
    # identical up to the first step the tube changed the control, different from there on
    np.testing.assert_array_equal(ep.U[:first], ep0.U[:first])
    assert differs(ep.U[first], ep0.U[first]) and n > first


# --- per-sample projection and shield ---------------------------------------------------------


@pytest.fixture(scope="module")
def head_on():
    """A double integrator at (1, 0) moving at -6 m/s straight at an obstacle at the origin:
    even full thrust away (u = (5, 0)) violates the discrete CBF, its projection points along
    +x and the box clips it back to (5, 0): a violated constraint whose projection moves
    nothing (NumPy sampler: no compilation)."""
    model = double_integrator(obstacles=(Circle((0.0, 0.0), 0.5),), u_limit=5.0)
    sp = navigation_costs(model, S=(10.0, 10.0, 1.0, 1.0))
    cfg = MPPIConfig(n_samples=16, horizon=10, sigma=(0.5, 0.5), lam=1.0, backend="numpy")
    return sp, cfg, np.array([1.0, 0.0, -6.0, 0.0]), np.array([5.0, 0.0])


def pinned(ctrl, u0):
    """``ctrl`` whose planner's first control is ``u0`` (the rest of the plan as planned)."""
    plan = ctrl.planner.plan

    def first_is(state, xb, rng):
        U, W, b = plan(state, xb, rng)
        U = U.copy()
        U[0] = u0
        return U, W, b

    ctrl.planner.plan = first_is
    return ctrl


def test_projection_the_box_clips_back_is_not_counted(head_on):
    sp, cfg, x, u = head_on
    ctrl = pinned(CBFProjectionMPPI(sp, (4.0, 4.0, 0.0, 0.0), cfg), u)
    v, moved, cmin = ctrl.project(x, u)
    assert cmin < 0 and not moved  # violated, and nothing moved
    np.testing.assert_array_equal(v, u)
    _, applied, info = ctrl.step(ctrl.initial_state(), x, np.random.default_rng(0))
    np.testing.assert_array_equal(applied, u)
    assert info.stats.activity["applied_projected"] == 0.0


def test_shield_repair_the_box_clips_back_is_not_counted(head_on):
    sp, cfg, x, u = head_on
    ctrl = pinned(ShieldMPPI(sp, (4.0, 4.0, 0.0, 0.0), cfg), u)
    _, applied, info = ctrl.step(ctrl.initial_state(), x, np.random.default_rng(0))
    np.testing.assert_array_equal(applied, u)
    assert info.repair_iterations > 0 and info.shield_failed  # it tried, and failed
    assert info.stats.activity["shield_acted"] == 0.0
    assert info.stats.activity["shield_failed"] == 1.0


def plain_safe(nav):
    """The safe-kernel sampler without projection, DCBF cost or applied projection: the
    controller both per-sample methods add their mechanism to, on the same noise."""
    c = CBFProjectionMPPI(nav.physical_problem(), nav.goal, nav.mppi,
                          CBFProjectionConfig(project_applied=False))
    c.planner = SafeMPPIPlanner(nav.physical_problem(), nav.goal, nav.mppi, SafeOptions())
    c.sampler = c.planner.sampler
    return c


@pytest.mark.parametrize("name", ["cbf_projection", "shield_mppi"])
def test_per_sample_mechanisms_idle_far_from_obstacles_and_act_near_them(nav, name):
    """With the only obstacle far beyond the samples' reach: activity 0 and the controls of
    the plain safe sampler; among the map's obstacles: activity > 0 and other controls."""
    key = method(name).activity
    far = run(nav, nav.controller(name), scene=FAR)
    np.testing.assert_array_equal(activity(far, key), 0.0)
    np.testing.assert_array_equal(activity(far, "dcbf_active" if name == "shield_mppi"
                                           else "applied_projected"), 0.0)
    np.testing.assert_array_equal(far.U, run(nav, plain_safe(nav), scene=FAR).U)
    near = run(nav, nav.controller(name))
    assert np.any(activity(near, key) > 0)
    n = min(len(near.U), len(run(nav, plain_safe(nav)).U))
    assert differs(near.U[:n], run(nav, plain_safe(nav)).U[:n])


def test_dcbf_cost_without_weight_is_not_counted(nav):
    from workbench.sampling.methods.shield import ShieldConfig

    ctrl = ShieldMPPI(nav.physical_problem(), nav.goal, nav.mppi, ShieldConfig(w_dcbf=0.0))
    ep = run(nav, ctrl)
    np.testing.assert_array_equal(activity(ep, "dcbf_active"), 0.0)


# --- gatekeeper -------------------------------------------------------------------------------


class Proposes:
    """An inner controller proposing ``law(x)`` (no samples)."""

    goal = None

    def __init__(self, law):
        self.law = law

    def initial_state(self, x0=None):
        return None

    def step(self, state, x, rng):
        return None, np.asarray(self.law(np.asarray(x)[:4]), dtype=float), None


@pytest.fixture(scope="module")
def braking():
    plant = double_integrator(obstacles=(Circle((0.0, 0.0), 0.5),), u_limit=5.0)
    return plant, braking_backup(plant)


def gate_step(plant, backup, inner, x):
    g = Gatekeeper(inner, plant, backup, GatekeeperConfig())
    _, u, info = g.step(g.initial_state(x), x, np.random.default_rng(0))
    return u, info


def test_backup_equal_to_the_proposal_is_not_counted(braking):
    """Heading at the obstacle too fast to stop: the check refuses the proposal, and the
    backup's control sent is the proposal itself (full braking)."""
    plant, backup = braking
    x = np.array([1.2, 0.0, -5.0, 0.0])
    u, info = gate_step(plant, backup, Proposes(backup), x)
    assert info.backup_used  # the event
    np.testing.assert_array_equal(u, info.proposed)
    assert info.stats.activity["backup_used"] == 0.0


def test_backup_that_overrides_the_proposal_is_counted_and_idle_far_away(braking):
    plant, backup = braking
    push = Proposes(lambda x: np.array([-5.0, 0.0]))  # full thrust at the obstacle
    u, info = gate_step(plant, backup, push, np.array([1.2, 0.0, -5.0, 0.0]))
    assert info.stats.activity["backup_used"] == 1.0 and differs(u, info.proposed)
    u, info = gate_step(plant, backup, push, np.array([20.0, 20.0, 0.0, 0.0]))
    assert info.stats.activity["backup_used"] == 0.0 and not info.backup_used
    np.testing.assert_array_equal(u, info.proposed)


# --- the tolerance --------------------------------------------------------------------------


def test_differs_is_relative_per_element_above_the_tolerance():
    a = np.array([1.0, 1e6, 0.0])
    assert not differs(a, a * (1 + 0.5 * EFFECT_RTOL))
    assert differs(a, a + np.array([0.0, 0.0, 2 * EFFECT_RTOL]))
    assert not differs(a, a + np.array([0.0, 0.5e6 * EFFECT_RTOL, 0.0]))
    assert differs(a, a + np.array([0.0, 2e6 * EFFECT_RTOL, 0.0]))
    np.testing.assert_array_equal(differs(np.ones((3, 2)), [[1, 1], [1, 2], [1, 1]], axis=1),
                                  [False, True, False])
    assert differs(np.nan, np.nan) and not differs(np.inf, np.inf)

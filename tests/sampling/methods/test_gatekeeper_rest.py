"""The gatekeeper's rest check.

A safe set is invariant under a backup only if the backup ends in a safe equilibrium: the
gatekeeper commits to a proposal only if the backup rollout from it stays safe AND ends at rest
(assumptions §8.4), and refuses, at the start of an episode, a backup that does not bring the
plant to rest from a moving state. Checked on the two user models of ``examples/user_models.py``
(a 3-D point mass, a torque-driven two-link arm; fixtures in conftest.py) and the double
integrator: (a) the position-velocity braking law does not brake the arm, and the gatekeeper
refuses it by name; (b) the derived backup (model_braking_backup) is accepted and keeps the arm
safe, and the rest check refuses proposals on cases built for it (none on the double
integrator's map: test_gatekeeper.py); (c) the compiled check equals a NumPy twin per element.
The derived backup itself: test_model_braking_backup.py."""

from __future__ import annotations

import re

import casadi as ca
import numpy as np
import pytest
from conftest import rel_err

from workbench.problem.models import Model
from workbench.problem.obstacles import Circle
from workbench.sampling.methods.gatekeeper import (
    DEFAULT_REST_TOL,
    GN_DAMPING,
    REST_PUSH_STEPS,
    BackupPolicy,
    Gatekeeper,
    GatekeeperConfig,
    backup_from_expression,
    braking_backup,
    model_braking_backup,
    push_controls,
)
from workbench.scenarios.navigation import navigation_setup
from workbench.scenarios.systems import QUAD_REST_SCALE
from workbench.sim import closed_loop

RTOL = 1e-10  # per element |a - b| <= RTOL max(|a|, |b|, 1)


class Constant:
    """A deliberately unsafe controller: the same control every step, whatever the state."""

    def __init__(self, u):
        self.u = np.asarray(u, float)

    def initial_state(self, x0=None):
        return 0

    def step(self, state, x, rng):
        return state + 1, self.u.copy(), None


def run(ctrl, plant, x0, steps, scene=None):
    return closed_loop(ctrl, plant, x0, steps, np.random.default_rng(0),
                       np.random.default_rng(1), scene=scene)


# --- (a) a backup that does not end at rest is refused by name ---------------------------------


def test_braking_law_does_not_brake_the_arm_and_is_refused(um, arm):
    """The position-velocity braking law u = clip(-dq / dt) on the arm's joint rates chatters
    at the torque limits (rate 73 after 60 steps from the start check's moving state): the
    gatekeeper refuses it at the start of an episode, naming the backup, the model, the rate
    and what to pass instead; from the first step when no start state was given."""
    bad = braking_backup(arm)  # states 2, 3 are the joint rates: it builds, but does not brake
    gk = Gatekeeper(Constant([0.0, 0.0]), arm, bad)
    want = (r"^backup = 'braking' is invalid: does not bring two_link_arm to rest: from the "
            rf"start state after {REST_PUSH_STEPS} steps of u = \[.*\], its 60-step rollout "
            r"ends moving at rate (\d[\d.e+]*) per second .*above GatekeeperConfig.rest_tol = "
            r"0\.1\. Pass model_braking_backup\(plant\)")
    with pytest.raises(ValueError, match=want) as err:
        gk.initial_state(um.ARM_START)
    rate = float(re.search(want, str(err.value)).group(1))
    assert rate > 10.0  # measured 73: far from rest, not a tolerance question
    assert "dq" in str(err.value)  # the state that moves fastest is a joint rate
    with pytest.raises(ValueError, match=r"^backup = 'braking' is invalid: does not bring"):
        run(gk, arm, um.ARM_START, 5)
    state = gk.initial_state()  # no start state: the first step checks the measured state
    with pytest.raises(ValueError, match=r"^backup = 'braking' is invalid: does not bring"):
        gk.step(state, um.ARM_START, np.random.default_rng(0))
    # measured without the check, from the same moving state: the same rate
    loose = Gatekeeper(Constant([0.0, 0.0]), arm, bad, GatekeeperConfig(rest_tol=1e6))
    assert loose.check_backup_rests(um.ARM_START) >= rate * (1 - 1e-3)  # rate has 4 digits


def test_a_backup_that_keeps_pushing_is_refused_by_its_name(di):
    push = backup_from_expression(di, ca.vertcat(1.0, 0.0), name="keeps_pushing")
    with pytest.raises(ValueError, match=r"^backup = 'keeps_pushing' is invalid: does not bring "
                                         r"double_integrator to rest"):
        Gatekeeper(Constant([0.0, 0.0]), di, push).initial_state(np.array([1.0, 1.0, 0, 0]))


def test_working_backups_pass_the_start_check(um, point_mass, di):
    """Deadbeat braking on the point mass (told its velocities) and on the double integrator
    stops exactly; the quadrotor's hover law ends the start check at 0.042 with its own rate
    units (theta_dot's in units of 15), and is refused with a 40-step horizon."""
    pm = Gatekeeper(Constant([0.0] * 3), point_mass, braking_backup(point_mass, (3, 4, 5)))
    assert pm.check_backup_rests(um.POINT_MASS_START) <= 1e-12
    d = Gatekeeper(Constant([0.0, 0.0]), di, braking_backup(di))
    assert d.check_backup_rests(np.array([1.0, 1.0, 0.0, 0.0])) <= 1e-12
    nav = navigation_setup(system="planar_quadrotor")
    hover = nav.system.backup(nav.plant, None)
    assert hover.rest_scale == QUAD_REST_SCALE
    gk = Gatekeeper(Constant([0.0, 0.0]), nav.plant, hover)
    assert 0.03 < gk.check_backup_rests(nav.x0) < DEFAULT_REST_TOL  # measured 0.042
    with pytest.raises(ValueError, match=r"^backup = 'hover' is invalid: does not bring "
                                         r"planar_quadrotor to rest"):
        Gatekeeper(Constant([0.0, 0.0]), nav.plant, hover,
                   GatekeeperConfig(horizon=40)).initial_state(nav.x0)


# --- (b) the derived backup is accepted; the rest check acts where it should ------------------


def test_model_braking_backup_keeps_the_torque_driven_arm_safe(um, arm):
    """Full torque on the shoulder swings the arm's elbow and hand into the disc (the bare
    controller crashes at step 37). Behind the gatekeeper with the derived backup the arm stays
    out for 300 steps; the rest check refuses proposals whose backup is still moving at the end
    of the horizon (measured: 43 of 300 steps)."""
    bare = run(Constant([3.0, 0.0]), arm, um.ARM_START, 300)
    assert bare.crashed
    gk = Gatekeeper(Constant([3.0, 0.0]), arm, model_braking_backup(arm))
    assert gk.check_backup_rests(um.ARM_START) < 1e-4  # measured 9e-7
    ep = run(gk, arm, um.ARM_START, 300)
    assert not ep.crashed and len(ep.infos) == 300 and ep.min_margin > 0
    used = np.array([i.stats.activity["backup_used"] for i in ep.infos])
    not_at_rest = np.array([i.stats.activity["backup_not_at_rest"] for i in ep.infos])
    assert 0 < used.sum() < used.size
    assert not_at_rest.sum() > 10
    for i in ep.infos:  # refused for rest alone: safe margins, too fast at the end, backup used
        if i.not_at_rest:
            assert i.backup_used and i.backup_min_margin > 0
            assert i.backup_rest_rate > DEFAULT_REST_TOL


@pytest.mark.parametrize("make", [braking_backup, model_braking_backup])
def test_rest_check_keeps_a_fast_robot_from_outrunning_its_backup(di, make):
    """Full acceleration along a 20 m corridor towards a circle. Without the rest check the
    check's 60 steps see the circle only once it is nearer than the backup's rollout reaches,
    but beyond about 6 m/s the backup cannot stop within the horizon: the robot is too fast to
    stop when the circle comes into view and crashes. With the rest check the shield refuses to
    accelerate once the backup would not stop in time (speed at most about 6 m/s) and stops
    before the circle."""
    scene = [Circle((20.0, 5.0), 1.0)]
    x0 = np.array([0.3, 5.0, 0.0, 0.0])
    bk = make(di)
    off = run(Gatekeeper(Constant([5.0, 0.0]), di, bk, GatekeeperConfig(rest_tol=np.inf)),
              di, x0, 400, scene)
    assert off.crashed and np.max(off.X[:, 2]) > 9.0  # measured: 10.1 m/s, crash at step 162
    ep = run(Gatekeeper(Constant([5.0, 0.0]), di, bk), di, x0, 400, scene)
    assert not ep.crashed and len(ep.infos) == 400
    assert np.max(ep.X[:, 2]) < 6.1 and 18.5 < ep.X[-1, 0] < 19.0  # stopped before the circle
    assert sum(i.not_at_rest for i in ep.infos) > 20  # measured: 48 and 62


# --- (c) the compiled check equals a NumPy twin ------------------------------------------------


def numpy_point_mass_check(um, X1, horizon, iterations=3):
    """The backup check of the 3-D point mass with the derived backup, in plain NumPy: per axis
    the Gauss-Newton steps of model_braking_backup in closed form (rates (v, u) at step 0 and
    (v + dt u, u) at step 1, authorities 4 dt and 4, from u = 0, each step clipped to +-4); the
    smallest margin over x1 and the rollout (spheres, floor, ceiling), the last state and the
    final rate."""
    dt, half = um.POINT_MASS_DT, 4.0

    def law(X):
        v, u = X[:, 3:], np.zeros((len(X), 3))
        for _ in range(iterations):
            g = (v + dt * u) / (half * dt) + 2.0 * u / half
            u = np.clip(u - half * g / (3.0 + GN_DAMPING), -half, half)
        return u

    def step(X):
        return np.concatenate([X[:, :3] + dt * X[:, 3:], X[:, 3:] + dt * law(X)], axis=1)

    def hmin(X):
        h = [np.sum((X[:, :3] - np.asarray(c)) ** 2, axis=1) - r**2 for c, r in um.SPHERES]
        h += [X[:, 2] - um.FLOOR, um.CEILING - X[:, 2]]
        return np.min(np.column_stack(h), axis=1)

    X = np.array(X1, float)
    m = hmin(X)
    for _ in range(horizon):
        X = step(X)
        m = np.minimum(m, hmin(X))
    return m, X, np.max(np.abs(step(X) - X), axis=1) / dt, law


@pytest.mark.parametrize("horizon", [60, 12])
def test_compiled_check_equals_numpy_twin_on_the_point_mass(um, point_mass, horizon):
    """Random states around the spheres, speeds up to 6 m/s per axis: the derived law, the
    smallest margin, the last state and the final rate agree per element; with 12 steps many
    rollouts end moving, with 60 none of these."""
    gk = Gatekeeper(Constant([0.0] * 3), point_mass, model_braking_backup(point_mass),
                    GatekeeperConfig(horizon=horizon))
    rng = np.random.default_rng(11)
    X1 = np.column_stack([rng.uniform([0, -1, 0.2], [5, 2, 2.4], (500, 3)),
                          rng.uniform(-6.0, 6.0, (500, 3))])
    out = [gk.backup_check(x) for x in X1]
    m_ref, xT_ref, rate_ref, law = numpy_point_mass_check(um, X1, horizon)
    assert rel_err([gk.backup(x) for x in X1], law(X1)) <= RTOL
    assert rel_err([o.min_margin for o in out], m_ref) <= RTOL
    assert rel_err([o.x_final for o in out], xT_ref) <= RTOL
    assert rel_err([o.rest_rate for o in out], rate_ref) <= RTOL
    assert np.sum(m_ref > 0) > 50 and np.sum(m_ref <= 0) > 50  # safe and unsafe rollouts
    moving = rate_ref > DEFAULT_REST_TOL
    assert (np.sum(moving) > 400) if horizon == 12 else not np.any(moving)


def test_rest_scale_weighs_each_state_and_inf_ignores_one():
    """A model with a clock state (t+ = t + dt) is never at rest; with its rate unit inf the
    rest check ignores it, and a larger unit for the speed lets a slower stop pass."""
    x, u = ca.SX.sym("x", 3), ca.SX.sym("u", 1)
    dt = 0.1
    m = Model.from_expressions("clocked", x, u, ca.vertcat(x[0] + dt * x[1], x[1] + dt * u,
                                                           x[2] + dt), dt=dt, u_min=[-1.0],
                               u_max=[1.0], h=ca.vertcat(10.0 - x[0]))
    soft = backup_from_expression(m, -0.5 * x[1], name="soft")
    x1 = np.array([0.0, 1.0, 0.0])
    plain = Gatekeeper(Constant([0.0]), m, soft, GatekeeperConfig(horizon=5))
    assert plain.backup_check(x1).rest_rate == pytest.approx(1.0)  # the clock
    no_clock = Gatekeeper(Constant([0.0]), m, soft,
                          GatekeeperConfig(horizon=5, rest_scale=(1.0, 1.0, np.inf)))
    v5 = 0.95**5  # the speed after 5 steps of u = -v / 2
    assert no_clock.backup_check(x1).rest_rate == pytest.approx(v5)
    slow = Gatekeeper(Constant([0.0]), m, soft,
                      GatekeeperConfig(horizon=5, rest_scale=(10.0, 1.0, np.inf)))
    assert slow.backup_check(x1).rest_rate == pytest.approx(0.5 * v5)  # the speed's rate u
    with pytest.raises(ValueError, match=r"^backup = 'soft' is invalid: does not bring clocked"):
        plain.check_backup_rests(x1)


def test_push_controls_are_a_quarter_and_three_quarters_across_the_box(arm):
    lo, hi = push_controls(arm)
    np.testing.assert_array_equal(lo, [-1.5, -1.5])
    np.testing.assert_array_equal(hi, [1.5, 1.5])
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 2)
    m = Model.from_expressions("box", x, u, x + u, dt=1.0, u_min=[0.0, -np.inf],
                               u_max=[4.0, np.inf], h=ca.vertcat(x[0]))
    lo, hi = push_controls(m)
    np.testing.assert_array_equal(lo, [1.0, -0.5])
    np.testing.assert_array_equal(hi, [3.0, 0.5])


# --- options ---------------------------------------------------------------------------------


def test_rest_tol_inf_switches_the_rest_check_off(um, arm):
    gk = Gatekeeper(Constant([0.0, 0.0]), arm, braking_backup(arm),
                    GatekeeperConfig(rest_tol=np.inf))
    assert np.isnan(gk.check_backup_rests(um.ARM_START))
    ep = run(gk, arm, um.ARM_START, 5)
    assert not any(i.not_at_rest for i in ep.infos)


@pytest.mark.parametrize(("kw", "field"), [
    ({"rest_tol": 0.0}, "GatekeeperConfig.rest_tol"),
    ({"rest_tol": -1.0}, "GatekeeperConfig.rest_tol"),
    ({"rest_tol": float("nan")}, "GatekeeperConfig.rest_tol"),
    ({"rest_tol": True}, "GatekeeperConfig.rest_tol"),
    ({"rest_tol": "0.1"}, "GatekeeperConfig.rest_tol"),
    ({"rest_scale": ()}, "GatekeeperConfig.rest_scale"),
    ({"rest_scale": (1.0, 0.0)}, "GatekeeperConfig.rest_scale"),
    ({"rest_scale": (1.0, float("nan"))}, "GatekeeperConfig.rest_scale"),
    ({"rest_scale": (True, 1.0)}, "GatekeeperConfig.rest_scale"),
    ({"rest_scale": "ab"}, "GatekeeperConfig.rest_scale"),
])
def test_bad_rest_options_name_the_field(kw, field):
    with pytest.raises(ValueError, match=re.escape(field + " =")):
        GatekeeperConfig(**kw)


def test_bad_rest_scales_name_the_field(di):
    with pytest.raises(ValueError, match=r"^GatekeeperConfig.rest_scale = .*needs 4 entries"):
        Gatekeeper(Constant([0.0, 0.0]), di, braking_backup(di),
                   GatekeeperConfig(rest_scale=(1.0, 1.0)))
    with pytest.raises(ValueError, match=r"^rest_scale = "):
        backup_from_expression(di, -di.x[2:], rest_scale=(1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match=r"^backup.rest_scale = .*needs 4 entries"):
        Gatekeeper(Constant([0.0, 0.0]), di,
                   BackupPolicy(braking_backup(di).function, "short", (1.0, 1.0)))

"""Gatekeeper (backup shield, Gurriet et al. 2020; Agrawal & Panagou, arXiv:2211.14361): the
compiled backup check (margins, last state, final rate) equals a plain-NumPy rollout per element
on many random states, safe and unsafe ones; in closed loop the shield keeps controllers that
would crash safe by applying the backup on some steps, and a shield that ignores its check
crashes; bad options name the field. The rest check and the derived braking backup:
test_gatekeeper_rest.py."""

from __future__ import annotations

import re
from dataclasses import dataclass

import casadi as ca
import numpy as np
import pytest

from workbench.problem.models import double_integrator, single_integrator
from workbench.problem.obstacles import Circle
from workbench.sampling.methods.gatekeeper import (
    BackupCheck,
    BackupPolicy,
    Gatekeeper,
    GatekeeperConfig,
    backup_from_expression,
    braking_backup,
)
from workbench.sampling.mppi import MPPI
from workbench.sampling.step_stats import StepStats
from workbench.scenarios.navigation import navigation_setup
from workbench.sim import Disturbance, closed_loop

OBST = (Circle((2.0, 2.0), 0.8), Circle((3.5, 1.0), 0.5), Circle((1.0, 3.2), 0.6))
RTOL = 1e-10  # per element |a - b| <= RTOL max(|a|, |b|, 1)


def rel_err(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    assert a.shape == b.shape
    return float(np.max(np.abs(a - b) / np.maximum(np.maximum(np.abs(a), np.abs(b)), 1.0)))


@pytest.fixture(scope="module")
def nav():
    return navigation_setup()


def numpy_check(x1, scene, dt, gain, horizon, u_lim=5.0, with_rate=False):
    """The backup check in plain NumPy for the Euler double integrator with squared circle
    margins: braking u = clip(-gain v) from x1 (M, 4) for ``horizon`` steps; the smallest margin
    over x1 and the rollout states, the last state, and (``with_rate``) the final rate
    max_i |x_H+1 - x_H| / dt."""
    C = np.asarray(scene, float).reshape(-1, 3)

    def hmin(X):
        d2 = (X[:, None, 0] - C[None, :, 0]) ** 2 + (X[:, None, 1] - C[None, :, 1]) ** 2
        return np.min(d2 - C[None, :, 2] ** 2, axis=1)

    def step(X):
        u = np.clip(-gain * X[:, 2:], -u_lim, u_lim)
        return np.concatenate([X[:, :2] + dt * X[:, 2:], X[:, 2:] + dt * u], axis=1)

    X = np.array(x1, float)
    m = hmin(X)
    for _ in range(horizon):
        X = step(X)
        m = np.minimum(m, hmin(X))
    if with_rate:
        return m, X, np.max(np.abs(step(X) - X), axis=1) / dt
    return m, X


def random_states(rng, M, lo=(0.0, 0.0), hi=(10.0, 10.0)):
    return np.column_stack([rng.uniform(lo, hi, (M, 2)), rng.uniform(-5.0, 5.0, (M, 2))])


class Constant:
    """A deliberately unsafe controller: the same control every step, whatever the state."""

    def __init__(self, u):
        self.u, self.scenes = np.asarray(u, float), []

    def initial_state(self, x0=None):
        return 0

    def step(self, state, x, rng):
        return state + 1, self.u.copy(), ConstInfo()

    def set_scene(self, scene):
        self.scenes.append(scene)


@dataclass(frozen=True)
class ConstInfo:
    time_s: float = 0.0

    @property
    def stats(self) -> StepStats:
        return StepStats(n_samples=1, n_collision_free=1, ess=1.0, activity={"inner": 0.5})


@pytest.mark.parametrize(("gain", "horizon", "moved"), [(None, 60, False), (5.0, 25, False),
                                                        (None, 60, True)])
def test_compiled_check_equals_numpy_rollout_per_element(nav, gain, horizon, moved):
    """Many random states on the navigation map (30 circles), default deadbeat braking and a
    soft gain with a short horizon; once with obstacles moved at run time (set_scene)."""
    plant = nav.plant
    gk = Gatekeeper(Constant([0.0, 0.0]), plant, braking_backup(plant, gain=gain),
                    GatekeeperConfig(horizon=horizon))
    rng = np.random.default_rng(7)
    if moved:
        circles = [Circle(tuple(rng.uniform(1.0, 9.0, 2)), rng.uniform(0.3, 1.0))
                   for _ in range(12)]
        gk.set_scene(circles)
        assert gk.inner.scenes == [circles]
    x1 = random_states(rng, 600)
    out = [gk.backup_check(x) for x in x1]
    m = np.array([o.min_margin for o in out])
    xT = np.array([o.x_final for o in out])
    rate = np.array([o.rest_rate for o in out])
    g = 1.0 / plant.dt if gain is None else gain
    m_ref, xT_ref, rate_ref = numpy_check(x1, gk.scene, plant.dt, g, horizon, with_rate=True)
    assert rel_err(m, m_ref) <= RTOL
    assert rel_err(xT, xT_ref) <= RTOL
    assert rel_err(rate, rate_ref) <= RTOL
    safe_x1 = numpy_check(x1, gk.scene, plant.dt, g, 0)[0] > 0
    assert np.sum(m_ref > 0) > 100  # the backup is safe from many states ...
    assert np.sum(safe_x1 & (m_ref <= 0)) > 50  # ... and hits an obstacle from x1 safe ones
    if gain is None:  # deadbeat braking stops within 50 steps from any speed <= 5 m/s per axis
        assert np.all(xT_ref[:, 2:] == 0.0) and np.all(rate == 0.0)
    else:  # the soft gain has not stopped in 25 steps: most of these rollouts end moving
        assert np.sum(rate > gk.cfg.rest_tol) > 300


def run_unsafe(plant, gk_or_inner, steps=150):
    return closed_loop(gk_or_inner, plant, np.array([0.3, 0.3, 0.0, 0.0]), steps,
                       np.random.default_rng(0), np.random.default_rng(1),
                       scene=list(OBST))


@pytest.fixture(scope="module")
def unsafe_plant():
    # the obstacles of the run are given at run time: the plant's own scene is elsewhere
    return double_integrator(obstacles=(Circle((8.0, 8.0), 0.5),), u_limit=5.0,
                             scene_capacity=4)


def test_constant_control_into_an_obstacle_is_stopped(unsafe_plant):
    """Full acceleration towards the first obstacle: the bare controller crashes, the shielded
    one brakes (backup on some steps, not all) and stays out over 150 steps; every decision
    equals the NumPy check's. Deadbeat braking from these speeds always ends at rest: the rest
    check never refuses a proposal here."""
    bare = run_unsafe(unsafe_plant, Constant([5.0, 5.0]))
    assert bare.crashed
    gk = Gatekeeper(Constant([5.0, 5.0]), unsafe_plant, braking_backup(unsafe_plant))
    ep = run_unsafe(unsafe_plant, gk)
    assert not ep.crashed and len(ep.infos) == 150 and ep.min_margin > 0
    used = np.array([i.backup_used for i in ep.infos])
    assert 0 < used.sum() < used.size  # measured: 125 of 150 steps (stopped at the edge)
    # the same decision as the NumPy rollout of the proposed step, and the applied control
    dt, g = unsafe_plant.dt, 1.0 / unsafe_plant.dt
    for x, u, info in zip(ep.X[:-1], ep.U, ep.infos, strict=True):
        x1 = np.r_[x[:2] + dt * x[2:], x[2:] + dt * np.array([5.0, 5.0])]
        m, _, rate = numpy_check(x1[None], gk.scene, dt, g, gk.cfg.horizon, with_rate=True)
        assert rate[0] == 0.0 and info.backup_rest_rate == 0.0 and not info.not_at_rest
        assert info.backup_used == (not m[0] > 0)
        assert abs(info.backup_min_margin - m[0]) <= RTOL * max(abs(m[0]), 1.0)
        want = np.clip(-g * x[2:], -5.0, 5.0) if info.backup_used else np.array([5.0, 5.0])
        np.testing.assert_allclose(u, want, rtol=1e-12, atol=1e-12)
        assert info.stats.activity == {"inner": 0.5, "backup_used": float(info.backup_used),
                                       "backup_not_at_rest": 0.0}


@pytest.mark.parametrize("mutant", ["ignore_check", "never_backup"])
def test_a_shield_that_does_not_act_crashes(unsafe_plant, monkeypatch, mutant):
    gk = Gatekeeper(Constant([5.0, 5.0]), unsafe_plant, braking_backup(unsafe_plant))
    if mutant == "ignore_check":
        monkeypatch.setattr(gk, "backup_check",
                            lambda x1: BackupCheck(np.inf, np.asarray(x1), 0.0))
    else:
        monkeypatch.setattr(gk, "backup", lambda x: np.array([5.0, 5.0]))
    assert run_unsafe(unsafe_plant, gk).crashed


def test_gatekeeper_keeps_disturbed_crash_cost_mppi_safe(nav):
    """Plain MPPI with a crash cost on the navigation map under Disturbance(10): with these
    seeds it crashes at step 123; behind the shield (deadbeat braking, 60 steps) it does not
    crash in 150 steps and the backup acts on some of them (measured: 9 of 150). Every backup
    rollout ends at rest: the rest check refuses nothing on the double integrator's map."""
    phys = nav.physical_problem()

    def episode(ctrl):
        return closed_loop(ctrl, nav.plant, nav.x0, 150, np.random.default_rng(48),
                           np.random.default_rng(49), Disturbance(10.0))

    bare = episode(MPPI(phys, nav.goal, nav.mppi))
    assert bare.crashed
    gk = Gatekeeper(MPPI(phys, nav.goal, nav.mppi), nav.plant, braking_backup(nav.plant))
    assert gk.sampler is gk.inner.sampler
    ep = episode(gk)
    assert not ep.crashed
    used = np.array([i.stats.activity["backup_used"] for i in ep.infos])
    assert 0 < used.sum() < used.size
    assert all(i.stats.n_samples == nav.mppi.n_samples for i in ep.infos)
    assert sum(i.stats.activity["backup_not_at_rest"] for i in ep.infos) == 0
    assert max(i.backup_rest_rate for i in ep.infos) == 0.0


def test_backup_from_expression_clips_and_is_used(unsafe_plant):
    x = unsafe_plant.x
    pol = backup_from_expression(unsafe_plant, -100.0 * x[2:] + ca.vertcat(x[0], 0.0))
    np.testing.assert_array_equal(pol([0.0, 0.0, 1.0, -1.0]), [-5.0, 5.0])
    np.testing.assert_allclose(pol([0.5, 0.0, 0.001, 0.0]), [0.4, 0.0])
    assert isinstance(braking_backup(unsafe_plant), BackupPolicy)


@pytest.mark.parametrize(("kw", "field"), [
    ({"horizon": 0}, "GatekeeperConfig.horizon"),
    ({"horizon": 2.5}, "GatekeeperConfig.horizon"),
    ({"horizon": True}, "GatekeeperConfig.horizon"),
    ({"margin": -0.1}, "GatekeeperConfig.margin"),
    ({"margin": float("inf")}, "GatekeeperConfig.margin"),
])
def test_bad_gatekeeper_config_names_the_field(kw, field):
    with pytest.raises(ValueError, match=re.escape(field + " =")):
        GatekeeperConfig(**kw)


def test_bad_backups_and_wrappers_name_the_field(unsafe_plant):
    p = unsafe_plant
    for kw in ({"velocity": (2,)}, {"velocity": (2, 2)}, {"velocity": (2, 7)},
               {"velocity": (2.0, 3)}):
        with pytest.raises(ValueError, match=r"^velocity = "):
            braking_backup(p, **kw)
    for gain in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match=r"^gain = "):
            braking_backup(p, gain=gain)
    with pytest.raises(ValueError, match=r"^expr = "):
        backup_from_expression(p, p.x[2])  # one entry for two controls
    with pytest.raises(ValueError, match=r"^expr = "):
        backup_from_expression(p, ca.vertcat(ca.SX.sym("z"), 0.0))
    good = braking_backup(p)
    with pytest.raises(ValueError, match=r"^inner = "):
        Gatekeeper(object(), p, good)
    with pytest.raises(ValueError, match=r"^plant = "):
        Gatekeeper(Constant([0, 0]), double_integrator(u_limit=5.0), good)  # no obstacles
    with pytest.raises(ValueError, match=r"^backup = "):
        Gatekeeper(Constant([0, 0]), p, good.function)
    with pytest.raises(ValueError, match=r"^expr = "):  # another model's symbols
        backup_from_expression(single_integrator(obstacles=OBST), -single_integrator().x)
    si = single_integrator(obstacles=OBST)
    with pytest.raises(ValueError, match=r"^backup = "):  # a backup for 2 states, not 4
        Gatekeeper(Constant([0, 0]), p, backup_from_expression(si, -si.x))
    with pytest.raises(ValueError, match=r"^config = "):
        Gatekeeper(Constant([0, 0]), p, good, {"horizon": 10})
    gk = Gatekeeper(Constant([0, 0]), p, good)
    with pytest.raises(ValueError, match=r"^x = "):
        gk.step(gk.initial_state(), np.full(4, np.nan), np.random.default_rng(0))
    with pytest.raises(ValueError, match=r"^state = "):
        gk.step(0, np.zeros(4), np.random.default_rng(0))

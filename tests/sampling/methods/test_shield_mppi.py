"""Shield-MPPI (Yin et al. 2023, arXiv:2302.11719): the shield's repair equals the same loop
written here in plain NumPy with the closed-form constraint and gradient of the Euler double
integrator, on many random states; one controller step on the compiled safe kernel equals a
NumPy twin of the step (DCBF-weighted batch, MPPI update, closed-form repair) fed the kernel's
noise; mutations (no repair, no DCBF cost) fail the comparison; a disturbed closed loop on the
navigation map runs with the shield acting; bad options name the field."""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
import pytest

from workbench.problem.models import double_integrator
from workbench.problem.obstacles import Circle
from workbench.sampling.methods.sampler import SafeSampler
from workbench.sampling.methods.shield import ShieldConfig, ShieldMPPI
from workbench.sampling.methods.twin import safe_twin
from workbench.sampling.mppi import MPPIConfig
from workbench.sampling.problem import navigation_costs
from workbench.sampling.weights import importance_weights
from workbench.scenarios.navigation import navigation_setup
from workbench.sim import Disturbance, closed_loop

OBST = (Circle((2.0, 2.0), 0.8), Circle((3.5, 1.0), 0.5), Circle((1.0, 3.2), 0.6),
        Circle((2.2, 0.6), 0.4))
N, T = 125, 30
GOAL = (4.0, 4.0, 0.0, 0.0)
DT = 0.02
SHIELD = ShieldConfig(gamma=0.1, w_dcbf=1e3, repair_steps=10)
STEPS = 12
KICK = 0.1  # std of the velocity kick per step, m/s
RTOL = 1e-10  # per element |a - b| <= RTOL max(|a|, |b|, 1)
TOL = 1e-9  # a constraint is met at c >= -TOL (the shield's INFEASIBLE_TOL)
MUTANTS = {"repair": "MPPI's first control is applied unrepaired",
           "dcbf_cost": "the samples are scored without the DCBF cost"}


def rel_err(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    assert a.shape == b.shape
    return float(np.max(np.abs(a - b) / np.maximum(np.maximum(np.abs(a), np.abs(b)), 1.0)))


def closed_form(x, u, gamma, scene, dt=DT):
    """c (nh,) and dc/du (nh, 2) of the Euler double integrator with squared margins:
    c_i = h_i(p2) - 2 (1 - g) h_i(p1) + (1 - g)^2 h_i(p0), dc_i/du = 2 dt^2 (p2 - centre_i)."""
    C = np.asarray(scene, float).reshape(-1, 3)

    def h(p):
        return (p[0] - C[:, 0]) ** 2 + (p[1] - C[:, 1]) ** 2 - C[:, 2] ** 2

    p, v, k = x[:2], x[2:4], 1.0 - gamma
    p2 = p + 2 * dt * v + dt**2 * u
    return h(p2) - 2 * k * h(p + dt * v) + k**2 * h(p), 2 * dt**2 * (p2 - C[:, :2])


def repair_numpy(x, u, cfg: ShieldConfig, scene, lo=-5.0, hi=5.0):
    """The repair loop in plain NumPy: while some c_i < -TOL and steps remain, move u to the
    minimum-norm point of the most violated constraint's linearisation, then clip."""
    u = np.clip(np.asarray(u, float), lo, hi)
    c, J = closed_form(x, u, cfg.gamma, scene)
    c0, it = c.min(), 0
    while it < cfg.repair_steps and c.min() < -TOL:
        i = int(np.argmin(c))
        g = J[i]
        u = np.clip(u - c[i] / (g @ g) * g, lo, hi)
        c, J = closed_form(x, u, cfg.gamma, scene)
        it += 1
    return u, it, c0, c.min()


@pytest.fixture(scope="module")
def problem():
    model = double_integrator(obstacles=OBST, u_limit=5.0)
    sp = navigation_costs(model, S=(10.0, 10.0, 1.0, 1.0))
    cfg = MPPIConfig(n_samples=N, horizon=T, lam=1.3, sigma=(3.0, 2.4), nu_mix=0.1,
                     backend="compiled")
    return model, sp, cfg


def start() -> np.ndarray:
    """0.9 m off the line through the first obstacle's centre, heading along it at 2 m/s."""
    return np.array([1.0 - 0.9 / np.sqrt(2.0), 1.0 + 0.9 / np.sqrt(2.0), np.sqrt(2.0),
                     np.sqrt(2.0)])


def test_repair_equals_numpy_loop_on_random_states(problem):
    """Random states around the obstacles (speeds up to 4 m/s) and random controls: the same
    control, step count and constraint values as the NumPy loop; the cases cover no repair,
    one step, several steps and a failed repair (the box)."""
    model, sp, cfg = problem
    ctrl = ShieldMPPI(sp, GOAL, cfg, SHIELD)
    rng = np.random.default_rng(8)
    outcomes = {"none": 0, "one": 0, "several": 0, "failed": 0}
    worst = 0.0
    for _ in range(600):
        x = np.r_[rng.uniform(0.0, 4.5, 2), rng.uniform(-4.0, 4.0, 2)]
        if np.min(model.margins(x)) <= 0:
            continue
        u = rng.uniform(-6.0, 6.0, 2)
        r = ctrl.repair(x, u)
        u_n, it, c0, c1 = repair_numpy(x, u, SHIELD, ctrl.scene)
        assert r.iterations == it
        worst = max(worst, rel_err(r.u, u_n), rel_err(r.c_min_before, c0),
                    rel_err(r.c_min_after, c1))
        failed = c1 < -TOL
        outcomes["failed" if failed else "none" if it == 0 else "one" if it == 1
                 else "several"] += 1
    assert worst <= RTOL, worst  # measured: <= 1.2e-12
    assert min(outcomes.values()) > 0, outcomes  # measured: 302, 41, 5, 98 of 446


def test_repair_without_violation_is_the_clipped_control(problem):
    _, sp, cfg = problem
    ctrl = ShieldMPPI(sp, GOAL, cfg, SHIELD)
    x = np.array([0.3, 0.3, 0.0, 0.0])  # at rest, far from the obstacles
    r = ctrl.repair(x, np.array([7.0, -1.0]))
    np.testing.assert_array_equal(r.u, [5.0, -1.0])
    assert r.iterations == 0 and r.c_min_after == r.c_min_before > 0


@dataclass(frozen=True)
class TwinStep:
    U: np.ndarray
    u: np.ndarray
    iterations: int
    dcbf_active: float


def twin_step(ctrl: ShieldMPPI, U, x, rng, drop=frozenset()) -> TwinStep:
    assert set(drop) <= set(MUTANTS)
    sp, c, cfg = ctrl.sp, ctrl.consts, ctrl.cfg
    seed = int(rng.integers(0, 2**63))
    Z = np.transpose(ctrl.sampler.lib.normals(N, T, sp.nu, seed), (2, 0, 1))
    w = 0.0 if "dcbf_cost" in drop else SHIELD.w_dcbf
    ref = safe_twin(sp, np.tile(x, (N, 1)), U, Z, c, False, w, SHIELD.gamma)
    W = importance_weights(ref["S"], cfg.lam)
    U = np.einsum("n,ntu->tu", W.w, ref["v"])
    u, it = np.clip(U[0], c.u_min, c.u_max), 0
    if "repair" not in drop:
        u, it, _, _ = repair_numpy(x, u, SHIELD, c.scene)
    return TwinStep(U=np.vstack([U[1:], U[-1:]]), u=u, iterations=it,
                    dcbf_active=float(np.mean(ref["dcbf"] > 0)))


def run(problem, drop=frozenset()):
    """Controller and twin side by side, each step from the same plan and measured state (the
    plant follows the controller's u plus a velocity kick): per-step errors and infos."""
    model, sp, cfg = problem
    ctrl = ShieldMPPI(sp, GOAL, cfg, SHIELD)
    rng_c, rng_t, rng_w = (np.random.default_rng(s) for s in (5, 5, 6))
    st, x = ctrl.initial_state(), start()
    errs, infos = [], []
    for _ in range(STEPS):
        tw = twin_step(ctrl, st.U, x, rng_t, drop)
        st, u, info = ctrl.step(st, x, rng_c)
        errs.append({"U": rel_err(st.U, tw.U), "u": rel_err(u, tw.u),
                     "iterations": float(info.repair_iterations != tw.iterations),
                     "dcbf_active": abs(info.dcbf_active - tw.dcbf_active)})
        infos.append(info)
        dt = model.dt
        x = np.concatenate([x[:2] + dt * x[2:], x[2:] + dt * u]) + np.r_[
            0.0, 0.0, KICK * rng_w.standard_normal(2)]
    return errs, infos


@pytest.fixture(scope="module")
def exact(problem):
    return run(problem)


def test_step_equals_numpy_twin_per_element(exact):
    errs, infos = exact
    worst = {k: max(e[k] for e in errs) for k in errs[0]}
    assert max(worst.values()) <= RTOL, worst  # measured: <= 1e-12 (u)
    acted = [i.shield_acted for i in infos]
    # measured: the shield acts on 7 of 12 steps, repairs 5 in one step, 2 still violate after
    # 10 steps; every sample of this crowded scene pays some DCBF cost
    assert 0 < sum(acted) < STEPS, acted
    assert any(i.shield_acted and not i.shield_failed for i in infos)
    assert all(i.dcbf_active > 0 for i in infos)
    for i in infos:
        s = i.stats
        assert set(s.activity) == {"shield_acted", "shield_failed", "dcbf_active"}
        assert s.activity["shield_acted"] == float(i.shield_acted)
        assert s.n_samples == N and s.ess >= 1.0 and i.time_s > 0
        assert i.shield_failed == (i.c_min_after < -TOL)
        if not i.shield_acted:
            assert i.c_min_before >= -TOL and i.repair_iterations == 0


@pytest.mark.parametrize("mutant", list(MUTANTS))
def test_mutated_twin_fails_the_comparison(problem, mutant):
    errs, _ = run(problem, drop={mutant})
    worst = max(max(e.values()) for e in errs)
    assert worst > 1e4 * RTOL, MUTANTS[mutant]


def test_navigation_closed_loop_shield_acts_on_some_steps():
    """150 steps on the navigation map (physical problem, crash cost only, N = 1024, T = 100)
    with a velocity disturbance of variance 1: no crash; the shield repairs the applied control
    on some steps, fails on a few (measured: acted on 111 of 150 steps, failed on 8 after 10
    steps; 1 repair step on 78 steps, 2 on 18), and most samples pay a DCBF cost."""
    nav = navigation_setup()
    ctrl = ShieldMPPI(nav.physical_problem(), nav.goal, nav.mppi)
    ep = closed_loop(ctrl, nav.plant, nav.x0, 150, np.random.default_rng(0),
                     np.random.default_rng(1), Disturbance(1.0))
    assert not ep.crashed and len(ep.infos) == 150
    act = {k: np.array([i.stats.activity[k] for i in ep.infos])
           for k in ("shield_acted", "shield_failed", "dcbf_active")}
    print({k: (float(a.mean()), int((a > 0).sum())) for k, a in act.items()},
          np.bincount([i.repair_iterations for i in ep.infos]))
    assert 0 < act["shield_acted"].sum() < 150
    assert act["shield_failed"].sum() < act["shield_acted"].sum()
    assert np.all(act["dcbf_active"] > 0)
    assert np.linalg.norm(ep.X[-1, :2] - nav.goal[:2]) < 9.0  # measured: 12.7 m -> 6.7 m


def test_set_scene_reaches_the_sampler_and_the_shield(problem):
    _, sp, cfg = problem
    ctrl = ShieldMPPI(sp, GOAL, cfg, SHIELD)
    assert isinstance(ctrl.sampler, SafeSampler) and ctrl.sampler.lib is not None
    circles = [Circle((3.0, 3.0), 0.4)]
    ctrl.set_scene(circles)
    want = sp.model.scene_vector(circles)
    np.testing.assert_array_equal(ctrl.scene, want)
    np.testing.assert_array_equal(ctrl.consts.scene, want)
    x, u = np.array([2.0, 2.0, 3.0, 3.0]), np.array([5.0, 5.0])
    r = ctrl.repair(x, u)
    u_n, it, _, _ = repair_numpy(x, u, SHIELD, want)
    assert r.iterations == it > 0 and rel_err(r.u, u_n) <= RTOL


@pytest.mark.parametrize(("kw", "field"), [
    ({"gamma": 0.0}, "ShieldConfig.gamma"), ({"gamma": 2.0}, "ShieldConfig.gamma"),
    ({"w_dcbf": -1.0}, "ShieldConfig.w_dcbf"), ({"w_dcbf": float("nan")}, "ShieldConfig.w_dcbf"),
    ({"repair_steps": 0}, "ShieldConfig.repair_steps"),
    ({"repair_steps": 2.0}, "ShieldConfig.repair_steps"),
])
def test_bad_config_names_the_field(kw, field):
    with pytest.raises(ValueError, match=re.escape(field + " =")):
        ShieldConfig(**kw)


def test_bad_controller_input_names_the_field(problem):
    _, sp, cfg = problem
    with pytest.raises(ValueError, match=r"^shield = "):
        ShieldMPPI(sp, GOAL, cfg, shield={"gamma": 0.1})
    with pytest.raises(ValueError, match=r"^config = "):
        ShieldMPPI(sp, GOAL, None)
    ctrl = ShieldMPPI(sp, GOAL, cfg, SHIELD)
    with pytest.raises(ValueError, match=r"^state = "):
        ctrl.step(None, start(), np.random.default_rng(0))
    with pytest.raises(ValueError, match=r"^x = "):
        ctrl.step(ctrl.initial_state(), np.zeros(3), np.random.default_rng(0))

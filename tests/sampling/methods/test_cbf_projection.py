"""MPPI with per-sample CBF projection (Tao et al. 2022, arXiv:2111.06974): one controller step on
the compiled safe kernel equals a NumPy twin of the step (the safe kernel's twin, MPPI weights
and update, and the applied control's projection written here in closed form for the Euler
double integrator), fed the kernel's noise for the same seeds; mutations of the twin (no
sample projection, no projection of the applied control) fail the comparison; a disturbed
closed loop on the navigation map runs with the projection acting; bad options name the
field."""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
import pytest

from workbench.problem.barrier import embed_barrier
from workbench.problem.models import double_integrator
from workbench.problem.obstacles import Circle
from workbench.sampling.methods.cbf_projection import CBFProjectionConfig, CBFProjectionMPPI
from workbench.sampling.methods.sampler import SafeMPPIState, SafeSampler
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
GAMMA = 0.1
STEPS = 12
KICK = 0.1  # std of the velocity kick per step, m/s
RTOL = 1e-10  # per element |a - b| <= RTOL max(|a|, |b|, 1)
MUTANTS = {"samples": "the samples are not projected (plain MPPI batch)",
           "applied": "the applied control is not projected"}


def rel_err(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    assert a.shape == b.shape
    return float(np.max(np.abs(a - b) / np.maximum(np.maximum(np.abs(a), np.abs(b)), 1.0)))


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


def project_closed_form(x, u, gamma, scene, dt, lo, hi):
    """The applied control's projection for the Euler double integrator with squared margins,
    in closed form: c_i = h_i(p2) - 2 (1 - g) h_i(p1) + (1 - g)^2 h_i(p0) with
    p_k the position k steps ahead (p2 = p + 2 dt v + dt^2 u), dc_i/du = 2 dt^2 (p2 - c_i);
    the most restrictive violated constraint's minimum-norm step, clipped."""
    C = np.asarray(scene, float).reshape(-1, 3)

    def h(p):
        return (p[0] - C[:, 0]) ** 2 + (p[1] - C[:, 1]) ** 2 - C[:, 2] ** 2

    p, v, k = x[:2], x[2:4], 1.0 - gamma
    u = np.clip(u, lo, hi)
    p2 = p + 2 * dt * v + dt**2 * u
    c = h(p2) - 2 * k * h(p + dt * v) + k**2 * h(p)
    i = int(np.argmin(c))
    if c[i] >= 0:
        return u, False
    g = 2 * dt**2 * (p2 - C[i, :2])
    return np.clip(u - c[i] / (g @ g) * g, lo, hi), True


@dataclass(frozen=True)
class TwinStep:
    U: np.ndarray
    u: np.ndarray
    projected: float
    infeasible: float
    applied_projected: bool


def twin_step(ctrl: CBFProjectionMPPI, U, x, rng, drop=frozenset()) -> TwinStep:
    assert set(drop) <= set(MUTANTS)
    sp, c, cfg = ctrl.sp, ctrl.consts, ctrl.cfg
    seed = int(rng.integers(0, 2**63))
    Z = np.transpose(ctrl.sampler.lib.normals(N, T, sp.nu, seed), (2, 0, 1))
    ref = safe_twin(sp, np.tile(x, (N, 1)), U, Z, c, "samples" not in drop, 0.0, GAMMA)
    W = importance_weights(ref["S"], cfg.lam)
    U = np.einsum("n,ntu->tu", W.w, ref["v"])
    u, acted = U[0], False
    if "applied" not in drop:
        u, acted = project_closed_form(x, U[0], GAMMA, c.scene, sp.model.dt, c.u_min, c.u_max)
    return TwinStep(U=np.vstack([U[1:], U[-1:]]), u=u, projected=ref["projected"].sum() / (N * T),
                    infeasible=ref["infeasible"].sum() / (N * T), applied_projected=acted)


def run(problem, drop=frozenset()):
    """Controller and twin side by side, each step from the same plan and measured state (the
    plant follows the controller's u plus a velocity kick): per-step errors and activity."""
    model, sp, cfg = problem
    ctrl = CBFProjectionMPPI(sp, GOAL, cfg, CBFProjectionConfig(gamma=GAMMA))
    rng_c, rng_t, rng_w = (np.random.default_rng(s) for s in (5, 5, 6))
    st, x = ctrl.initial_state(), start()
    errs, infos, us = [], [], []
    for _ in range(STEPS):
        tw = twin_step(ctrl, st.U, x, rng_t, drop)  # the same plan and state as the step's
        st, u, info = ctrl.step(st, x, rng_c)
        errs.append({"U": rel_err(st.U, tw.U), "u": rel_err(u, tw.u),
                     "projected": abs(info.projected - tw.projected),
                     "infeasible": abs(info.infeasible - tw.infeasible),
                     "applied": float(info.applied_projected != tw.applied_projected)})
        infos.append(info)
        us.append(u)
        dt = model.dt
        x = np.concatenate([x[:2] + dt * x[2:], x[2:] + dt * u]) + np.r_[
            0.0, 0.0, KICK * rng_w.standard_normal(2)]
    return errs, infos, us


@pytest.fixture(scope="module")
def exact(problem):
    return run(problem)


def test_step_equals_numpy_twin_per_element(exact):
    errs, infos, us = exact
    worst = {k: max(e[k] for e in errs) for k in errs[0]}
    assert max(worst.values()) <= RTOL, worst  # measured: <= 7e-13 (u)
    applied = [i.applied_projected for i in infos]
    # the applied control is projected on some steps only (measured: 6 of 12), the samples on
    # every step (measured: 40-73 % of sample-steps, 8-28 % infeasible)
    assert 0 < sum(applied) < STEPS, applied
    assert all(0 < i.infeasible < i.projected < 1 for i in infos)
    for i, u in zip(infos, us, strict=True):
        s = i.stats
        assert set(s.activity) == {"projected", "infeasible", "applied_projected"}
        assert s.activity["projected"] == i.projected
        assert s.n_samples == N and 0 <= s.n_collision_free <= N and s.ess >= 1.0
        assert i.time_s > 0 and i.valid_weights
        # a projected applied control meets the constraints unless the box clipped it
        if i.applied_projected and i.applied_c_min < -1e-9:
            assert np.any(np.abs(u) == 5.0), (u, i.applied_c_min)


@pytest.mark.parametrize("mutant", list(MUTANTS))
def test_mutated_twin_fails_the_comparison(problem, mutant):
    errs, _, _ = run(problem, drop={mutant})
    worst = max(max(e.values()) for e in errs)
    assert worst > 1e4 * RTOL, MUTANTS[mutant]


def test_without_project_applied_the_plan_head_is_applied(problem):
    _, sp, cfg = problem
    ctrl = CBFProjectionMPPI(sp, GOAL, cfg, CBFProjectionConfig(gamma=GAMMA,
                                                                project_applied=False))
    st, u, info = ctrl.step(ctrl.initial_state(), start(), np.random.default_rng(0))
    assert not info.applied_projected and np.isnan(info.applied_c_min)
    assert info.stats.activity["applied_projected"] == 0.0
    assert u.shape == (2,) and st.U.shape == (T, 2)


def test_barrier_embedded_problem_runs(problem):
    model, _, cfg = problem
    sp = navigation_costs(embed_barrier(model))
    ctrl = CBFProjectionMPPI(sp, GOAL, cfg, CBFProjectionConfig(gamma=GAMMA))
    st, x, rng = ctrl.initial_state(), start(), np.random.default_rng(2)
    for _ in range(3):
        st, u, info = ctrl.step(st, x, rng)
        x = np.concatenate([x[:2] + model.dt * x[2:], x[2:] + model.dt * u])
    assert info.projected > 0 and np.all(np.abs(u) <= 5.0)


def test_set_scene_and_sampler(problem):
    _, sp, cfg = problem
    ctrl = CBFProjectionMPPI(sp, GOAL, cfg)
    assert isinstance(ctrl.sampler, SafeSampler) and ctrl.sampler.lib is not None
    ctrl.sampler.lib.set_threads(1)
    ctrl.sampler.lib.set_threads(2)
    ctrl.set_scene([Circle((3.0, 3.0), 0.4)])
    want = sp.model.scene_vector([Circle((3.0, 3.0), 0.4)])
    np.testing.assert_array_equal(ctrl.scene, want)
    np.testing.assert_array_equal(ctrl.consts.scene, want)
    # the applied projection uses the new scene: only the circle at (3, 3) can bind
    x = np.array([2.0, 2.0, 3.0, 3.0])
    v, acted, cmin = ctrl.project(x, np.array([5.0, 5.0]))
    vv, aa = project_closed_form(x, np.array([5.0, 5.0]), ctrl.ccfg.gamma, want, 0.02,
                                 -5.0, 5.0)
    assert acted and aa and rel_err(v, vv) <= RTOL
    C = want.reshape(-1, 3)[0]
    p2 = x[:2] + 2 * 0.02 * x[2:] + 0.02**2 * v
    k = 1.0 - ctrl.ccfg.gamma
    h = [np.sum((p - C[:2]) ** 2) - C[2] ** 2 for p in (p2, x[:2] + 0.02 * x[2:], x[:2])]
    assert abs(cmin - (h[0] - 2 * k * h[1] + k**2 * h[2])) <= 1e-12
    assert CBFProjectionMPPI(sp, GOAL, MPPIConfig(n_samples=8, horizon=5, sigma=(3.0, 2.4),
                                                  backend="numpy")).sampler.lib is None


def test_navigation_closed_loop_projects_on_some_steps():
    """150 steps on the navigation map (physical problem, crash cost only, N = 1024, T = 100)
    with a velocity disturbance of variance 1: no crash, the samples are projected on every
    step and the applied control on some (measured: on average 33 % of the sample-steps
    projected, 6 % infeasible; the applied control projected on 26 of the 150 steps)."""
    nav = navigation_setup()
    ctrl = CBFProjectionMPPI(nav.physical_problem(), nav.goal, nav.mppi)
    ep = closed_loop(ctrl, nav.plant, nav.x0, 150, np.random.default_rng(0),
                     np.random.default_rng(1), Disturbance(1.0))
    assert not ep.crashed and len(ep.infos) == 150
    act = {k: np.array([i.stats.activity[k] for i in ep.infos])
           for k in ("projected", "infeasible", "applied_projected")}
    print({k: (float(a.mean()), int((a > 0).sum())) for k, a in act.items()})
    assert np.all(act["projected"] > 0)
    assert 0 < act["applied_projected"].sum() < 150
    # it makes progress towards the goal (measured: from 12.7 m to 7.1 m in 3 s)
    assert np.linalg.norm(ep.X[-1, :2] - nav.goal[:2]) < 9.0


@pytest.mark.parametrize(("kw", "field"), [
    ({"gamma": 0.0}, "CBFProjectionConfig.gamma"), ({"gamma": 1.1}, "CBFProjectionConfig.gamma"),
    ({"gamma": "0.1"}, "CBFProjectionConfig.gamma"),
    ({"project_applied": 1}, "CBFProjectionConfig.project_applied"),
])
def test_bad_config_names_the_field(kw, field):
    with pytest.raises(ValueError, match=re.escape(field + " =")):
        CBFProjectionConfig(**kw)


def test_bad_controller_input_names_the_field(problem):
    _, sp, cfg = problem
    with pytest.raises(ValueError, match=r"^cbf = "):
        CBFProjectionMPPI(sp, GOAL, cfg, cbf={"gamma": 0.1})
    with pytest.raises(ValueError, match=r"^config = "):
        CBFProjectionMPPI(sp, GOAL, {"n_samples": 10})
    with pytest.raises(ValueError, match=re.escape("MPPIConfig.sigma =")):
        CBFProjectionMPPI(sp, GOAL, MPPIConfig(sigma=(1.0,)))
    ctrl = CBFProjectionMPPI(sp, GOAL, cfg)
    with pytest.raises(ValueError, match=r"^state = "):
        ctrl.step({"U": np.zeros((T, 2))}, start(), np.random.default_rng(0))
    with pytest.raises(ValueError, match=re.escape("state.U =")):
        ctrl.step(SafeMPPIState(U=np.zeros((T + 1, 2))), start(), np.random.default_rng(0))
    with pytest.raises(ValueError, match=r"^x = "):
        ctrl.step(ctrl.initial_state(), np.array([np.nan, 0, 0, 0]), np.random.default_rng(0))

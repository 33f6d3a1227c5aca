"""Moving circles predicted over the samplers' horizon: the compiled MPPI, SAIS, candidate and
safe-MPPI kernels evaluate rollout step k (the state x_{k+1}) in the scene predicted to
(k + 1) dt and equal their twins per element; a sample that stays where it is crashes into a
circle heading for it (predicted) though not into the circle where it is now; a new scene
(other velocities) builds nothing; models without moving circles build the kernels they built
before prediction existed."""

from __future__ import annotations

from dataclasses import replace

import casadi as ca
import numpy as np
import pytest

import workbench as wb
import workbench.sampling.kernels.safe as safe
import workbench.sampling.kernels.specs as specs
import workbench.sampling.kernels.vocabulary as vocabulary
from workbench.problem.scene_kinds import MovingCircle
from workbench.problem.scene_layout import SceneLayout
from workbench.sampling.kernels.constants import SamplerConstants
from workbench.sampling.kernels.library import library_sources
from workbench.sampling.kernels.safe import safe_spec
from workbench.sampling.methods.sampler import SafeOptions, SafeSampler
from workbench.sampling.methods.twin import safe_twin
from workbench.sampling.sampler import Sampler
from workbench.sampling.samples import Rollout
from workbench.sampling.twin import mppi_twin, sais_twin, sample_major

LAYOUT = SceneLayout.of(circles=1, moving=3)
DT, T, N = 0.05, 24, 64
# circle 0 heads for the origin and reaches it at t = 1.25 s - 0.4 / 2 = 1.05 s (step 20), after
# the horizon's start; circle 1 is static; slot 2 is unused (inert)
HEADING = MovingCircle((2.5, 0.0), 0.4, (-2.0, 0.0))
SCENE = [wb.Circle((-1.5, 1.5), 0.3), HEADING, MovingCircle((0.0, -1.2), 0.3, (0.0, 0.0))]


def _problem(gamma: float = 0.0):
    model = wb.double_integrator(dt=DT, scene_layout=LAYOUT, obstacles=SCENE, u_limit=4.0)
    emb = wb.embed_barrier(model, wb.BarrierOptions(gamma=gamma))
    x, g = emb.x, ca.SX.sym("goal", emb.nx)
    e = x[:2] - g[:2]
    return wb.SamplingProblem.from_costs(emb, q=ca.dot(e, e), phi=10 * ca.dot(e, e), p=g)


def _consts(sp, scene, sigma=0.6):
    return SamplerConstants(sigma=np.full(2, sigma), lam=1.0, nu_mix=0.0,
                            u_min=sp.model.u_min, u_max=sp.model.u_max, crash_cost=1e3,
                            p=np.zeros(sp.nx), alpha=50.0,
                            scene=sp.model.scene_vector(scene))


@pytest.fixture(scope="module")
def setup():
    sp = _problem()
    sampler = Sampler(sp, backend="compiled")
    return sp, sampler


def _close(a, b, rtol=1e-12):
    a, b = np.asarray(a, float), np.asarray(b, float)
    assert a.shape == b.shape
    err = np.abs(a - b) / np.maximum(np.maximum(np.abs(a), np.abs(b)), 1.0)
    assert np.all(err <= rtol), float(err.max())


def _start(sp):
    return sp.model.lift(np.zeros(4), sp.model.scene_value)


def test_predicted_scene_moves_only_the_moving_centres():
    v = LAYOUT.vector(SCENE)
    s, t = ca.SX.sym("s", LAYOUT.size), ca.SX.sym("t")
    f = ca.Function("f", [s, t], [LAYOUT.predicted_sx(s, t)])
    for tt in (0.0, 0.35, -0.05):
        got = np.asarray(f(v, tt)).ravel()
        np.testing.assert_array_equal(got, LAYOUT.predicted(v, tt))
        want = v.copy()
        want[3:5] += tt * np.array([-2.0, 0.0])  # the heading circle; the inert slot stays
        np.testing.assert_allclose(got, want, rtol=1e-15, atol=0)
    still = SceneLayout.of(circles=2, halfspaces=1)
    assert not still.moves and still.predicted_sx(s[:still.size], t) is not None


def test_step_times_are_those_of_the_next_states(setup):
    sp, _ = setup
    np.testing.assert_allclose(vocabulary.step_times(sp, 3)["t"].ravel(),
                               [DT, 2 * DT, 3 * DT], rtol=1e-15)
    still = wb.embed_barrier(wb.double_integrator(obstacles=(wb.Circle((1, 1), 0.3),)))
    assert vocabulary.step_times(wb.navigation_costs(still), 3) == {}


def test_kernels_equal_their_twins_and_predict(setup):
    sp, sampler = setup
    lib = sampler.lib
    c = _consts(sp, SCENE, sigma=4.0)
    x0 = _start(sp)
    U = np.zeros((T, 2))
    seed = 11
    Z = sample_major(lib.normals(N, T, 2, seed))
    # a sample with no noise stays at the origin: the heading circle reaches it
    Z[0] = 0.0
    z_lane = np.ascontiguousarray(np.transpose(Z, (1, 2, 0)))
    k = lib.mppi
    out = k(k.carry.pack(1, x=x0), n=N, consts=c.kernel_consts(),
            time_in={"u": U, **vocabulary.step_times(sp, T)}, noise=z_lane)
    r = k.result.unpack(out.result)
    ref = mppi_twin(sp, np.tile(x0, (N, 1)), U, Z, c, model_backend="casadi")
    _close(r["S"], ref["S"])
    np.testing.assert_array_equal(r["crashed"] > 0, ref["crashed"])
    _close(sample_major(out.lane_out[0]), ref["v"])
    assert ref["crashed"][0] and 0 < ref["crashed"].sum() < N
    # the same sample in the present scene (velocities zeroed): no crash
    still = [SCENE[0], MovingCircle(HEADING.center, HEADING.radius, (0.0, 0.0)), SCENE[2]]
    ref0 = mppi_twin(sp, np.tile(x0, (N, 1)), U, Z, _consts(sp, still, sigma=4.0),
                     model_backend="casadi")
    assert not ref0["crashed"][0]
    # SAIS (real and nominal systems) and the strided candidates
    K = np.random.default_rng(5).normal(0, 0.5, (T, 2, sp.nx))
    xs0 = x0 + np.array([0.05, -0.05, 0, 0, 0])
    xs0[4:] = sp.model.lift(xs0[:4], sp.model.scene_value)[4:]
    b = sampler.sais(x0, xs0, U, K, N, c, seed)
    Zs = sample_major(lib.normals(N, T, 2, seed))
    rs = sais_twin(sp, np.tile(x0, (N, 1)), np.tile(xs0, (N, 1)), U, K, Zs, c,
                   model_backend="casadi")
    for f in ("S_nom", "S_real", "S_state_nom", "S_hat", "LR"):
        _close(getattr(b, f), rs[f])
    np.testing.assert_array_equal(b.crashed_real, rs["crashed_real"])
    np.testing.assert_array_equal(b.crashed_nom, rs["crashed_nom"])
    _close(sample_major(b.v_real), rs["v_real"])
    starts = np.tile(x0, (N, 1))
    stride = (np.arange(N) % 2).astype(float)
    got = sampler.candidates(starts, U + 0.3, stride, c, seed)
    U_next = np.vstack([U[1:], U[-1:]]) + 0.3
    U_lane = np.where(stride[:, None, None] > 0, U_next[None], U[None] + 0.3)
    Zc = sample_major(lib.normals(N, T, 2, seed))
    _close(got, mppi_twin(sp, starts, U_lane, Zc, c, model_backend="casadi",
                          delay=stride)["S"])


def test_safe_kernel_equals_its_twin_with_moving_circles(setup):
    sp, _ = setup
    safe = SafeSampler(sp, backend="compiled")
    c = _consts(sp, SCENE, sigma=1.5)
    x0 = _start(sp)
    U = np.tile([0.5, 0.0], (T, 1))
    for opts in (SafeOptions(project=True, w_dcbf=2.0, gamma=0.3),
                 SafeOptions(project=False, w_dcbf=1.0, gamma=0.5)):
        b = safe.batch(x0, U, N, c, opts, seed=3)
        Z = sample_major(safe.lib.normals(N, T, 2, 3))
        ref = safe_twin(sp, np.tile(x0, (N, 1)), U, Z, c, opts.project, opts.w_dcbf,
                        opts.gamma, model_backend="casadi")
        _close(b.S, ref["S"])
        _close(b.dcbf, ref["dcbf"])
        _close(sample_major(b.v), ref["v"])
        np.testing.assert_array_equal(b.crashed, ref["crashed"])
        np.testing.assert_array_equal(b.projected, ref["projected"])
        assert b.crashed.any() or not opts.project


def test_a_new_scene_builds_nothing(setup):
    sp, sampler = setup
    x0 = _start(sp)
    U = np.zeros((T, 2))
    sampler.mppi(x0, U, N, _consts(sp, SCENE), seed=1)
    before = wb.build_counts()
    other = [wb.Circle((1.0, 1.0), 0.5), MovingCircle((-2.0, 0.0), 0.5, (1.5, 0.5)),
             MovingCircle((0.0, 2.0), 0.2, (0.0, -1.0))]
    a = sampler.mppi(x0, U, N, _consts(sp, other), seed=1)
    b = sampler.mppi(x0, U, N, _consts(sp, SCENE), seed=1)
    assert wb.build_counts() == before
    assert not np.array_equal(a.S, b.S)


def test_barrier_with_gamma_sees_the_present_state_where_the_circles_were():
    """gamma != 0: the dynamics' scene is x_{k+1}'s; the present-state term sees c - v dt."""
    sp = _problem(gamma=0.4)
    v = sp.model.scene_vector(SCENE)
    x = sp.model.lift(np.array([1.2, 0.1, 0.5, 0.0]), LAYOUT.predicted(v, 0.0))
    u = np.array([0.3, -0.2])
    got = np.asarray(sp.functions()["dyn"](x, u, LAYOUT.predicted(v, DT))).ravel()
    phys = x[:4] + DT * np.r_[x[2:4], u]  # the Euler double integrator
    h_next = LAYOUT.numpy_margins(phys[:2], LAYOUT.predicted(v, DT))[0]
    h_now = LAYOUT.numpy_margins(x[:2], v)[0]
    beta = np.sum(1.0 / h_next) - 0.4 * (x[4] - np.sum(1.0 / h_now))
    _close(got[:4], phys)
    _close(got[4], beta, rtol=1e-12)


def test_models_without_moving_circles_build_the_kernels_they_built_before(monkeypatch):
    """Their kernels take no time input t, and their source is what it is with prediction
    switched off entirely."""
    circles = wb.navigation_costs(wb.embed_barrier(wb.double_integrator(
        obstacles=(wb.Circle((1, 1), 0.3), wb.Circle((2, 0), 0.4)))))
    still = _still_layout_problem()
    before = {id(sp): (library_sources(sp)[2], library_sources(sp, precision="float32")[2],
                       safe_spec(sp).step.name_in()) for sp in (circles, still)}
    for sp in (circles, still):
        assert "t" not in library_sources(sp)[1][0].step.name_in()
    assert "t" in library_sources(_problem())[1][0].step.name_in()
    for mod in (specs, safe):
        monkeypatch.setattr(mod, "time_symbol", lambda sp: None)
    for sp in (circles, still):
        assert before[id(sp)] == (library_sources(sp)[2],
                                  library_sources(sp, precision="float32")[2],
                                  safe_spec(sp).step.name_in())


def _still_layout_problem():
    model = wb.double_integrator(scene_layout=SceneLayout.of(circles=1, halfspaces=1),
                                 obstacles=[wb.Circle((1, 1), 0.3)])
    emb = wb.embed_barrier(model)
    x, g = emb.x, ca.SX.sym("goal", emb.nx)
    return wb.SamplingProblem.from_costs(emb, q=ca.dot(x - g, x - g), phi=ca.dot(x - g, x - g),
                                         p=g)


def test_float32_and_diagnostics_kernels_predict_too(setup):
    """The float32 kernels (crash flags those of float64, guard band included) and the SAIS
    diagnostics kernel (trajectories equal the twin's) take the same step times."""
    sp, sampler = setup
    c = _consts(sp, SCENE, sigma=4.0)
    x0 = _start(sp)
    U = np.zeros((T, 2))
    s32 = Sampler(sp, backend="compiled", precision="float32")
    assert s32.precision == "float32"
    b64, b32 = sampler.mppi(x0, U, N, c, seed=9), s32.mppi(x0, U, N, c, seed=9)
    np.testing.assert_array_equal(b32.crashed, b64.crashed)
    assert 0 < b64.crashed.sum() < N
    np.testing.assert_allclose(b32.S, b64.S, rtol=1e-4)
    K = np.zeros((T, 2, sp.nx))
    d = sampler.sais(x0, x0, U, K, N, c, seed=9, diagnostics=True)
    Z = sample_major(sampler.lib.normals(N, T, 2, 9))
    ref = sais_twin(sp, np.tile(x0, (N, 1)), np.tile(x0, (N, 1)), U, K, Z, c,
                    model_backend="casadi", pure_costs=True)
    _close(sample_major(d.X), ref["X"])
    np.testing.assert_array_equal(d.crashed_real, ref["crashed_real"])


def test_recorded_sample_trajectories_step_in_the_predicted_scenes(setup):
    sp, _ = setup
    rollout = Rollout(sp)
    assert rollout.lib is None  # the compiled rollout holds one scene
    V = np.random.default_rng(6).normal(0, 2.0, (3, T, 2))
    x0 = _start(sp)
    X = rollout(x0, V, sp.model.scene_value)
    for i in range(3):
        np.testing.assert_allclose(X[i], sp.problem.rollout(x0, V[i]), rtol=1e-12, atol=0)


@pytest.mark.parametrize("gamma", [0.0, 0.4])
def test_numpy_and_casadi_twins_predict_alike(gamma):
    """The plain-NumPy navigation twin (moving circles predicted per step, x_k's barrier term
    at c - v dt when gamma != 0) equals the CasADi one per element."""
    from workbench.sampling.twin_model import NumpyModelTwin, model_twin

    model = wb.double_integrator(dt=DT, scene_layout=LAYOUT, obstacles=SCENE, u_limit=4.0)
    sp = wb.navigation_costs(wb.embed_barrier(model, wb.BarrierOptions(gamma=gamma)))
    assert isinstance(model_twin(sp, N, sp.model.scene_value), NumpyModelTwin)
    c = _consts(sp, SCENE, sigma=4.0)
    c = replace(c, p=sp.model.lift(np.array([2.0, 0.0, 0.0, 0.0]), sp.model.scene_value))
    Z = np.random.default_rng(8).standard_normal((N, T, 2))
    x0 = np.tile(_start(sp), (N, 1))
    a = mppi_twin(sp, x0, np.zeros((T, 2)), Z, c)
    b = mppi_twin(sp, x0, np.zeros((T, 2)), Z, c, model_backend="casadi")
    _close(a["X"], b["X"])
    _close(a["S"], b["S"])
    np.testing.assert_array_equal(a["crashed"], b["crashed"])
    assert 0 < a["crashed"].sum() < N

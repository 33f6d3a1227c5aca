"""Float32 sampling far from the origin and towards a far goal: per-sample crash decisions and
the applied control equal float64's with the map shifted by 0, 1e5 and 4e6 m (UTM-sized
coordinates); a cost beyond float32's range is recomputed in float64 and counted; a goal too
far for float32 to resolve, and a problem float32 cannot run relative to the current state far
from the origin, are refused, naming the value.

Without the local frame (a broken copy that leaves the coordinates as given) float32 loses
46 of 1001 crash decisions at 1e5 m and all 121 at 4e6 m on this case, and its applied control
points elsewhere: the shift tests fail on it (test_without_the_local_frame_...).

Tolerance of the applied control: relative per element, |a - b| <= RTOL max(|a|, |b|, 1);
measured 6e-6 at every shift, RTOL = 1e-4.
"""

from __future__ import annotations

from dataclasses import replace

import casadi as ca
import numpy as np
import pytest

from workbench.problem.barrier import embed_barrier
from workbench.problem.models import double_integrator, single_integrator
from workbench.problem.obstacles import Circle
from workbench.sampling.kernels.constants import SamplerConstants
from workbench.sampling.mppi import MPPI, MPPIConfig
from workbench.sampling.problem import SamplingProblem, goal_costs, navigation_costs
from workbench.sampling.sampler import Sampler
from workbench.sampling.weights import importance_weights, weighted_controls

BASE = ((2.0, 2.0, 0.8), (3.5, 1.0, 0.5), (1.0, 3.2, 0.6))
SHIFTS = (0.0, 1e5, 4e6)
N, T = 1001, 30
LAM = 1.3
RTOL = 1e-4


def rel(a, b) -> np.ndarray:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return np.abs(a - b) / np.maximum(np.maximum(np.abs(a), np.abs(b)), 1.0)


@pytest.fixture(scope="module")
def setup():
    """One model for every shift (the circles are run-time inputs; two inert slots too)."""
    obst = tuple(Circle((x, y), r) for x, y, r in BASE)
    model = embed_barrier(double_integrator(obstacles=obst, u_limit=5.0, scene_capacity=5))
    sp = navigation_costs(model)
    s32, s64 = Sampler(sp, "compiled", "float32"), Sampler(sp, "compiled")
    if s32.precision != "float32":
        pytest.skip("no C compiler")
    return model, sp, s32, s64


def case(model, shift: float, goal=(4.0, 4.0)):
    """The scene, goal and starts shifted by ``shift`` m in x and y: real and nominal starts
    0.9 m off the line through the first circle, heading along it at 2 m/s (some samples
    hit the circle, some graze it)."""
    scene = model.scene_vector([(x + shift, y + shift, r) for x, y, r in BASE])
    side = np.array([-1.0, 1.0]) / np.sqrt(2.0)
    heading = np.array([1.0, 1.0]) * np.sqrt(2.0)
    x_phys = np.array([*(1.0 + shift + 0.9 * side), *heading])
    xs_phys = np.array([*(0.95 + shift + 0.9 * side), *(heading + np.array([0.1, -0.1]))])
    goal_phys = np.array([goal[0] + shift, goal[1] + shift, 0.0, 0.0])
    c = SamplerConstants(sigma=np.array([3.0, 2.4]), lam=LAM, nu_mix=0.1, u_min=model.u_min,
                         u_max=model.u_max, crash_cost=1e6, p=model.lift(goal_phys, scene),
                         scene=scene, alpha=np.inf)
    return {"x0": model.lift(x_phys, scene), "xs0": model.lift(xs_phys, scene), "c": c,
            "x_phys": x_phys, "goal": goal_phys, "scene": scene}


def plan(T_: int = T) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(2026)
    U = rng.normal(0.0, 2.0, (T_, 2))
    K = np.zeros((T_, 2, 5))
    K[:, 0, 0] = K[:, 1, 1] = -2.0
    K[:, 0, 2] = K[:, 1, 3] = -1.5
    return U, K + rng.normal(0.0, 0.3, K.shape)


def applied(b_v, S) -> np.ndarray:
    """The first control the importance weights of the costs S give."""
    return weighted_controls(b_v, importance_weights(S, LAM).w)[0]


def sais_mismatches(setup, shift: float) -> dict[str, float]:
    """Crash flags that differ between float32 and float64 (SAIS real and nominal, MPPI), the
    largest relative error of the applied first controls and the share of candidate costs
    within RTOL of float64's."""
    model, _, s32, s64 = setup
    k = case(model, shift)
    U, K = plan()
    b32 = s32.sais(k["x0"], k["xs0"], U, K, N, k["c"], 7)
    b64 = s64.sais(k["x0"], k["xs0"], U, K, N, k["c"], 7)
    m32, m64 = s32.mppi(k["x0"], U, N, k["c"], 11), s64.mppi(k["x0"], U, N, k["c"], 11)
    for flags in (b64.crashed_real, b64.crashed_nom, m64.crashed):
        assert 0 < flags.sum() < N  # crash decisions to get right
    u = [rel(applied(b32.v_real, b32.S_real), applied(b64.v_real, b64.S_real)).max(),
         rel(applied(b32.v_nom, b32.S_nom), applied(b64.v_nom, b64.S_nom)).max(),
         rel(applied(m32.v, m32.S), applied(m64.v, m64.S)).max()]
    # candidates: per-sample starts 0.3 m apart at most, the frame's origin the first one
    starts = np.tile(k["x0"], (N, 1))
    starts[:, 1] += np.linspace(-0.3, 0.3, N)
    starts = np.array([model.lift(s[:4], k["scene"]) for s in starts])
    stride = (np.arange(N) % 2).astype(float)
    cand = rel(s32.candidates(starts, U, stride, k["c"], 9),
               s64.candidates(starts, U, stride, k["c"], 9))
    return {"crashed_real": int(np.sum(b32.crashed_real != b64.crashed_real)),
            "crashed_nom": int(np.sum(b32.crashed_nom != b64.crashed_nom)),
            "crashed_mppi": int(np.sum(m32.crashed != m64.crashed)), "u": float(max(u)),
            "candidates_within": float(np.mean(cand <= RTOL))}


@pytest.mark.parametrize("shift", SHIFTS)
def test_crash_decisions_and_applied_control_equal_float64_far_from_the_origin(setup, shift):
    got = sais_mismatches(setup, shift)
    assert got["crashed_real"] == got["crashed_nom"] == got["crashed_mppi"] == 0, got
    assert got["u"] <= RTOL, got
    assert got["u"] > 0.0, got  # really float32 (float64 agrees bitwise)
    # candidate costs (no crash flags returned): those of samples passing close to a circle
    # carry float32's error amplified by the barrier (up to 8e-4 measured), the rest 3e-6
    assert got["candidates_within"] >= 0.9, got


@pytest.mark.parametrize("shift", SHIFTS)
def test_mppi_controller_step_matches_float64_far_from_the_origin(setup, shift):
    """The control the controller applies: same sign and within RTOL of float64's."""
    model, sp = setup[0], setup[1]
    k = case(model, shift)
    u = {}
    for p in ("float32", "float64"):
        cfg = MPPIConfig(n_samples=N, horizon=T, sigma=(3.0, 2.4), lam=LAM, precision=p)
        ctrl = MPPI(sp, k["goal"], cfg)
        ctrl.set_scene(k["scene"])
        _, u[p], info = ctrl.step(ctrl.initial_state(), k["x_phys"], np.random.default_rng(5))
        assert info.valid_weights and 0 < info.n_crashed < N
    big = np.abs(u["float64"]) > 1e-2  # (a component near 0 may take either sign)
    assert big.any() and np.array_equal(np.sign(u["float32"][big]), np.sign(u["float64"][big]))
    assert rel(u["float32"], u["float64"]).max() <= RTOL, u


def test_without_the_local_frame_crash_decisions_differ(setup, monkeypatch):
    """A broken copy that leaves the coordinates as given (frame origin 0) fails the test
    above at 1e5 m and 4e6 m: the comparison detects a missing translation."""
    from workbench.sampling.frame import LocalFrame

    monkeypatch.setattr(LocalFrame, "origin", lambda self, carry: np.zeros(len(self.state)))
    monkeypatch.setattr("workbench.sampling.sampler.check_goal", lambda frame, consts: None)
    for shift in SHIFTS[1:]:
        got = sais_mismatches(setup, shift)
        assert got["crashed_real"] + got["crashed_mppi"] > 0 and got["u"] > RTOL, got


def test_the_navigation_problem_runs_in_a_local_frame(setup):
    from workbench.sampling.frame import LocalFrame

    s32, s64 = setup[2], setup[3]
    assert s32.frame == LocalFrame(state=(0, 1), param=(0, 1), scene=True)
    assert s64.frame is None  # float64 runs as given


def overflow_case(model, vg: float = 1e20):
    """A goal velocity of 1e20 m/s: the terminal cost S (v - v_g)^2 ~ 1e40 is beyond float32's
    range (3.4e38), within float64's. (Not a position: the goal-distance check does not
    apply.)"""
    k = case(model, 0.0)
    g = np.array([4.0, 4.0, vg, 0.0])
    k["goal"], k["c"] = g, replace(k["c"], p=model.lift(g, k["scene"]))
    return k


def test_a_cost_beyond_float32_range_is_recomputed_in_float64(setup):
    """Every float32 cost overflows; the samples are recomputed in float64 (their results
    exactly float64's), and the controller moves as the float64 one does instead of keeping
    its plan (no valid weight)."""
    model, sp, s32, s64 = setup
    k = overflow_case(model)
    U, _ = plan()
    b32, b64 = s32.mppi(k["x0"], U, N, k["c"], 3), s64.mppi(k["x0"], U, N, k["c"], 3)
    assert np.isfinite(b64.S).all() and b64.S.min() > 3.4e38
    assert np.array_equal(b32.S, b64.S) and np.array_equal(b32.v, b64.v)
    u = {}
    for p in ("float32", "float64"):
        cfg = MPPIConfig(n_samples=N, horizon=T, sigma=(3.0, 2.4), lam=LAM, precision=p)
        ctrl = MPPI(sp, k["goal"], cfg)
        _, u[p], info = ctrl.step(ctrl.initial_state(), k["x_phys"], np.random.default_rng(5))
        assert info.valid_weights, p
    assert np.array_equal(u["float32"], u["float64"]) and np.any(u["float32"] != 0.0)


def test_overflowed_samples_are_counted(setup):
    model, _, s32, _ = setup
    U, _ = plan()
    g0 = s32.guard.overflowed
    k = overflow_case(model, 1e10)  # 1e20: finite in float32
    s32.mppi(k["x0"], U, N, k["c"], 3)
    assert s32.guard.overflowed == g0
    k = overflow_case(model)
    s32.mppi(k["x0"], U, N, k["c"], 3)
    assert s32.guard.overflowed - g0 == N
    assert s32.guard.fractions()["overflowed"] > 0


@pytest.mark.parametrize("shift", SHIFTS)
def test_a_goal_float32_cannot_resolve_is_refused(setup, shift):
    """A goal 1e4 m from the start runs and matches float64; one 1e6 m away (float32 spacing
    0.06 m there; the applied control measured off by 1.4 at 1e7 m) is refused, naming the
    value and the limit, wherever the map lies."""
    model, _, s32, s64 = setup
    U, _ = plan()
    near = case(model, shift, goal=(1e4, 4.0))
    a, b = s32.mppi(near["x0"], U, N, near["c"], 4), s64.mppi(near["x0"], U, N, near["c"], 4)
    assert np.array_equal(a.crashed, b.crashed)
    assert rel(applied(a.v, a.S), applied(b.v, b.S)).max() <= RTOL
    far = case(model, shift, goal=(4.0, 1e6))
    s64.mppi(far["x0"], U, N, far["c"], 4)
    with pytest.raises(ValueError, match=r"goal \(position relative to the state\) = "
                                         r"99999\d\.\d+ is invalid: must be at most 100000 m "
                                         r"per axis for precision 'float32'.*0\.062 m"):
        s32.mppi(far["x0"], U, N, far["c"], 4)


def test_a_problem_that_is_not_translation_invariant_has_no_local_frame():
    """Costs of absolute positions, or circles compiled into the model: no frame."""
    from workbench.sampling.frame import local_frame

    m = single_integrator(obstacles=(Circle((2.0, 2.0), 0.5),))
    assert local_frame(goal_costs(m, Q=(1.0, 1.0), S=(1.0, 1.0))) is not None
    x, g = m.x, ca.SX.sym("g", 2)
    absolute = SamplingProblem.from_costs(m, ca.sumsqr(x - g) + 1e-3 * x[0] ** 2,
                                          ca.sumsqr(x - g), g)
    assert local_frame(absolute) is None
    baked = single_integrator(obstacles=(Circle((2.0, 2.0), 0.5),), runtime_obstacles=False)
    assert local_frame(goal_costs(baked, Q=(1.0, 1.0), S=(1.0, 1.0))) is None


def test_float32_far_from_the_origin_is_refused_without_a_local_frame():
    """Circles compiled in: float32 runs near the origin and is refused at 1e5 m, the error
    naming the value and the limit; float64 runs there."""
    model = single_integrator(obstacles=(Circle((2.0, 2.0), 0.5),), runtime_obstacles=False)
    sp = goal_costs(model, Q=(1.0, 1.0), S=(1.0, 1.0))
    s32, s64 = Sampler(sp, "compiled", "float32"), Sampler(sp, "compiled")
    if s32.precision != "float32":
        pytest.skip("no C compiler")
    c = SamplerConstants(sigma=np.array([1.0, 1.0]), lam=1.0, nu_mix=0.0, u_min=model.u_min,
                         u_max=model.u_max, crash_cost=1e6, p=np.array([4.0, 4.0]))
    U = np.zeros((10, 2))
    s32.mppi(np.array([0.5, 0.5]), U, 64, c, 1)
    far = np.array([1e5, 0.5])
    s64.mppi(far, U, 64, c, 1)
    with pytest.raises(ValueError, match=r"x \(position entries\) = 100000\.? is invalid: must be "
                                         r"at most 100 in magnitude for precision 'float32'"):
        s32.mppi(far, U, 64, c, 1)
    with pytest.raises(ValueError, match=r"x \(position entries\).*float32"):
        s32.candidates(np.tile(far, (8, 1)), U, np.zeros(8), c, 1)


def test_circles_far_from_the_origin_are_refused_without_a_local_frame(setup):
    """The circle check of a problem without a frame: a used circle beyond 100 m is refused,
    an inert slot (radius 0, far away by design) is not."""
    from workbench.sampling.frame import check_coordinates

    model, sp = setup[0], setup[1]
    near, far = case(model, 0.0), case(model, 1e5)
    check_coordinates(sp, {"x": near["x0"]}, near["scene"])  # two inert slots at 1e8
    with pytest.raises(ValueError, match=r"scene \(circle centres\) = 100003\.5 is invalid: "
                                         r"must be at most 100 m from the origin"):
        check_coordinates(sp, {"x": near["x0"]}, far["scene"])


def test_cost_weights_beyond_float32_range_are_refused_at_load():
    """Goal weights 1e37 (a cost of 4e39 at the load check's points): the float32 library is
    refused, the error saying that float32's range is the reason."""
    from workbench.sampling.kernels.verify import KernelMismatch

    sp = goal_costs(single_integrator(obstacles=(Circle((2.0, 2.0), 0.5),)), Q=(1e37, 1e37),
                    S=(1e37, 1e37))
    with pytest.warns(RuntimeWarning, match="rebuilding"), pytest.raises(
            KernelMismatch, match=r"beyond float32's range 3\.4e38.*use 'float64'"):
        if Sampler(sp, "compiled", "float32").precision != "float32":
            pytest.skip("no C compiler")


def test_reused_frame_constants_follow_the_origin(setup):
    """The buffers the sampler reuses hold what LocalFrame.consts computes afresh, for every
    origin in turn, and another thread gets buffers of its own."""
    import threading

    from workbench.sampling.frame import FrameConsts

    model, s32 = setup[0], setup[2]
    fr, kc = s32.frame, case(model, 4e6)["c"].kernel_consts()
    fc = FrameConsts(fr)
    rng = np.random.default_rng(8)
    mine = None
    for o in 4e6 + rng.normal(0.0, 3.0, (4, 2)):
        got, want = fc(kc, o), fr.consts(kc, o)
        assert got.keys() == want.keys()
        assert all(np.array_equal(got[k], want[k]) for k in want)
        assert mine is None or got["p"] is mine  # the same buffer, rewritten
        mine = got["p"]
    other: list = []
    t = threading.Thread(target=lambda: other.append(fc(kc, np.zeros(2))["p"]))
    t.start()
    t.join()
    assert other[0] is not mine and np.array_equal(fc(kc, o)["p"], fr.consts(kc, o)["p"])

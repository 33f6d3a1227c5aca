"""The float32 local frame on a scene of several kinds: the frame moves circles, a half-plane,
capsules and a moving circle with the state (its translation-invariance check passes), so
float32 crash decisions and the applied control equal float64's with the map shifted 1e5 m; a
broken copy that leaves the layout's obstacles where they are fails that. A problem without a
frame refuses obstacles beyond 100 m by their places (unused slots, far by design, are not).
Every float32 result is finite (an unused capsule slot stays a segment in float32), so no
sample is recomputed in float64 for that.

Tolerance of the applied control as in the circle tests: relative per element, 1e-4.
"""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from workbench.problem.barrier import embed_barrier
from workbench.problem.models import double_integrator
from workbench.problem.obstacles import Circle
from workbench.problem.scene_kinds import Capsule, HalfSpace, MovingCircle
from workbench.problem.scene_layout import SceneLayout
from workbench.sampling.frame import FrameConsts, LocalFrame, check_coordinates, local_frame
from workbench.sampling.kernels.constants import SamplerConstants
from workbench.sampling.problem import SamplingProblem, navigation_costs
from workbench.sampling.sampler import Sampler
from workbench.sampling.weights import importance_weights, weighted_controls

LAYOUT = SceneLayout.of(circles=2, halfspaces=1, capsules=2, moving=1)
SCENE = (Circle((2.0, 2.0), 0.6), HalfSpace((0.6, -0.8), -2.5),
         Capsule((2.6, 0.4), (3.6, 1.4), 0.3), MovingCircle((1.0, 3.2), 0.5, (0.4, 0.0)))
N, T, LAM, RTOL = 1001, 30, 50.0, 1e-4  # LAM: weights spread over many samples


def rel(a, b) -> np.ndarray:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return np.abs(a - b) / np.maximum(np.maximum(np.abs(a), np.abs(b)), 1.0)


@pytest.fixture(scope="module")
def setup():
    model = embed_barrier(double_integrator(scene_layout=LAYOUT, obstacles=SCENE, u_limit=5.0))
    sp = navigation_costs(model)
    s32, s64 = Sampler(sp, "compiled", "float32"), Sampler(sp, "compiled")
    if s32.precision != "float32":
        pytest.skip("no C compiler")
    return model, sp, s32, s64


def shifted(model, shift: float):
    """Scene, start and constants with the map moved by ``shift`` m in x and y."""
    o = np.array([shift, shift])
    scene = LAYOUT.translate(model.scene_value, -o)
    x = np.array([1.0 + shift - 0.64, 1.0 + shift + 0.64, np.sqrt(2.0), np.sqrt(2.0)])
    goal = np.array([4.0 + shift, 4.0 + shift, 0.0, 0.0])
    c = SamplerConstants(sigma=np.array([3.0, 2.4]), lam=LAM, nu_mix=0.1, u_min=model.u_min,
                         u_max=model.u_max, crash_cost=1e6, p=model.lift(goal, scene),
                         scene=scene)
    return model.lift(x, scene), c


def mismatches(setup, shift: float) -> tuple[int, float]:
    """Crash flags that differ between float32 and float64 and the largest relative error of
    the applied first control."""
    model, _, s32, s64 = setup
    x0, c = shifted(model, shift)
    U = np.random.default_rng(2026).normal(0.0, 2.0, (T, 2))
    overflowed = s32.guard.overflowed
    b32, b64 = s32.mppi(x0, U, N, c, 11), s64.mppi(x0, U, N, c, 11)
    assert 0 < b64.crashed.sum() < N
    assert s32.guard.overflowed == overflowed  # every float32 result finite: none redone
    u32 = weighted_controls(b32.v, importance_weights(b32.S, LAM).w)[0]
    u64 = weighted_controls(b64.v, importance_weights(b64.S, LAM).w)[0]
    return int(np.sum(b32.crashed != b64.crashed)), float(rel(u32, u64).max())


def test_the_layout_problem_runs_in_a_local_frame_that_moves_every_kind(setup):
    _, sp, s32, s64 = setup
    assert s32.frame == LocalFrame((0, 1), (0, 1), True, LAYOUT) == local_frame(sp)
    assert s64.frame is None


@pytest.mark.parametrize("shift", [0.0, 1e5])
def test_float32_equals_float64_with_the_map_far_from_the_origin(setup, shift):
    wrong, u = mismatches(setup, shift)
    assert wrong == 0 and 0 < u <= RTOL, (wrong, u)


def test_a_frame_that_leaves_the_layout_in_place_fails_the_comparison(setup, monkeypatch):
    monkeypatch.setattr(LocalFrame, "scene_at", lambda self, scene, shift: np.array(scene))
    wrong, u = mismatches(setup, 1e5)
    assert wrong > 0 or u > RTOL, (wrong, u)


def test_reused_frame_constants_follow_the_origin(setup):
    model, s32 = setup[0], setup[2]
    fr, kc = s32.frame, shifted(model, 1e5)[1].kernel_consts()
    fc = FrameConsts(fr)
    for o in 1e5 + np.random.default_rng(8).normal(0.0, 3.0, (3, 2)):
        got, want = fc(kc, o), fr.consts(kc, o)
        assert all(np.array_equal(got[k], want[k]) for k in want)


def test_obstacles_far_from_the_origin_are_refused_without_a_local_frame():
    model = double_integrator(scene_layout=LAYOUT, obstacles=SCENE)
    x, g = model.x, ca.SX.sym("g", 4)
    absolute = SamplingProblem.from_costs(model, ca.sumsqr(x - g) + 1e-3 * x[0] ** 2,
                                          ca.sumsqr(x - g), g)
    assert local_frame(absolute) is None
    x0 = np.array([0.5, 0.5, 0.0, 0.0])
    check_coordinates(absolute, {"x": x0}, model.scene_value)  # unused slots at 1e8 pass
    far = model.scene_vector([Capsule((0.0, 0.0), (150.0, 0.0), 0.5)])
    with pytest.raises(ValueError, match=r"scene \(obstacle positions\) = 150\.? is invalid: "
                                         r"must be at most 100 m from the origin"):
        check_coordinates(absolute, {"x": x0}, far)

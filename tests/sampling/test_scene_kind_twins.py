"""Compiled margins, barrier states and crash flags of every scene kind against the NumPy twin.

For each primitive (circles, moving circles at t = 0, half-planes and capsules in the plane;
spheres, half-spaces and capsules in space with a 3-D double integrator; the signed-distance
grid) the generated C of the model's margins and barrier-embedded dynamics, evaluated on states
that lie exactly on each boundary, inside each obstacle, beyond the capsules' ends (the clamped
end caps), on the grid's nodes, cell edges and beyond the grid, and at random, equals the NumPy
twin (:class:`~workbench.sampling.twin_model.NumpyNavigation`, margins from
:meth:`~workbench.problem.scene_layout.SceneLayout.numpy_margins`) per element to 1e-12
relative (unused slots included); the crash flags are equal. The sampler kernels' crash flags
and costs, and the safe-sampling kernel's (DCBF projection and cost), equal their twins'
rollouts fed the same noise. The tests count that the states reach every branch.

The safe-sampling kernel of a grid model (its DCBF projection needs the grid's derivative,
which the C emitter does not write) falls back to the CasADi virtual machine (a
RuntimeWarning): that one comparison is skipped then, with the reason.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import casadi as ca
import numpy as np
import pytest

import workbench as wb
from workbench.codegen import build_library
from workbench.problem.models import Model
from workbench.problem.obstacles import Circle
from workbench.problem.scene_kinds import Capsule, HalfSpace, MovingCircle, Sphere
from workbench.problem.scene_layout import SceneLayout
from workbench.problem.sdf_grid import SignedDistanceGrid
from workbench.sampling.kernels.constants import SamplerConstants
from workbench.sampling.methods.sampler import SafeOptions, SafeSampler
from workbench.sampling.methods.twin import safe_twin
from workbench.sampling.problem import SamplingProblem, navigation_costs
from workbench.sampling.sampler import Sampler
from workbench.sampling.twin import mppi_twin
from workbench.sampling.twin_model import NumpyModelTwin, model_twin

RTOL = 1e-12  # per element, relative to max(|a|, |b|, 1) (m or m^2 below 1)
# The kernels' costs sum T terms in another order than the twin (as in the sampler kernel
# tests): 1e-10 relative; their crash flags must be equal.
KERNEL_RTOL = 1e-10
N, T = 125, 30


def rel_err(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    assert a.shape == b.shape and np.all(np.isfinite(a)) and np.all(np.isfinite(b))
    return float(np.max(np.abs(a - b) / np.maximum(np.maximum(np.abs(a), np.abs(b)), 1.0)))


# ------------------------------------------------------------------------------- the cases

PLANE = SceneLayout.of(circles=2, halfspaces=2, capsules=2, moving=2)
PLANE_SCENE = (Circle((2.0, 2.0), 0.5), HalfSpace((0.0, 1.0), -1.0),
               HalfSpace((-0.6, -0.8), -6.0), Capsule((3.0, 0.0), (3.0, 1.5), 0.25),
               MovingCircle((0.5, 3.0), 0.5, (0.3, -0.2)))
PLANE_MOVED = (Circle((1.5, 2.5), 0.75), Circle((2.5, 0.5), 0.25), HalfSpace((0.0, 1.0), -0.5),
               Capsule((2.0, 3.0), (3.5, 3.0), 0.5), MovingCircle((0.5, 1.0), 0.5, (0.0, 0.7)))
# exactly on a boundary (squared margins 0 in floating point), inside, beyond the capsule ends
PLANE_POINTS = {
    "boundary": [(2.5, 2.0), (2.0, 1.5), (0.7, -1.0), (3.25, 0.75), (3.0, -0.25), (3.0, 1.75),
                 (1.0, 3.0), (0.5, 2.5), (1.5, 1.0), (2.0, 3.5), (2.5, -1.0), (3.5, 3.5),
                 (3.0, 2.5), (0.0, 1.0), (6.0, 3.0)],
    "inside": [(2.0, 2.0), (3.0, 0.75), (3.1, -0.1), (3.0, 1.6), (0.5, 3.0), (1.0, -1.5),
               (6.0, 4.0)],
    "beyond_ends": [(3.0, -1.0), (3.4, 2.5), (1.0, 3.2), (4.2, 2.9)],
}
SPACE = SceneLayout.of(dim=3, spheres=2, halfspaces=2, capsules=2)
SPACE_SCENE = (Sphere((1.0, 1.0, 1.0), 0.5), HalfSpace((0.0, 0.0, 1.0), 0.0),
               HalfSpace((-1.0, -2.0, -2.0), -9.0), Capsule((2.0, 0.0, 1.0), (2.0, 2.0, 1.0), 0.5))
SPACE_MOVED = (Sphere((0.5, 2.0, 1.5), 0.25), Sphere((2.0, 1.0, 0.5), 0.5),
               HalfSpace((0.0, 0.0, 1.0), -0.5), Capsule((0.0, 0.0, 2.0), (1.0, 0.0, 2.0), 0.25),
               Capsule((1.0, 2.0, 0.0), (1.0, 2.0, 1.0), 0.5))
SPACE_POINTS = {
    "boundary": [(1.5, 1.0, 1.0), (1.0, 1.0, 0.5), (0.3, 0.4, 0.0), (2.5, 1.0, 1.0),
                 (2.0, -0.5, 1.0), (2.0, 2.5, 1.0), (2.0, 1.0, 1.5), (0.5, 2.0, 1.75),
                 (-0.25, 0.0, 2.0), (1.0, 2.5, 0.5), (1.0, 0.0, -0.5)],
    "inside": [(1.0, 1.0, 1.0), (2.0, 1.0, 1.0), (2.1, -0.2, 1.1), (0.5, 0.5, -0.3),
               (3.0, 3.0, 3.0)],
    "beyond_ends": [(2.0, -1.0, 1.2), (2.3, 3.0, 0.8), (-1.0, 0.0, 2.0), (1.0, 2.0, 2.0)],
    "at_crash_margin": [(0.3, 0.4, 1e-6)],  # the floor's margin is exactly eps_h (crashed)
}
GRID_LAYOUT = SceneLayout.of(circles=1, grid=(9, 7))


def sdf(center, radius, origin=(-1.0, -0.5), res=0.5, shape=(9, 7)) -> SignedDistanceGrid:
    xs = origin[0] + np.arange(shape[0]) * res
    ys = origin[1] + np.arange(shape[1]) * res
    d = np.hypot(xs[:, None] - center[0], ys[None, :] - center[1]) - radius
    return SignedDistanceGrid(d, origin, res)


GRID_SCENE = (Circle((3.5, 2.5), 0.5), sdf((1.0, 1.0), 1.0))  # 0 at 4 nodes
GRID_MOVED = (sdf((1.5, 0.5), 0.6, origin=(-0.5, -1.0), res=0.45),)
GRID_POINTS = {  # grid of nodes x = -1 + 0.5 i (i < 9), y = -0.5 + 0.5 j (j < 7)
    "nodes": [(-1.0, -0.5), (3.0, 2.5), (1.0, 1.0), (-1.0, 2.5), (3.0, -0.5), (0.5, 1.5),
              (1.0, 0.0), (2.0, 1.0)],
    "cell_edges": [(0.25, 1.0), (1.0, 0.75), (3.0, 1.25), (-1.0, 0.1), (2.2, 2.5)],
    "inside": [(1.1, 0.9), (0.7, 1.3), (1.6, 1.2)],
    "beyond_grid": [(-2.0, 0.3), (4.5, 1.0), (1.2, -1.7), (0.3, 3.6), (-1.6, -1.2),
                    (4.1, 3.3)],
}


@dataclass(frozen=True)
class Case:
    name: str
    plain: Model
    sp: SamplingProblem
    scenes: tuple[np.ndarray, np.ndarray]
    points: dict[str, np.ndarray]
    X: np.ndarray  # barrier-embedded states (M, nx)
    V: np.ndarray  # controls (M, nu)
    start: np.ndarray  # a physical state heading for an obstacle (kernel rollouts)


def double_integrator_3d(layout: SceneLayout, scene, h_form: str) -> Model:
    """x = [p (3), v (3)], u = a (3), Euler steps of 0.02 s, margins of ``layout``."""
    x, u, dt = ca.SX.sym("x", 6), ca.SX.sym("u", 3), 0.02
    s = layout.symbol()
    return Model.from_expressions(
        "double_integrator_3d", x, u, ca.vertcat(x[:3] + dt * x[3:], x[3:] + dt * u), dt=dt,
        u_min=-5 * np.ones(3), u_max=5 * np.ones(3), h=layout.margins(x[:3], s, h_form),
        position=(0, 1, 2), scene=s, scene_value=list(scene), scene_layout=layout)


def navigation_3d(model: Model) -> SamplingProblem:
    """The navigation costs (assumptions §8.2) in space, with the twin's weights."""
    w = {"Qp": np.ones(3), "Qv": 0.1 * np.ones(3), "q_beta": 1.0,
         "S": np.array([10.0, 10.0, 10.0, 1.0, 1.0, 1.0, 1.0])[:model.nx]}
    x, g = model.x, ca.SX.sym("goal", model.nx)
    ep, v, eb, e = x[:3] - g[:3], x[3:6], x[6:] - g[6:], x - g
    q = ca.dot(w["Qp"] * ep, ep) + ca.dot(w["Qv"] * v, v) + w["q_beta"] * ca.dot(eb, eb)
    return SamplingProblem.from_costs(model, q, ca.dot(w["S"] * e, e), g, weights=w)


def make_case(name: str) -> Case:
    rng = np.random.default_rng({"plane": 1, "space": 2, "grid": 3}[name])
    if name == "space":
        plain = double_integrator_3d(SPACE, SPACE_SCENE, "signed_distance")
        sp, pts, moved = navigation_3d(wb.embed_barrier(plain)), SPACE_POINTS, SPACE_MOVED
        box = ([-0.5, -1.5, -0.5], [3.5, 3.5, 3.0])
        start = np.array([0.2, 0.2, 1.55, 1.4, 1.4, 0.0])
    else:
        layout, scene, pts, moved = ((PLANE, PLANE_SCENE, PLANE_POINTS, PLANE_MOVED)
                                     if name == "plane" else
                                     (GRID_LAYOUT, GRID_SCENE, GRID_POINTS, GRID_MOVED))
        plain = wb.double_integrator(scene_layout=layout, obstacles=scene, u_limit=5.0)
        sp = navigation_costs(wb.embed_barrier(plain))
        box = ([-1.5, -1.5], [5.0, 4.5])
        start = (np.array([0.6, 0.9, 1.4, 1.4]) if name == "plane"
                 else np.array([-0.9, 1.7, 1.8, -0.4]))
    d = plain.scene_layout.dim
    points = {k: np.array(v, dtype=float) for k, v in pts.items()}
    points["random"] = rng.uniform(box[0], box[1], (40, d))
    P = np.concatenate(list(points.values()))
    M = len(P)
    X = np.hstack([P, rng.normal(0.0, 2.0, (M, d)), rng.uniform(0.0, 30.0, (M, 1))])
    V = rng.uniform(-6.0, 6.0, (M, d))  # beyond the control box too: the model does not clip
    scenes = (plain.scene_value, plain.scene_vector(list(moved)))
    return Case(name, plain, sp, scenes, points, X, V, start)


@pytest.fixture(scope="module", params=["plane", "space", "grid"])
def case(request) -> Case:
    return make_case(request.param)


@pytest.fixture(scope="module")
def compiled(case):
    """The generated C of the margins and the barrier-embedded dynamics (cached per case)."""
    m = case.sp.model
    fns = [ca.Function(f"twins_{case.name}_margins", [m.x, m.scene], [m.h]),
           ca.Function(f"twins_{case.name}_dyn", [m.x, m.u, m.scene], [m.x_next])]
    lib = build_library(f"scene_kind_twins_{case.name}", fns)
    if lib is None:
        pytest.skip("no C compiler")
    return (lib.functions[f"twins_{case.name}_margins"].map(len(case.X)),
            lib.functions[f"twins_{case.name}_dyn"].map(len(case.X)))


def the_twin(case: Case, scene: np.ndarray):
    twin = model_twin(case.sp, len(case.X), scene, "numpy")
    assert isinstance(twin, NumpyModelTwin)
    return twin.twin


# ------------------------------------------------------------------------------- the tests


def test_the_states_reach_every_branch(case):
    """On a boundary (a margin exactly 0) and inside (< 0) of every used obstacle; beyond a
    capsule's ends (its clamp at t = 0 and t = 1); the grid's nodes, edges and outside; the
    unused slots' margins about 1e16 (squared) or 1e8 (signed distance) everywhere."""
    layout = case.plain.scene_layout
    H = layout.numpy_margins(case.X[:, :layout.dim], case.scenes[0],
                             "signed_distance" if case.name == "space" else "squared")
    used = [i for i, o in enumerate(_slot_objects(layout, case.scenes[0])) if o is not None]
    for i in used:
        assert np.any(H[:, i] == 0.0) and np.any(H[:, i] < 0.0) and np.any(H[:, i] > 0.0), i
    unused = [i for i in range(H.shape[1]) if i not in used]
    assert unused or case.name == "grid"
    for i in unused:
        assert np.all(H[:, i] > (1e7 if case.name == "space" else 1e15)), i
    for b in layout.blocks():
        if b.kind.name == "capsules":
            S = case.scenes[0][b.start:b.start + b.width]
            d = layout.dim
            a, ab = S[:d], S[d:2 * d] - S[:d]
            t = (case.X[:, :d] - a) @ ab / (ab @ ab)
            assert np.sum(t < 0) >= 2 and np.sum(t > 1) >= 2 and np.sum((t > 0) & (t < 1)) >= 2
    if layout.grid:
        g = np.asarray(case.scenes[0])[layout.grid_start:]
        u = (case.X[:, 0] - g[0]) / g[2]
        v = (case.X[:, 1] - g[1]) / g[2]
        nx, ny = layout.grid
        on_node = (u == np.round(u)) & (v == np.round(v))
        assert on_node.sum() >= 4 and np.any(u == nx - 1) and np.any(v == ny - 1)
        assert np.sum((u == np.round(u)) ^ (v == np.round(v))) >= 3  # on a cell edge only
        assert np.sum((u < 0) | (u > nx - 1) | (v < 0) | (v > ny - 1)) >= 6


def _slot_objects(layout: SceneLayout, v: np.ndarray) -> list:
    """One entry per margin: the slot's row, or None for an unused slot."""
    out: list = []
    for b in layout.blocks():
        S = v[b.start:b.stop].reshape(b.count, b.width)
        out += [None if np.all(r == np.array(b.kind.inert(layout.dim))) else r for r in S]
    if layout.grid:
        out.append(v[layout.grid_start:])
    return out


@pytest.mark.parametrize("which", [0, 1], ids=["own_scene", "new_scene"])
def test_compiled_margins_barrier_states_and_crash_flags_equal_the_twin(case, compiled, which):
    margins, dyn = compiled
    scene = case.scenes[which]
    twin = the_twin(case, scene)
    H = np.asarray(margins(case.X.T, scene)).T
    assert rel_err(H, twin.margins(case.X)) <= RTOL
    eps = case.sp.eps_h
    np.testing.assert_array_equal(np.any(H <= eps, axis=1), twin.crashed(case.X, eps))
    assert 0 < twin.crashed(case.X, eps).sum() < len(case.X)
    nxt = np.asarray(dyn(case.X.T, case.V.T, scene)).T
    with np.errstate(divide="ignore", invalid="ignore"):
        ref = twin.step(case.X, case.V)
    assert rel_err(nxt, ref) <= RTOL
    beta_max = case.sp.model.barrier.options.beta_max
    assert np.any(nxt[:, -1] == beta_max) and np.any(nxt[:, -1] < beta_max)


def test_the_casadi_path_equals_the_twin(case):
    """The CasADi virtual machine (the samplers' fallback) against the twin."""
    scene = case.scenes[1]
    f = case.sp.functions()
    twin = the_twin(case, scene)
    H = np.asarray(f["margins"].map(len(case.X))(case.X.T, scene)).T
    assert rel_err(H, twin.margins(case.X)) <= RTOL
    nxt = np.asarray(f["dyn"].map(len(case.X))(case.X.T, case.V.T, scene)).T
    with np.errstate(divide="ignore", invalid="ignore"):
        assert rel_err(nxt, twin.step(case.X, case.V)) <= RTOL


def at_rest(layout: SceneLayout, v: np.ndarray) -> np.ndarray:
    """The scene with its moving circles' velocities 0: the rollout comparisons check margins
    at the present (t = 0), not a prediction over the horizon."""
    out = np.array(v, dtype=float)
    for b in layout.blocks():
        if b.kind.name == "moving":
            out[b.start:b.stop].reshape(b.count, b.width)[:, 3:] = 0.0
    return out


def compiled_or_skip(make):
    """``make()``'s sampler; the test is skipped, with the warning's reason, when it has no
    compiled kernels (no C compiler, or an operation its C emitter does not support)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RuntimeWarning)
        sampler = make()
    if sampler.lib is None:
        reasons = "; ".join(str(w.message) for w in caught) or "no C compiler"
        pytest.skip(f"the sampler kernels run on the CasADi virtual machine: {reasons}")
    return sampler


def test_sampler_kernel_crash_flags_and_costs_equal_the_twin(case):
    sp = case.sp
    sampler = compiled_or_skip(lambda: Sampler(sp, backend="auto"))
    nu = sp.nu
    scene = at_rest(case.plain.scene_layout, case.scenes[0])
    goal = sp.model.lift(np.concatenate([case.start[:nu] + 2.0, np.zeros(nu)]), scene)
    c = SamplerConstants(sigma=np.full(nu, 2.5), lam=1.0, nu_mix=0.0, u_min=sp.model.u_min,
                         u_max=sp.model.u_max, crash_cost=1e6, p=goal, scene=scene)
    x0 = sp.model.lift(case.start, scene)
    U = np.random.default_rng(9).normal(0.0, 1.0, (T, nu))
    batch = sampler.mppi(x0, U, N, c, seed=21)
    Z = np.transpose(sampler.lib.normals(N, T, nu, 21), (2, 0, 1))
    ref = mppi_twin(sp, np.tile(x0, (N, 1)), U, Z, c, "numpy")
    assert 0 < ref["crashed"].sum() < N  # some samples crash, most do not
    np.testing.assert_array_equal(batch.crashed, ref["crashed"])
    assert rel_err(batch.S, ref["S"]) <= KERNEL_RTOL


def test_safe_kernel_equals_its_twin(case):
    """The DCBF projection and cost of the safe-sampling methods (CBF projection, Shield-MPPI)
    on the physical model: crash flags, projected and infeasible step counts equal, costs,
    controls and DCBF violations per element (KERNEL_RTOL)."""
    plain = case.plain
    sp = (navigation_3d(plain) if case.name == "space"
          else navigation_costs(plain, S=(10.0, 10.0, 1.0, 1.0)))
    sampler = compiled_or_skip(lambda: SafeSampler(sp, backend="auto"))
    nu = sp.nu
    c = SamplerConstants(sigma=np.full(nu, 2.5), lam=1.0, nu_mix=0.0, u_min=plain.u_min,
                         u_max=plain.u_max, crash_cost=1e6,
                         p=np.concatenate([case.start[:nu] + 2.0, np.zeros(nu)]),
                         scene=at_rest(plain.scene_layout, case.scenes[0]))
    U = np.random.default_rng(9).normal(0.0, 1.0, (T, nu))
    opts = SafeOptions(project=True, w_dcbf=1e3, gamma=0.9)
    batch = sampler.batch(case.start, U, N, c, opts, 21)
    Z = np.transpose(sampler.lib.normals(N, T, nu, 21), (2, 0, 1))
    ref = safe_twin(sp, np.tile(case.start, (N, 1)), U, Z, c, True, 1e3, 0.9, "numpy")
    assert 0 < (ref["projected"] > 0).sum() < N and 0 < ref["crashed"].sum() < N
    for k in ("crashed", "projected", "infeasible"):
        np.testing.assert_array_equal(getattr(batch, k), ref[k], err_msg=k)
    assert rel_err(batch.S, ref["S"]) <= KERNEL_RTOL
    assert rel_err(batch.dcbf, ref["dcbf"]) <= KERNEL_RTOL
    assert rel_err(batch.v, np.transpose(ref["v"], (1, 2, 0))) <= KERNEL_RTOL

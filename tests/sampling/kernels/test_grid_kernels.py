"""The signed-distance grid in the compiled sampler kernels.

* The emitted lookup, alone (a probe kernel of the grid margin at given positions): equal to
  CasADi's interpolant bitwise (float64) at interior points, nodes, cell edges, the last node
  row and column, beyond every side and far away, and for a NaN position; within float32
  rounding (float32). A copy that clamps the cell to nx - 1 instead of nx - 2 fails it.
* The sampler kernels on a layout with a grid alone and mixed with circles (one slot unused),
  a half-plane and a capsule: SAIS and MPPI costs, crash flags and controls equal the
  CasADi-twin rollout on the kernels' own noise, relative 1e-12 per element; states, barrier
  states and every margin of a rollout of the model's dynamics equal CasADi's; the load-time
  check passes; float32 crash decisions equal float64's on the same samples.
* A new grid of the same shape (moved, rescaled) builds nothing.
* Calls the emitter cannot write are refused, named, and the sampler falls back.

Tolerance: |a - b| <= 1e-12 max(|a|, |b|, 1) per element (float64; in practice bitwise),
1e-5 for the float32 lookup (float rounding of the position, the weights and the values).
"""

from __future__ import annotations

import warnings
from dataclasses import replace

import casadi as ca
import numpy as np
import pytest

import workbench as wb
from workbench.problem.barrier import embed_barrier
from workbench.problem.models import double_integrator
from workbench.problem.obstacles import Circle
from workbench.problem.scene_kinds import Capsule, HalfSpace
from workbench.problem.scene_layout import SceneLayout
from workbench.problem.sdf_grid import SignedDistanceGrid, grid_numpy, grid_sx, row_interpolant
from workbench.sampling.kernels.constants import SamplerConstants
from workbench.sampling.kernels.emit import EmitError, KernelSpec, emit_kernel
from workbench.sampling.kernels.verify import reference_rollout, verify_kernel
from workbench.sampling.problem import navigation_costs
from workbench.sampling.sampler import Sampler
from workbench.sampling.twin import lane_major, mppi_twin, sais_twin

RTOL = 1e-12
RTOL_F32 = 1e-5
SHAPE = (24, 18)  # nodes along x, y
N, T = 61, 30  # samples (a padded last block), steps


def rel(a, b) -> np.ndarray:
    a, b = np.asarray(a, float), np.asarray(b, float)
    same = (a == b) | (np.isnan(a) & np.isnan(b))
    with np.errstate(invalid="ignore"):
        d = np.abs(a - b) / np.maximum(np.maximum(np.abs(a), np.abs(b)), 1.0)
    return np.where(same, 0.0, d)


def circles_grid(shape, origin, res, circles) -> SignedDistanceGrid:
    """The signed distance of a union of circles (x, y, r) at the nodes."""
    xs = origin[0] + res * np.arange(shape[0])
    ys = origin[1] + res * np.arange(shape[1])
    d = np.min([np.hypot(xs[:, None] - x, ys[None, :] - y) - r for x, y, r in circles], axis=0)
    return SignedDistanceGrid(d, origin, res)


# ------------------------------------------------------------------------------------ the lookup

PROBE_SHAPE, PROBE_ORIGIN, PROBE_RES = (7, 5), (-1.0, 0.5), 0.5


def probe_spec(precision: str) -> KernelSpec:
    """Lane outputs: the grid margin at lane-input positions, the scene a const input."""
    nx, ny = PROBE_SHAPE
    c, pos, s = ca.SX.sym("carry"), ca.SX.sym("pos", 2), ca.SX.sym("scene", 3 + nx * ny)
    name = "wb_grid_probe" + ("_f32" if precision == "float32" else "")
    step = ca.Function(name + "_step", [c, pos, s], [c, grid_sx(pos, s, PROBE_SHAPE)],
                       ["carry", "pos", "scene"], ["carry_next", "h"])
    final = ca.Function(name + "_final", [c], [c], ["carry"], ["result"])
    return KernelSpec(name=name, step=step, final=final, precision=precision,
                      roles={"carry": "carry", "pos": "lane", "scene": "const"})


def probe_points(rng: np.random.Generator) -> np.ndarray:
    """Unit-grid points (u, v): interior, every node, cell edges, the last node row and column
    (exact: the probe's positions are multiples of 1/8 cell there), beyond every side and
    corner, far away."""
    nx, ny = PROBE_SHAPE
    nodes = np.stack(np.meshgrid(np.arange(nx), np.arange(ny)), -1).reshape(-1, 2)
    inner = np.c_[rng.uniform(0, nx - 1, 40), rng.uniform(0, ny - 1, 40)]
    edges = np.r_[np.c_[rng.integers(0, nx, 10), rng.integers(0, 8 * (ny - 1), 10) / 8],
                  np.c_[rng.integers(0, 8 * (nx - 1), 10) / 8, rng.integers(0, ny, 10)]]
    last = np.r_[np.c_[np.full(8, nx - 1.0), rng.uniform(0, ny - 1, 8)],
                 np.c_[rng.uniform(0, nx - 1, 8), np.full(8, ny - 1.0)]]

    def side(n: int, k: int) -> np.ndarray:  # below, inside, above the nodes 0..n-1
        return (rng.uniform(-3.0, -0.01, 4), rng.uniform(0, n - 1, 4),
                rng.uniform(n - 1 + 0.01, n + 2.0, 4))[k]

    beyond = [np.c_[side(nx, a), side(ny, b)] for a in range(3) for b in range(3) if a != 1
              or b != 1]
    far = np.array([[-1e3, 2.0], [1e3, 2.0], [3.0, -1e3], [3.0, 1e3], [-1e3, -1e3], [1e3, 1e3]])
    return np.vstack([inner, nodes, edges, last, *beyond, far])


def run_probe(lib, spec, P: np.ndarray, row: np.ndarray) -> np.ndarray:
    from workbench.sampling.kernels.compiled import CompiledKernel

    k = CompiledKernel(spec, lib.cdll)
    out = k(np.zeros((P.shape[0], 1)), consts={"scene": row},
            lane_in={"pos": P.T[None].copy()})
    return out.lane_out[0][0, 0, :P.shape[0]].copy()


@pytest.fixture(scope="module")
def probe(tmp_path_factory):
    from workbench.codegen import build_library
    from workbench.sampling.kernels.flags import kernel_flags
    from workbench.sampling.kernels.library import kernel_source

    rng = np.random.default_rng(41)
    uv = probe_points(rng)
    P = np.asarray(PROBE_ORIGIN) + PROBE_RES * uv
    P = np.vstack([P, [[np.nan, 1.0]]])
    row = SignedDistanceGrid(rng.normal(0.0, 2.0, PROBE_SHAPE), PROBE_ORIGIN, PROBE_RES).row()
    libs = {}
    for p in ("float64", "float32"):
        spec = probe_spec(p)
        lib = build_library(f"wb_grid_probe_{p}", [], kernel_source([spec]),
                            root=tmp_path_factory.mktemp(p), extra_flags=kernel_flags(p))
        if lib is None:
            pytest.skip("no C compiler")
        libs[p] = (lib, spec)
    return P, row, libs


def casadi_margins(P: np.ndarray, row: np.ndarray) -> np.ndarray:
    s = ca.SX.sym("s", row.size)
    p = ca.SX.sym("p", 2)
    f = ca.Function("h", [p, s], [grid_sx(p, s, PROBE_SHAPE)])
    return np.array(f.map(P.shape[0])(P.T, row)).ravel()


def test_the_float64_lookup_equals_casadis_interpolant_everywhere(probe):
    P, row, libs = probe
    lib, spec = libs["float64"]
    got = run_probe(lib, spec, P, row)
    want = casadi_margins(P, row)
    assert np.array_equal(got, want, equal_nan=True)  # bitwise, NaN where CasADi's is
    assert np.isnan(got[-1]) and np.isfinite(got[:-1]).all()
    # the NumPy twin: the same bilinear form written independently
    assert rel(got[:-1], grid_numpy(P[:-1], row, PROBE_SHAPE)).max() <= RTOL
    # the grid's own values at the nodes
    nx, ny = PROBE_SHAPE
    V = row[3:].reshape(ny, nx)
    uv = np.rint((P[:-1] - PROBE_ORIGIN) / PROBE_RES)
    at_node = np.all(np.abs((P[:-1] - PROBE_ORIGIN) / PROBE_RES - uv) == 0, axis=1) & np.all(
        (uv >= 0) & (uv <= [nx - 1, ny - 1]), axis=1)
    assert at_node.sum() >= nx * ny
    idx = uv[at_node].astype(int)
    assert np.array_equal(got[:-1][at_node], V[idx[:, 1], idx[:, 0]])


def test_the_float32_lookup_is_within_float_rounding(probe):
    P, row, libs = probe
    lib, spec = libs["float32"]
    got = run_probe(lib, spec, P, row)
    r32 = row.astype(np.float32).astype(float)
    want = casadi_margins(P.astype(np.float32).astype(float), r32)
    assert np.isnan(got[-1])
    err = rel(got[:-1], want[:-1])
    assert err.max() <= RTOL_F32, err.max()
    assert err.max() > 0.0  # really float


def test_a_lookup_with_a_shifted_weight_fails(probe, tmp_path, monkeypatch):
    """A broken copy (the weight a = x - i off by 1e-9) disagrees with CasADi: the comparison
    above sees it."""
    from workbench.codegen import build_library
    from workbench.sampling.kernels import grid_lookup
    from workbench.sampling.kernels.flags import kernel_flags
    from workbench.sampling.kernels.library import kernel_source

    real = grid_lookup.lookup_c

    def broken(name, x, table, g, ctype):
        return real(name, x, table, g, ctype).replace(f"= {x} - {name}_i;",
                                                      f"= {x} - {name}_i + 1e-9;")

    monkeypatch.setattr("workbench.sampling.kernels.emit.lookup_c", broken)
    P, row, _ = probe
    spec = probe_spec("float64")
    lib = build_library("wb_grid_probe_broken", [], kernel_source([spec]), root=tmp_path,
                        extra_flags=kernel_flags("float64"))
    got = run_probe(lib, spec, P, row)
    assert not np.array_equal(got, casadi_margins(P, row), equal_nan=True)


# ------------------------------------------------------------------------- the sampler kernels

GRID = SceneLayout.of(grid=SHAPE)
MIXED = SceneLayout.of(circles=2, halfspaces=1, capsules=1, grid=SHAPE)
ORIGIN, RES = (0.0, 0.25), 0.2
BLOBS = ((1.3, 1.9, 0.35), (1.0, 3.2, 0.3))  # the grid's obstacles (x, y, r)


def scene_objects(layout: SceneLayout, grid: SignedDistanceGrid) -> list:
    if layout is GRID:
        return [grid]
    return [grid, Circle((2.2, 2.6), 0.25), HalfSpace((0.0, -1.0), -3.4),
            Capsule((1.9, 1.0), (2.6, 1.3), 0.15)]


def problem(layout: SceneLayout):
    grid = circles_grid(SHAPE, ORIGIN, RES, BLOBS)
    model = embed_barrier(double_integrator(scene_layout=layout, u_limit=6.0,
                                            obstacles=scene_objects(layout, grid)))
    return navigation_costs(model)


@pytest.fixture(scope="module", params=["grid", "mixed"])
def sampler(request):
    sp = problem(GRID if request.param == "grid" else MIXED)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no fallback, no failed load-time check
        s = Sampler(sp, "auto")
    if s.backend != "compiled":
        pytest.skip("no C compiler")
    return sp, s


def batch_inputs(sp, rng: np.random.Generator):
    """Starts left of the grid (its extrapolation in play) heading for the edge of the first
    blob (some samples crash, some pass), a plan, gains and constants."""
    m = sp.model
    x_phys = np.array([-0.3, 1.52, 3.2, 0.0])
    xs_phys = x_phys + np.array([0.05, -0.05, 0.1, 0.0])
    goal = np.array([3.5, 2.5, 0.0, 0.0])
    U = rng.normal(0.0, 1.0, (T, 2))
    K = np.zeros((T, 2, m.nx))
    K[:, 0, 0] = K[:, 1, 1] = -2.0
    K[:, 0, 2] = K[:, 1, 3] = -1.5
    K += rng.normal(0.0, 0.3, K.shape)
    c = SamplerConstants(sigma=np.array([3.0, 3.0]), lam=1.3, nu_mix=0.1, u_min=m.u_min,
                         u_max=m.u_max, crash_cost=1e4, p=m.lift(goal), scene=m.scene_value,
                         alpha=60.0)
    return m.lift(x_phys), m.lift(xs_phys), U, K, c


def test_sais_and_mppi_kernels_equal_the_casadi_twin(sampler):
    sp, s = sampler
    x0, xs0, U, K, c = batch_inputs(sp, np.random.default_rng(5))
    b = s.sais(x0, xs0, U, K, N, c, 17)
    Z = s.lib.normals(N, T, sp.nu, 17).transpose(2, 0, 1)  # the kernel's draws, (N, T, nu)
    ref = sais_twin(sp, np.tile(x0, (N, 1)), np.tile(xs0, (N, 1)), U, K, Z, c, "casadi")
    for f in ("S_nom", "S_real", "S_state_nom", "S_hat", "LR"):
        assert rel(getattr(b, f), ref[f]).max() <= RTOL, f
    for f in ("crashed_real", "crashed_nom"):
        assert np.array_equal(getattr(b, f), ref[f]), f
        assert 0 < ref[f].sum() < N, f  # crash decisions to get right
    assert rel(b.v_real[..., :N], lane_major(ref["v_real"])).max() <= RTOL
    m = s.mppi(x0, U, N, c, 23)
    Z = s.lib.normals(N, T, sp.nu, 23).transpose(2, 0, 1)
    ref = mppi_twin(sp, np.tile(x0, (N, 1)), U, Z, c, "casadi")
    assert rel(m.S, ref["S"]).max() <= RTOL
    assert np.array_equal(m.crashed, ref["crashed"]) and 0 < ref["crashed"].sum() < N
    # some states leave the grid's nodes (its extrapolation is in play)
    X = ref["X"][..., :2]
    lo, hi = np.asarray(ORIGIN), np.asarray(ORIGIN) + RES * (np.asarray(SHAPE) - 1)
    assert np.any((X < lo) | (X > hi))


def test_the_load_time_check_passes(sampler):
    _, s = sampler
    for k in (s.lib.mppi, s.lib.sais, s.lib.candidates):
        verify_kernel(k)


def test_states_barrier_states_and_margins_equal_casadi(tmp_path):
    """A rollout of the embedded model's dynamics (physical and barrier states) and of every
    margin (grid, circles with one unused slot, half-plane, capsule) in an emitted kernel."""
    from workbench.codegen import build_library
    from workbench.sampling.kernels.compiled import CompiledKernel
    from workbench.sampling.kernels.flags import kernel_flags
    from workbench.sampling.kernels.library import kernel_source

    sp = problem(MIXED)
    m, f = sp.model, sp.functions()
    x, v, s = ca.SX.sym("carry", m.nx), ca.SX.sym("v", m.nu), ca.SX.sym("scene", m.n_scene)
    xn = f["dyn"](x, v, s)
    step = ca.Function("wb_grid_states_step", [x, v, s], [xn, ca.vertcat(xn, f["margins"](
        xn, s))], ["carry", "v", "scene"], ["carry_next", "out"])
    final = ca.Function("wb_grid_states_final", [x], [x], ["carry"], ["result"])
    spec = KernelSpec(name="wb_grid_states", step=step, final=final,
                      roles={"carry": "carry", "v": "lane", "scene": "const"})
    lib = build_library("wb_grid_states", [], kernel_source([spec]), root=tmp_path,
                        extra_flags=kernel_flags("float64"))
    if lib is None:
        pytest.skip("no C compiler")
    rng = np.random.default_rng(9)
    n = 13
    carry0 = np.array([m.lift(p) for p in np.c_[rng.uniform(-0.8, 3.0, (n, 2)),
                                                  rng.normal(0.0, 2.0, (n, 2))]])
    V = rng.normal(0.0, 4.0, (T, m.nu, n))
    got = CompiledKernel(spec, lib.cdll)(carry0, consts={"scene": m.scene_value},
                                         lane_in={"v": V})
    lane_ref, res_ref = reference_rollout(spec, carry0, {}, {"v": V},
                                          {"scene": m.scene_value}, None)
    out, want = got.lane_out[0][..., :n], lane_ref[0]
    assert rel(out, want).max() <= RTOL and rel(got.result[:n], res_ref).max() <= RTOL
    nh = m.nh
    assert nh == 2 + 1 + 1 + 1
    H = want[:, -nh:, :]
    assert np.any(H[:, -1] < 0) and np.any(H[:, -1] > 0)  # inside and outside the grid's blobs
    assert np.all(H[:, 1] > 1e10)  # the unused circle slot


def test_float32_crash_decisions_equal_float64(sampler):
    """Same samples (the kernels' common draws), positions within float32's coordinate limit:
    every crash flag agrees (samples near the crash margin are recomputed in float64, the rest
    decide alike)."""
    sp, s64 = sampler
    s32 = Sampler(sp, "compiled", "float32")
    x0, xs0, U, K, c = batch_inputs(sp, np.random.default_rng(6))
    a, b = s32.sais(x0, xs0, U, K, N, c, 31), s64.sais(x0, xs0, U, K, N, c, 31)
    for f in ("crashed_real", "crashed_nom"):
        assert np.array_equal(getattr(a, f), getattr(b, f)) and 0 < getattr(b, f).sum() < N
    # costs: float32 rounding, amplified by the barrier on samples passing close to an
    # obstacle (up to 1e-4 measured); the rest within 1e-5
    assert np.mean(rel(a.S_real, b.S_real) <= 1e-5) >= 0.8
    a, b = s32.mppi(x0, U, N, c, 37), s64.mppi(x0, U, N, c, 37)
    assert np.array_equal(a.crashed, b.crashed) and 0 < b.crashed.sum() < N
    assert s32.guard.batches >= 2


def test_a_new_grid_of_the_same_shape_builds_nothing(sampler):
    sp, s = sampler
    x0, xs0, U, K, c = batch_inputs(sp, np.random.default_rng(7))
    m = sp.model
    a = s.sais(x0, xs0, U, K, N, c, 3)
    before = wb.build_counts()
    moved = circles_grid(SHAPE, (-0.7, 0.1), 0.23, ((1.1, 1.7, 0.4),))
    objs = [moved, *scene_objects(m.scene_layout, moved)[1:]]
    c2 = replace(c, scene=m.scene_vector(objs))
    b = s.sais(x0, xs0, U, K, N, c2, 3)
    s.mppi(x0, U, N, c2, 4)
    assert wb.build_counts() == before
    assert not np.array_equal(a.S_real, b.S_real)  # the new grid is in play


# ----------------------------------------------------------------------------- what is refused


def tiny(margin) -> KernelSpec:
    c, w, s = ca.SX.sym("carry", 2), ca.SX.sym("w", 12), ca.SX.sym("scene", 3 + 12)
    step = ca.Function("wb_tiny_step", [c, w, s], [c, margin(c, w, s)], ["carry", "w", "scene"],
                       ["carry_next", "h"])
    final = ca.Function("wb_tiny_final", [c], [c], ["carry"], ["result"])
    return KernelSpec(name="wb_tiny", step=step, final=final,
                      roles={"carry": "carry", "w": "lane", "scene": "const"})


def test_other_calls_are_refused_and_named():
    p = ca.SX.sym("p", 2)
    other = ca.Function("wb_other", [p], [p[0] * p[1]], {"never_inline": True})
    with pytest.raises(EmitError, match=r"operation call \(wb_other\), which the sampler's C "
                                        r"emitter does not support"):
        emit_kernel(tiny(lambda c, w, s: other(c)))
    # a derivative of the interpolant (the sampler kernels need none)
    with pytest.raises(EmitError, match=r"operation call \(fwd1_wrap_wb_row_12\)"):
        emit_kernel(tiny(lambda c, w, s: ca.jacobian(grid_sx(c, s, (4, 3)), c)[0]))
    # values compiled into the model instead of the run-time scene, or partly computed
    with pytest.raises(EmitError, match=r"not one contiguous run of an input.*run-time scene"):
        emit_kernel(tiny(lambda c, w, s: row_interpolant(12)(c[0], np.arange(12.0))))
    with pytest.raises(EmitError, match=r"not one contiguous run of an input"):
        emit_kernel(tiny(lambda c, w, s: row_interpolant(12)(c[0], ca.vertcat(c, s[3:13]))))
    # values from a per-sample input
    with pytest.raises(EmitError, match=r"values must be an input shared by every sample"):
        emit_kernel(tiny(lambda c, w, s: row_interpolant(12)(c[0], w)))
    emit_kernel(tiny(lambda c, w, s: grid_sx(c, s, (4, 3))))  # the scene's grid is written


def test_a_model_with_another_call_falls_back_with_a_warning():
    p = ca.SX.sym("p", 2)
    bump = ca.Function("wb_bump", [p], [p[0] * p[0] + p[1] * p[1] - 1.0],
                       {"never_inline": True})  # a call node in the margin
    base = double_integrator(obstacles=())
    model = wb.Model.from_expressions(
        "bumped", base.x, base.u, base.x_next, dt=base.dt, u_min=base.u_min, u_max=base.u_max,
        h=bump(base.x[:2]), position=(0, 1))
    g = ca.SX.sym("goal", 4)
    e = model.x[:2] - g[:2]
    sp = wb.SamplingProblem.from_costs(model, q=ca.dot(e, e), phi=ca.dot(e, e), p=g)
    with pytest.warns(RuntimeWarning, match=r"no compiled sampler kernels for bumped.*"
                                            r"call \(wb_bump\).*NumPy/CasADi evaluation"):
        s = Sampler(sp, "auto")
    assert s.backend == "numpy"

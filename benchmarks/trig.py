"""Vectorised trigonometry (issue 13 item 4): a unicycle-like model against the double integrator
of the same size on the paper's map, per sample-step of the compiled MPPI and SAIS kernels.

Both models have 4 states and 2 controls, the same 30 circles, barrier state and costs; only the
dynamics differ (the unicycle's heading enters through cos and sin). The unicycle's kernels are
built twice, with glibc's SIMD variants (libmvec, the default) and with scalar libm calls
(``WORKBENCH_VECTOR_MATH=0``); the two are checked to agree before they are timed.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from benchmarks.sampling import _interleaved, _record, _rel_err
from workbench.problem.barrier import BarrierOptions, embed_barrier
from workbench.problem.models import Model, double_integrator
from workbench.problem.obstacles import circle_margins
from workbench.sampling import SamplingProblem
from workbench.sampling.kernels.constants import SamplerConstants
from workbench.sampling.kernels.flags import KERNEL_FLAGS
from workbench.sampling.kernels.library import SamplerLibrary, load_sampler_library
from workbench.sampling.kernels.vector_math import MAX_ULP, unavailable
from workbench.scenarios.scenes import NavigationScene

N, T, DT = 1024, 100, 0.02
GOAL_SLOWDOWN = 1.3  # issue 13: the unicycle within 1.3x of the double integrator


def unicycle(obstacles, polynomial: bool = False) -> Model:
    """x = [px, py, heading, speed], u = [acceleration, turn rate]. ``polynomial`` replaces cos
    and sin by their cubic Taylor polynomials: the same kernel without libm calls, which
    measures what the calls themselves cost (a floor for any libm-based kernel)."""
    x, u = ca.SX.sym("x", 4), ca.SX.sym("u", 2)
    th = x[2]
    c, s = ((1 - th * th / 2, th - th * th * th / 6) if polynomial else (ca.cos(th), ca.sin(th)))
    x_next = x + DT * ca.vertcat(x[3] * c, x[3] * s, u[1], u[0])
    return Model.from_expressions(
        "bench_unicycle" + ("_polynomial" if polynomial else ""), x, u, x_next, dt=DT,
        u_min=[-15.0, -15.0], u_max=[15.0, 15.0],
        h=circle_margins(x[:2], obstacles, "squared"), state_names=("px", "py", "th", "v"),
        control_names=("a", "omega"), position=(0, 1), obstacles=obstacles)


def problem(model: Model) -> SamplingProblem:
    """Distance to the goal and the barrier state, the same expressions for both models."""
    emb = embed_barrier(model, BarrierOptions())
    x, g = emb.x, ca.SX.sym("goal", emb.nx)
    e = x[:2] - g[:2]
    return SamplingProblem.from_costs(emb, ca.dot(e, e) + 0.01 * x[4] ** 2, 10.0 * ca.dot(e, e),
                                      g, description=f"{model.name} to a goal")


def _inputs(sp: SamplingProblem, x_phys):
    rng = np.random.default_rng(0)
    consts = SamplerConstants(
        sigma=np.array([2.0, 2.0]), lam=1.0, nu_mix=0.0, u_min=sp.model.u_min,
        u_max=sp.model.u_max, crash_cost=1e6, p=sp.model.lift(np.array([9.5, 9.5, 0.0, 0.0])),
        alpha=2e4, scene=sp.model.scene_value).kernel_consts()
    carry_nom = np.tile(sp.model.lift(x_phys), (N, 1))
    extra = np.zeros((N, 2))
    U = rng.normal(0, 1.0, (T, 2))
    K = rng.normal(0, 0.5, (T, 2 * sp.nx))
    return consts, np.hstack([carry_nom, extra]), U, K, carry_nom


def _calls(lib: SamplerLibrary, sp: SamplingProblem, x_phys):
    consts, carry, U, K, nom = _inputs(sp, x_phys)
    sais_carry = np.hstack([nom, nom, np.zeros((N, 6))])
    mppi_c = {k: consts[k] for k in lib.mppi.spec.inputs("const")}
    sais_c = {k: consts[k] for k in lib.sais.spec.inputs("const")}
    return {
        "mppi": lambda seed: lib.mppi(carry, consts=mppi_c, time_in={"u": U}, seed=seed),
        "sais": lambda seed: lib.sais(sais_carry, consts=sais_c, time_in={"u": U, "K": K},
                                      seed=seed),
    }


def records(repeats: int) -> list[dict]:
    scene = NavigationScene()
    obstacles = scene.obstacles()
    di = problem(double_integrator(dt=DT, obstacles=obstacles))
    uni = problem(unicycle(obstacles))
    start = np.array([*scene.start])
    poly = problem(unicycle(obstacles, polynomial=True))
    libs = {"di": load_sampler_library(di), "uni_vec": load_sampler_library(uni, True),
            "uni_scalar": load_sampler_library(uni, False), "uni_poly": load_sampler_library(poly)}
    why = unavailable(KERNEL_FLAGS, 4)
    if any(v is None for v in libs.values()):
        return [_record("trig_" + k, None, "ns/sample-step", None, None, {})
                | {"skipped": "no C compiler"} for k in ("mppi", "sais")]
    for lib in libs.values():
        lib.set_threads(1)  # one thread: per sample-step cost, robust to other processes
    calls = {"di": _calls(libs["di"], di, np.array([*start, 0.0, 0.0])),
             "uni_vec": _calls(libs["uni_vec"], uni, np.array([*start, np.pi / 4, 0.0])),
             "uni_scalar": _calls(libs["uni_scalar"], uni, np.array([*start, np.pi / 4, 0.0])),
             "uni_poly": _calls(libs["uni_poly"], poly, np.array([*start, np.pi / 4, 0.0]))}
    out = []
    per = 1e9 / (N * T)
    for kernel in ("mppi", "sais"):
        a, b = calls["uni_vec"][kernel](3), calls["uni_scalar"][kernel](3)
        agree = max(_rel_err(a.result, b.result),
                    *(_rel_err(x, y) for x, y in zip(a.lane_out, b.lane_out, strict=True)))
        if agree > 1e-6:
            raise AssertionError(f"unicycle {kernel}: vector and scalar libm differ by {agree}")
        t_vec, t_di = _interleaved(calls["uni_vec"][kernel], calls["di"][kernel],
                                   4 * repeats, 4 * repeats)
        t_vec2, t_sc = _interleaved(calls["uni_vec"][kernel], calls["uni_scalar"][kernel],
                                    4 * repeats, 4 * repeats)
        t_poly, t_di2 = _interleaved(calls["uni_poly"][kernel], calls["di"][kernel],
                                     4 * repeats, 4 * repeats)
        params = {"N": N, "T": T, "threads": 1, "obstacles": len(obstacles),
                  "vector_math": why or "libmvec", "max_ulp_tested": MAX_ULP,
                  "vector_vs_scalar_max_rel_diff": agree,
                  "floor_polynomial_unicycle_vs_di": t_poly / t_di2}
        out.append(_record(
            f"trig_{kernel}_unicycle_vs_double_integrator", per * t_vec, "ns/sample-step",
            "double_integrator_same_size", per * t_di,
            params | {"slowdown_vs_di": t_vec / t_di, "goal_slowdown": GOAL_SLOWDOWN,
                      "goal_met": t_vec / t_di <= GOAL_SLOWDOWN}))
        out.append(_record(
            f"trig_{kernel}_unicycle_libmvec_vs_scalar_libm", per * t_vec2, "ns/sample-step",
            "unicycle_scalar_libm", per * t_sc, params))
    return out

"""Every fast path of the workbench and its twin, as one registry of cases.

A twin is the plain NumPy counterpart of a fast path (compiled kernels, compiled iLQG passes,
vectorised steps), written independently of it and named ``<fast name>_twin`` in a ``twin.py``
of the fast path's package. A :class:`TwinCase` names the pair, builds its inputs once, runs
both sides and says how close they must be: per element, |fast - twin| <= rtol * max(|fast|,
|twin|, floor), so the tolerance is relative and becomes absolute (rtol * floor) only below
magnitude ``floor``. Booleans, integers (counts, indices), strings and None must be equal.

Both sides return their outputs in one layout, the twin's: the fast side converts lane-major
kernel arrays (T, nu, N) with :func:`workbench.sampling.twin.sample_major` (the boundary the
samplers use the other way round, :func:`~workbench.sampling.twin.lane_major`).

The cases reuse the set-ups of the per-path tests (their module-level helpers, loaded from
their files), so the inputs are the ones those tests show reach every branch.
"""

from __future__ import annotations

import importlib.util
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

TESTS = Path(__file__).parent
Outputs = Mapping[str, Any]


@dataclass(frozen=True)
class TwinCase:
    """One (fast path, twin) pair: ``inputs()`` builds what both take (cached by the harness),
    ``fast(inputs)`` and ``twin(inputs)`` return their outputs by name, in the same layout."""

    name: str
    fast: Callable[[Any], Outputs]
    twin: Callable[[Any], Outputs]
    inputs: Callable[[], Any]
    rtol: float
    floor: float = 1.0

    def __post_init__(self) -> None:
        if not 0.0 < self.rtol < 1e-3:
            raise ValueError(f"TwinCase.rtol = {self.rtol!r}: must be in (0, 1e-3)")
        if not self.floor > 0.0:
            raise ValueError(f"TwinCase.floor = {self.floor!r}: must be > 0")


def element_error(a, b, floor: float) -> float:
    """Largest |a - b| / max(|a|, |b|, floor) over the elements (equal entries, NaN with NaN
    included, count 0; a shape mismatch or one-sided NaN counts inf)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    if a.shape != b.shape:
        return np.inf
    if a.size == 0:
        return 0.0
    same = (a == b) | (np.isnan(a) & np.isnan(b))
    with np.errstate(invalid="ignore", over="ignore"):
        e = np.where(same, 0.0,
                     np.abs(a - b) / np.maximum(np.maximum(np.abs(a), np.abs(b)), floor))
    return float(np.max(np.where(np.isnan(e), np.inf, e)))


def mismatch(fast: Outputs, twin: Outputs, floor: float) -> dict[str, float]:
    """Per output: the relative element error (floats), or 0 / inf (equal or not: booleans,
    integers such as counts and indices, strings, None, and outputs one side lacks)."""
    out = {}
    for name in sorted(set(fast) | set(twin)):
        if name not in fast or name not in twin:
            out[name] = np.inf
            continue
        a, b = fast[name], twin[name]
        if a is None or b is None or isinstance(a, str) or isinstance(b, str):
            out[name] = 0.0 if a == b else np.inf
        elif np.asarray(a).dtype.kind in "biu" or np.asarray(b).dtype.kind in "biu":
            same = np.shape(a) == np.shape(b) and bool(np.all(np.asarray(a) == np.asarray(b)))
            out[name] = 0.0 if same else np.inf
        else:
            out[name] = element_error(a, b, floor)
    return out


def disagreements(case: TwinCase, fast: Outputs, twin: Outputs) -> dict[str, float]:
    """The outputs on which ``fast`` and ``twin`` differ beyond the case's tolerance (empty:
    they agree)."""
    return {k: v for k, v in mismatch(fast, twin, case.floor).items() if not v <= case.rtol}


# --- the per-path tests' set-ups ---------------------------------------------------------------


def test_module(relative: str):
    """A per-path test module, loaded from its file under the name pytest gives it."""
    path = TESTS / relative
    name = path.stem
    mod = sys.modules.get(name)
    if mod is not None and Path(mod.__file__).resolve() == path.resolve():
        return mod
    if str(path.parent) not in sys.path:
        sys.path.insert(0, str(path.parent))  # its own sibling imports, as under pytest
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def _numbers(obj, prefix: str = "") -> dict[str, Any]:
    """The fields of a (nested) dataclass result as named outputs (arrays, numbers, flags)."""
    out = {}
    for f in fields(obj):
        v = getattr(obj, f.name)
        if f.name in ("timing", "time_s"):
            continue
        if hasattr(v, "__dataclass_fields__"):
            out |= _numbers(v, f"{prefix}{f.name}.")
        elif isinstance(v, Mapping):
            out |= {f"{prefix}{f.name}.{k}": v[k] for k in sorted(v)}
        elif isinstance(v, bool | np.bool_):
            out[prefix + f.name] = np.bool_(v)
        else:
            out[prefix + f.name] = v
    return out


# MPPI and SAIS kernels (tests/sampling/kernels/test_sampler_kernels.py)


def _sampler_inputs():
    from workbench.problem.barrier import embed_barrier
    from workbench.problem.models import double_integrator
    from workbench.sampling.kernels.constants import SamplerConstants
    from workbench.sampling.problem import navigation_costs
    from workbench.sampling.sampler import Sampler

    sk = test_module("sampling/kernels/test_sampler_kernels.py")
    model = embed_barrier(double_integrator(obstacles=sk.OBST, u_limit=5.0))
    sp = navigation_costs(model)
    sampler = Sampler(sp, backend="compiled")
    consts = SamplerConstants(sigma=np.array([3.0, 2.4]), lam=1.3, nu_mix=0.1,
                              u_min=model.u_min, u_max=model.u_max, crash_cost=1e6,
                              p=model.lift(sk.GOAL))
    x0 = sk.mppi_start(model)
    U = np.random.default_rng(11).normal(0, 2.0, (sk.T, 2))
    return sk, model, sp, sampler, consts, x0, U, sk.sais_case(model, sampler, consts)


def _mppi_fast(i):
    sk, _, _, sampler, c, x0, U, _ = i
    from workbench.sampling.twin import sample_major

    b = sampler.mppi(x0, U, sk.N, c, seed=123)
    return {"S": b.S, "crashed": b.crashed, "v": sample_major(b.v)}


def _mppi_twin(i):
    from workbench.sampling.twin import mppi_twin

    sk, _, sp, sampler, c, x0, U, _ = i
    r = mppi_twin(sp, np.tile(x0, (sk.N, 1)), U, sk.kernel_noise(sampler, sk.N, sk.T, 123), c)
    return {"S": r["S"], "crashed": r["crashed"], "v": r["v"]}


SAIS_OUT = ("S_nom", "S_real", "S_state_nom", "S_hat", "LR", "crashed_real", "crashed_nom")


def _sais_fast(i):
    from workbench.sampling.twin import sample_major

    sk, _, _, sampler, _, _, _, case = i
    b = sk.run_sais(sampler, case)
    return {**{k: getattr(b, k) for k in SAIS_OUT}, "v_nom": sample_major(b.v_nom),
            "v_real": sample_major(b.v_real)}


def _sais_twin(i):
    sk, _, sp, _, _, _, _, case = i
    r = sk.twin_sais(sp, case)
    return {k: r[k] for k in (*SAIS_OUT, "v_nom", "v_real")}


# safe-sampling kernel (tests/sampling/kernels/test_safe_kernels.py)


def _safe_inputs():
    from workbench.problem.models import double_integrator
    from workbench.sampling.kernels.constants import SamplerConstants
    from workbench.sampling.methods.sampler import SafeSampler
    from workbench.sampling.problem import navigation_costs

    sf = test_module("sampling/kernels/test_safe_kernels.py")
    model = double_integrator(obstacles=sf.OBST, u_limit=5.0)
    sp = navigation_costs(model, S=(10.0, 10.0, 1.0, 1.0))
    sampler = SafeSampler(sp, backend="compiled")
    c = SamplerConstants(sigma=np.array([3.0, 2.4]), lam=1.0, nu_mix=0.1, u_min=model.u_min,
                         u_max=model.u_max, crash_cost=1e6, p=np.array(sf.GOAL))
    U = np.random.default_rng(11).normal(0.0, 2.0, (sf.T, 2))
    Z = np.transpose(sampler.lib.normals(sf.N, sf.T, 2, sf.SEED), (2, 0, 1))
    return sf, sp, sampler, c, U, Z


SAFE_OUT = ("S", "crashed", "projected", "infeasible", "dcbf")


def _safe_fast(i):
    from workbench.sampling.methods.sampler import SafeOptions
    from workbench.sampling.twin import sample_major

    sf, _, sampler, c, U, _ = i
    b = sampler.batch(sf.start(), U, sf.N, c,
                      SafeOptions(project=True, w_dcbf=sf.W_DCBF, gamma=sf.GAMMA), sf.SEED)
    return {**{k: getattr(b, k) for k in SAFE_OUT}, "v": sample_major(b.v)}


def _safe_twin(i):
    sf, sp, _, c, U, Z = i
    r = sf.twin(sp, c, U, Z, True, sf.W_DCBF)
    return {k: r[k] for k in (*SAFE_OUT, "v")}


# iLQG passes (tests/ilqg/test_ilqg.py: forward, derivatives, backward, line search)


def _ilqg_inputs():
    from conftest import bas_tracking_problem

    from workbench.ilqg import make_passes
    from workbench.ilqg.twin import PassesTwin
    from workbench.scenarios.scenes import TrackingScene

    scene = TrackingScene()
    problem, P = bas_tracking_problem(scene)
    T = scene.horizon
    U = np.random.default_rng(12345).normal(0, 4, (T, 2))
    return (problem, P, T, U, problem.check_initial_state(scene.start),
            make_passes(problem, T, "compiled"), PassesTwin(problem, T))


def _ilqg_run(i, passes) -> dict[str, Any]:
    problem, P, T, U, x0 = i[:5]
    nx, nu = problem.nx, problem.nu
    umin, umax = problem.model.u_min, problem.model.u_max
    fw = passes.forward(x0, np.zeros((T + 1, nx)), U, np.zeros((T, nu)), np.zeros((T, nu, nx)),
                        P, 0.0, umin, umax, use_policy=False)
    Uc = np.clip(U, umin, umax)
    d = passes.derivatives(fw.X, Uc, P)
    out = {"forward.X": fw.X, "forward.cost": fw.cost, **{f"d.{k}": v for k, v in d.items()}}
    for reg, boxed in ((0, True), (1, False)):
        bw = passes.backward(d, Uc, umin, umax, 0.3, reg, boxed)
        out |= {f"backward{reg}{boxed}.{k}": getattr(bw, k) for k in ("status", "k", "K", "dV")}
        ls = passes.line_search(x0, fw.X, Uc, bw.k, bw.K, P, fw.cost, bw.dV, (1.0, 0.5, 0.1),
                                0.0, umin, umax)
        out |= {f"line_search{reg}{boxed}.{k}": getattr(ls, k)
                for k in ("accepted", "alpha", "X", "U", "cost")}
    return out


# Robust MPPI step (tests/sampling/test_robust_step_fast.py)


def _robust_inputs():
    import casadi as ca

    from workbench.codegen.fastcall import FastFunction
    from workbench.sampling.robust import RMPPIConfig
    from workbench.scenarios.navigation import navigation_setup

    rs = test_module("sampling/test_robust_step_fast.py")
    nav = navigation_setup()
    robust = RMPPIConfig(applied="real", fallback="keep_previous")
    fast, slow = rs.make(nav, True, robust), rs.make(nav, False, robust)
    p = nav.plant
    plant = FastFunction(ca.Function("plant", [p.x, p.u], [p.x_next]))
    # states along the twin's own undisturbed episode, each stepped by both with one seed
    rng = np.random.default_rng(2)
    x, state, steps = np.asarray(nav.x0, float), slow.initial_state(nav.x0), []
    for _ in range(6):
        seed = int(rng.integers(0, 2**63))
        steps.append((state, x, seed))
        state, u, _ = slow.step_twin(state, x, np.random.default_rng(seed))
        x = plant(x, np.clip(u, p.u_min, p.u_max))[0]
    return fast, slow, steps


def _robust_run(ctrl, steps, method: str) -> dict[str, Any]:
    out = {}
    for k, (state, x, seed) in enumerate(steps):
        s, u, info = getattr(ctrl, method)(state, x, np.random.default_rng(seed))
        out |= {f"{k}.u": u, f"{k}.U": s.U, f"{k}.x_nom": s.x_nom, f"{k}.index": s.index,
                **_numbers(s.gains, f"{k}.gains."), **_numbers(info, f"{k}.info.")}
    return out


# ECBF feedback gains (tests/sampling/test_ecbf_feedback_fast.py)


def _ecbf_inputs():
    from workbench.filters.ecbf import ECBFOptions
    from workbench.problem.models import double_integrator
    from workbench.sampling.feedback.ecbf import ECBFFeedback

    ef = test_module("sampling/test_ecbf_feedback_fast.py")
    model = double_integrator(obstacles=(ef.OBSTACLE,), u_limit=5.0)
    laws = [ECBFFeedback(model, ef.T, 5, ecbf=ECBFOptions(mode=m)) for m in ("soft", "hard")]
    return laws, ef.plans()


def _ecbf_run(i, method: str) -> dict[str, Any]:
    laws, plans = i
    out = {}
    for j, law in enumerate(laws):
        for k, (x0, U) in enumerate(plans):
            out |= _numbers(getattr(law, method)(x0, U, None, 0), f"{j}.{k}.")
    return out


CASES: tuple[TwinCase, ...] = (
    # the kernels and the twin evaluate the same formulas in another order: measured <= 3e-14
    # relative (see test_sampler_kernels.RTOL); a mutated twin moves costs by ~1e-3
    TwinCase("mppi kernel / mppi_twin", _mppi_fast, _mppi_twin, _sampler_inputs, 1e-10),
    TwinCase("sais kernel / sais_twin", _sais_fast, _sais_twin, _sampler_inputs, 1e-10),
    TwinCase("safe kernel / safe_twin", _safe_fast, _safe_twin, _safe_inputs, 1e-10),
    # the backward pass's Cholesky solves differ in order from NumPy's: measured ~1e-11
    TwinCase("compiled iLQG passes / PassesTwin", lambda i: _ilqg_run(i, i[5]),
             lambda i: _ilqg_run(i, i[6]), _ilqg_inputs, 1e-9),
    # the fast step is written to reproduce the twin's operations in the same order
    TwinCase("RobustMPPI.step / step_twin", lambda i: _robust_run(i[0], i[2], "step"),
             lambda i: _robust_run(i[1], i[2], "step_twin"), _robust_inputs, 1e-12),
    TwinCase("ECBFFeedback.gains / gains_twin", lambda i: _ecbf_run(i, "gains"),
             lambda i: _ecbf_run(i, "gains_twin"), _ecbf_inputs, 1e-12),
)

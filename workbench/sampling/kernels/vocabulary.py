"""The emitter vocabulary: the CasADi pieces every generated sampling kernel is written in.

The MPPI, SAIS and candidate kernels (:mod:`workbench.sampling.kernels.specs`), their slot-loop
forms (:mod:`~workbench.sampling.kernels.slots`) and the safe-MPPI kernel
(:mod:`~workbench.sampling.kernels.safe`) build their step Functions from these, so the same
input names, control clip and crash rule appear in each (and CSE shares them within a step).
"""

from __future__ import annotations

from collections.abc import Callable

import casadi as ca
import numpy as np

from workbench.problem.barrier import min_margin
from workbench.problem.prediction import predicts, scene_sx_at
from workbench.sampling.problem import SamplingProblem


def clip(v, lo, hi):
    """v clipped elementwise to [lo, hi] as ``fmin(fmax(v, lo), hi)`` (hi wins if lo > hi)."""
    return ca.fmin(ca.fmax(v, lo), hi)


def kernel_symbols(sp: SamplingProblem) -> dict[str, ca.SX]:
    """Fresh symbols of the kernels' shared const inputs, in this order: ``sigma`` (nu),
    ``lr`` (1), ``u_min``, ``u_max`` (nu), ``crash`` (1), ``p`` (n_p) and, only when the model
    has a run-time scene, ``scene`` (n_scene). Kernels add their own entries to the dict."""
    nu = sp.nu
    out = {
        "sigma": ca.SX.sym("sigma", nu), "lr": ca.SX.sym("lr"),
        "u_min": ca.SX.sym("u_min", nu), "u_max": ca.SX.sym("u_max", nu),
        "crash": ca.SX.sym("crash", 1), "p": ca.SX.sym("p", sp.n_p),
    }
    if sp.model.n_scene:
        out["scene"] = ca.SX.sym("scene", sp.model.n_scene)
    return out


def time_symbol(sp: SamplingProblem) -> ca.SX | None:
    """The kernels' ``t`` time input when the model's scene has moving circles (a fresh
    symbol: the time from now of the state a step computes, x_{k+1} at t = (k + 1) dt, see
    :func:`step_times`), else None (the kernels then take no such input and are those of a
    model without prediction)."""
    return ca.SX.sym("t") if predicts(sp.model) else None


def step_times(sp: SamplingProblem, T: int) -> dict[str, np.ndarray]:
    """The ``t`` time input of a T-step kernel call, {"t": (T, 1)} with t_k = (k + 1) dt (the
    time of x_{k+1}, whose margins step k evaluates), or {} when the kernels take none."""
    if not predicts(sp.model):
        return {}
    return {"t": ((np.arange(T) + 1.0) * sp.model.dt)[:, None]}


def model_parts(sp: SamplingProblem, c: dict, t: ca.SX | None = None
                ) -> tuple[Callable, Callable, ca.Function, ca.Function]:
    """(dyn, margins, q, phi) of the problem: ``dyn(x, v)`` and ``margins(x)`` evaluated in
    the kernel's ``scene`` symbol of ``c`` (the empty scene when it has none) or, with the time
    symbol ``t`` of :func:`time_symbol`, in the scene predicted to time t (moving circles at
    c + v t; ``dyn`` of step k and the margins of x_{k+1} both at t = (k + 1) dt), and the stage
    and final cost Functions ``q(x, p)`` and ``phi(x, p)``."""
    fns = sp.functions()
    s = c.get("scene", ca.SX(0, 1))
    if t is not None:
        s = scene_sx_at(sp.model, s, t)
    return (lambda x, v: fns["dyn"](x, v, s)), (lambda x: fns["margins"](x, s)), \
        fns["q"], fns["phi"]


def crashed_flag(margins: Callable, x, eps_h: float, nh: int):
    """1 if any of the nh margins at x is <= eps_h, else 0 (the constant 0 when nh == 0);
    formed with the barrier's :func:`~workbench.problem.barrier.min_margin`, like its crash
    rule, so CSE shares the margins with the cost."""
    if nh == 0:
        return ca.SX(0)
    return min_margin(margins(x), range(nh)) <= eps_h


def near_crash_flag(margins: Callable, x, eps_h: float, nh: int, band):
    """1 if the smallest margin at x is within ``band`` of eps_h, |min_i h_i - eps_h| <= band
    (the float32 kernels' guard), else 0 (the constant 0 when nh == 0)."""
    if nh == 0:
        return ca.SX(0)
    return ca.fabs(min_margin(margins(x), range(nh)) - eps_h) <= band


__all__ = ["clip", "crashed_flag", "kernel_symbols", "model_parts", "near_crash_flag",
           "step_times", "time_symbol"]

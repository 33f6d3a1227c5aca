"""The safe-MPPI kernel: MPPI rollouts whose sample controls may be projected onto the discrete
CBF constraints (:mod:`workbench.problem.dcbf`) and whose costs may carry the DCBF violation,
in its own lazily built, verified library (like the diagnostics library: plain sampler calls
neither compile nor run anything extra).

Per rollout step k of a sample (x_k its state, u_k the plan, z_k standard normals):

1. v0 = clip(u_k + sigma z_k) (the plain MPPI sample control);
2. projection (Tao, Kim, Yoon, Hovakimyan, Voulgaris, "Control Barrier Function Augmentation in
   Sampling-based Control Algorithm for Sample Efficiency", ACC 2022, arXiv:2111.06974): when
   ``project`` is 1, the constraints c_i(x_k, v0) and their u-gradients g_i are evaluated, the
   most restrictive one i* = argmin_i c_i is taken (the first on ties), and when c_{i*} < 0
   the control moves to the minimum-norm point of its linearisation,
   v1 = v0 + (-c_{i*} / |g_{i*}|^2) g_{i*} (no move when g_{i*} = 0), clipped to the box:
   v_hat = clip(v1). Otherwise v_hat = v0. The selection and the move are exact 0/1
   arithmetic blends (no branch in the lane loop);
3. x_{k+1} = f(x_k, v_hat), the crash rule of the MPPI kernel, and the step cost
   q(x_{k+1}) + C_crash crashed + lambda (1 - nu_mix) / 2 (u' Sigma^-1 u + 2 u' Sigma^-1 eps_hat)
   + w_dcbf sum_i max(0, -c_i(x_k, v_hat)),
   the last term the DCBF violation cost of Shield-MPPI (Yin, Dawson, Fan, Tsiotras,
   "Shield Model Predictive Path Integral", arXiv:2302.11719).

Likelihood ratio and control cost: the projection is treated like the clip. The applied
control is v_hat = u + eps_hat with the *effective* noise eps_hat = v_hat - u, and the
likelihood-ratio/control-cost term is formed from eps_hat exactly as the MPPI kernel forms it
from the clipped noise; the update averages the applied controls v_hat (lane output), so the
plan moves towards what the samples actually did.

Per-sample counts: ``projected`` the steps where the projection acted (project = 1 and
c_{i*}(x_k, v0) < 0); ``infeasible`` those of them where the applied v_hat still violates
some constraint at the exact (not linearised) c: min_i c_i(x_k, v_hat) < -:data:`INFEASIBLE_TOL`.
For squared-distance margins and linear dynamics c_i is convex in u (c_i(v) = c_i(v0) +
g_i'(v - v0) + dt^4 |v - v0|^2 for the double integrator), so the linearised step satisfies
the chosen constraint exactly unless the box clips it; the tolerance only absorbs rounding.
``dcbf`` the violation sum_k sum_i max(0, -c_i(x_k, v_hat_k)) (without the weight).

Run-time constants: the MPPI kernel's (sigma, lr, u_min, u_max, crash, p, scene) plus
``project`` (0/1), ``w_dcbf`` (>= 0) and ``gamma`` (in (0, 1]).

Moving circles (a scene with moving slots): like the MPPI kernel, step k takes the time input
t = (k + 1) dt; the dynamics and the crash test of x_{k+1} see the scene predicted to t, the
constraints c_i(x_k, .) the scene predicted to x_k's time t - dt (the obstacles held where they
are at step k over that one step: the discrete CBF is of one scene).
"""

from __future__ import annotations

import ctypes
from dataclasses import dataclass

import casadi as ca
import numpy as np

from workbench.problem.barrier import min_margin
from workbench.problem.dcbf import DiscreteCBF, discrete_cbf
from workbench.problem.prediction import scene_sx_at
from workbench.sampling.kernels.compiled import CompiledKernel
from workbench.sampling.kernels.emit import KernelSpec
from workbench.sampling.kernels.layout import Layout
from workbench.sampling.kernels.library import (
    compiled_or_twin,
    kernel_source,
    load_verified,
    set_threads,
)
from workbench.sampling.kernels.vocabulary import (
    clip,
    crashed_flag,
    kernel_symbols,
    model_parts,
    time_symbol,
)
from workbench.sampling.problem import SamplingProblem

_OPTS = {"cse": True}
# Absolute, in the units of c (the margins' units: m^2 for squared-distance margins). c is a
# sum of margin values of size up to ~100 m^2 on the navigation map, so its rounding is
# ~1e-13; a violation below 1e-9 is rounding, not an infeasible projection.
INFEASIBLE_TOL = 1e-9
SAFE_CONSTS = ("project", "w_dcbf", "gamma")


def safe_layouts(sp: SamplingProblem) -> tuple[Layout, Layout]:
    """(carry, result) of the safe kernel."""
    counts = (("crashed", 1), ("projected", 1), ("infeasible", 1), ("dcbf", 1))
    return (Layout(name="safe carry", fields=(("x", sp.nx), ("S", 1), *counts)),
            Layout(name="safe result", fields=(("S", 1), *counts)))


def most_restrictive(c: ca.SX, J: ca.SX) -> tuple[ca.SX, ca.SX]:
    """(c_{i*}, g_{i*}) with i* = argmin_i c_i (the first on ties), by exact 0/1 blends:
    c (nh,), J (nh, nu) -> scalar, (nu,)."""
    cmin, g = c[0], J[0, :].T
    for i in range(1, c.numel()):
        take = c[i] < cmin
        cmin = take * c[i] + (1.0 - take) * cmin
        g = take * J[i, :].T + (1.0 - take) * g
    return cmin, g


def projection(cbf: DiscreteCBF, x, v0, gamma, scene, lo, hi, enable) -> tuple[ca.SX, ca.SX]:
    """(v_hat, acted): the closed-form projection of v0 (already in the box) onto the
    linearisation of the most restrictive constraint, then clipped to [lo, hi]; ``acted`` is
    enable * (c_{i*}(x, v0) < 0). With ``enable`` 0 (or no violation) v_hat = v0 exactly."""
    c = cbf.c(x, v0, gamma, scene)
    J = cbf.jacobian(x, v0, gamma, scene)
    cmin, g = most_restrictive(c, J)
    acted = enable * (cmin < 0)
    gg = ca.dot(g, g)
    mu = (acted * (-cmin)) / (gg + (gg <= 0))  # 0 when the projection does not act
    return clip(v0 + mu * g, lo, hi), acted


def projection_function(cbf: DiscreteCBF) -> ca.Function:
    """(x, v0, gamma, scene, u_min, u_max) -> (v_hat, acted, c_min): :func:`projection` with
    enable = 1 as a CasADi Function, and min_i c_i(x, v_hat): the applied control's projection
    of :class:`~workbench.sampling.methods.cbf_projection.CBFProjectionMPPI` and one repair step
    of :class:`~workbench.sampling.methods.shield.ShieldMPPI`."""
    m = cbf.model
    x, v0 = ca.SX.sym("x", m.nx), ca.SX.sym("v0", m.nu)
    gamma, s = ca.SX.sym("gamma"), ca.SX.sym("scene", m.n_scene)
    lo, hi = ca.SX.sym("u_min", m.nu), ca.SX.sym("u_max", m.nu)
    v, acted = projection(cbf, x, v0, gamma, s, lo, hi, 1.0)
    cmin = min_margin(cbf.c(x, v, gamma, s), range(cbf.nh))
    return ca.Function("dcbf_project", [x, v0, gamma, s, lo, hi], [v, acted, cmin],
                       ["x", "v0", "gamma", "scene", "u_min", "u_max"],
                       ["v_hat", "acted", "c_min"], _OPTS)


def safe_spec(sp: SamplingProblem, name: str = "wb_safe") -> KernelSpec:
    """The safe-MPPI rollout (see module docstring); lane output ``v`` (v_hat)."""
    nx, nu, nh = sp.nx, sp.nu, sp.model.nh
    cbf = discrete_cbf(sp.model)
    c = kernel_symbols(sp)
    project, w_dcbf, gamma = (ca.SX.sym(n) for n in SAFE_CONSTS)
    t = time_symbol(sp)
    dyn, margins, q, phi = model_parts(sp, c, t)
    s = c.get("scene", ca.SX(0, 1))
    if t is not None:
        # the constraints of step k at the scene of x_k's time (obstacles held over the step)
        s = scene_sx_at(sp.model, s, t - sp.model.dt)
    carry = ca.SX.sym("carry", nx + 5)
    z, u = ca.SX.sym("z", nu), ca.SX.sym("u", nu)
    x, S, cr, npr, ninf, viol = (carry[:nx], *(carry[nx + i] for i in range(5)))
    v0 = clip(u + c["sigma"] * z, c["u_min"], c["u_max"])
    v, acted = projection(cbf, x, v0, gamma, s, c["u_min"], c["u_max"], project)
    ch = cbf.c(x, v, gamma, s)
    infeasible = acted * (min_margin(ch, range(nh)) < -INFEASIBLE_TOL)
    step_viol = ca.sum1(ca.fmax(-ch, 0.0))
    eps = v - u
    xn = dyn(x, v)
    crn = ca.fmax(cr, crashed_flag(margins, xn, sp.eps_h, nh))
    inv = 1.0 / (c["sigma"] * c["sigma"])
    lr = 0.5 * c["lr"] * (ca.dot(u * inv, u) + 2.0 * ca.dot(u * inv, eps))
    Sn = S + (q(xn, c["p"]) + c["crash"][0] * crn) + lr + w_dcbf * step_viol
    ins = {"carry": carry, "z": z, "u": u, **({"t": t} if t is not None else {}), **c,
           "project": project, "w_dcbf": w_dcbf, "gamma": gamma}
    new = ca.vertcat(xn, Sn, crn, npr + acted, ninf + infeasible, viol + step_viol)
    step = ca.Function(name + "_step", list(ins.values()), [new, v], list(ins),
                       ["carry_next", "v"], _OPTS)
    final = ca.Function(name + "_final", [carry, c["p"]],
                        [ca.vertcat(S + phi(x, c["p"]), cr, npr, ninf, viol)],
                        ["carry", "p"], ["result"], _OPTS)
    roles = {"carry": "carry", "z": "noise", "u": "time", "t": "time",
             **{k: "const" for k in ins if k not in ("carry", "z", "u", "t")}}
    return KernelSpec(name=name, step=step, final=final, roles=roles)


@dataclass(frozen=True, eq=False)
class SafeLibrary:
    """The safe kernel of one sampling problem, in its own cached shared library."""

    safe: CompiledKernel
    cdll: ctypes.CDLL

    def normals(self, N: int, T: int, m: int, seed: int) -> np.ndarray:
        """The standard normals (T, m, N) the kernel draws with the same seed."""
        out = np.empty((T, m, N))
        self.cdll.wb_normals(N, T, m, ctypes.c_ulonglong(int(seed) & (2**64 - 1)),
                             ctypes.c_void_p(out.__array_interface__["data"][0]))
        return out

    def set_threads(self, n: int) -> None:
        """:func:`~workbench.sampling.kernels.library.set_threads` (every kernel library)."""
        set_threads(n)


def _build(cdll: ctypes.CDLL, spec: KernelSpec, sp: SamplingProblem) -> SafeLibrary:
    cdll.wb_normals.restype = None
    cdll.wb_normals.argtypes = [ctypes.c_int] * 3 + [ctypes.c_ulonglong, ctypes.c_void_p]
    cdll.wb_set_threads.argtypes = [ctypes.c_int]
    return SafeLibrary(safe=CompiledKernel(spec, cdll, *safe_layouts(sp)), cdll=cdll)


_LIBS: dict[str, SafeLibrary | None] = {}
_FALLBACK_WARNED: set[str] = set()


def safe_library(sp: SamplingProblem) -> SafeLibrary | None:
    """Build (or load from the cache) and verify the safe kernel of a sampling problem, once per
    process (keyed by the problem's fingerprint); None without a compiler, or, with one
    warning, when the emitter or the C back end cannot compile the model (the NumPy twin,
    :mod:`workbench.sampling.methods.twin`, is then used)."""
    def build() -> SafeLibrary | None:  # load_verified applies the set_threads count
        spec = safe_spec(sp)
        return load_verified(f"safe_{sp.model.name.replace('+', '_')}", kernel_source([spec]),
                             lambda cdll: _build(cdll, spec, sp), lambda lib: (lib.safe,))

    return compiled_or_twin(_LIBS, _FALLBACK_WARNED, sp.fingerprint(), build,
                            "safe-MPPI kernel", sp.model.name)


__all__ = ["INFEASIBLE_TOL", "SafeLibrary", "most_restrictive", "projection",
           "projection_function", "safe_layouts", "safe_library", "safe_spec"]

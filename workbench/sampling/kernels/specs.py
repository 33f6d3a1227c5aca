"""The sampler's kernel specs: MPPI rollouts, the SAIS dual rollout of Algorithm 1 and the RMPPI
candidate evaluation, as CasADi step and final Functions with their input roles
(:class:`~workbench.sampling.kernels.emit.KernelSpec`), emitted by :mod:`.emit` (straight-line)
or :mod:`.slots` (loop over the scene's circle slots) and loaded by :mod:`.library`.

Run-time constants (``const`` role, shared by all samples):
  sigma (nu) sampling std, lr (1) = lambda (1 - nu_mix), u_min, u_max (nu), crash (1) =
  C_crash, p (n_p) cost parameters, scene (n_scene, when the model has a run-time scene) the
  obstacles, alpha (1) the RMPPI threshold and inv_var (nu) = 1 / sigma^2 (SAIS only: its
  likelihood-ratio terms multiply by it instead of dividing by sigma^2 per sample, four
  divisions fewer per sample and step, measured 5% of the navigation SAIS rollout).
Per-time inputs: u (nu) the importance-sampling sequence; SAIS also K (nu*nx, row-major K_k);
t (1) when the scene has moving circles: the time of the state x_{k+1} that step k computes,
(k + 1) dt (:func:`~workbench.sampling.kernels.vocabulary.step_times`); the step's dynamics and
the crash test of x_{k+1} then see the moving circles at c + v t (the scene predicted to that
time, :meth:`~workbench.problem.scene_layout.SceneLayout.predicted_sx`). Other models' kernels
take no ``t`` (they are exactly those of a model without moving obstacles).
Carries and results are named by :func:`layouts` (one :class:`Layout` per kernel and role).

Float32 kernels (``precision="float32"``, their own library ``sampler_<model>_f32``) compute the
same rollouts in float with the cost sums in double (:mod:`.emit`: a step's cost is formed in
float and added to a double sum; 0/1 crash flags are exact in float), and add a
per-sample ``guard`` flag and the const input ``guard`` (the band g): the flag is 1 when, at its
crash step or before it (a system that has not crashed yet), the smallest margin lies within g
of the crash margin, |min_i h_i - eps_h| <= g, where the float crash decision may differ from
the double one; :class:`~workbench.sampling.sampler.Sampler` recomputes those samples in
double. Outside the band, float and double decide every step's crash test alike whenever their
margins differ by less than g, so crash flags and crash steps agree.
"""

from __future__ import annotations

import casadi as ca

from workbench.sampling.kernels.emit import KernelSpec
from workbench.sampling.kernels.flags import is_float32
from workbench.sampling.kernels.layout import Layout
from workbench.sampling.kernels.vocabulary import (
    clip,
    crashed_flag,
    kernel_symbols,
    model_parts,
    near_crash_flag,
    time_symbol,
)
from workbench.sampling.problem import SamplingProblem

_OPTS = {"cse": True}


def layouts(sp: SamplingProblem, kernel: str,
            precision: str = "float64") -> tuple[Layout, Layout]:
    """(carry, result) layouts of a kernel ("mppi", "sais" or "candidates"); the specs below
    index their carries in this order. Float32 kernels add a ``guard`` field to both."""
    nx = sp.nx
    carry: tuple[tuple[str, int], ...]
    result: tuple[tuple[str, int], ...]
    if kernel == "sais":
        carry = (("x", nx), ("x_nom", nx), ("S_state_nom", 1), ("S_hat", 1), ("S_real", 1),
                 ("LR", 1), ("crashed_real", 1), ("crashed_nom", 1))
        result = (("S_nom", 1), ("S_real", 1), ("S_state_nom", 1), ("S_hat", 1), ("LR", 1),
                  ("crashed_real", 1), ("crashed_nom", 1))
    else:
        carry = (("x", nx), ("S", 1), ("crashed", 1))
        if kernel == "candidates":
            carry += (("delay", 1), ("stride", 1))
        result = (("S", 1), ("crashed", 1))
    if is_float32(precision):
        carry, result = (*carry, ("guard", 1)), (*result, ("guard", 1))
    tag = " (float32)" if precision == "float32" else ""
    return (Layout(name=f"{kernel} carry{tag}", fields=carry),
            Layout(name=f"{kernel} result{tag}", fields=result))


def mppi_spec(sp: SamplingProblem, name: str = "wb_mppi", strided: bool = False,
              precision: str = "float64") -> KernelSpec:
    """MPPI rollout (assumptions §8.1 with the crash rule of 4.6).

    ``strided`` (RMPPI candidates, assumptions §9.3) adds per-sample ``delay`` and ``stride`` s in
    {0, 1} as carry entries after the crash flag: the sample follows u_{min(t+s, T-1)} (time
    input ``u_next`` holds the shifted sequence) and draws no noise while delay > 0. A float32
    kernel (named ``<name>_f32``) ends its carry with the guard flag.
    """
    nx, nu, nh = sp.nx, sp.nu, sp.model.nh
    f32 = is_float32(precision)
    c = kernel_symbols(sp)
    if f32:
        c["guard"] = ca.SX.sym("guard")
    t = time_symbol(sp)
    dyn, margins, q, phi = model_parts(sp, c, t)
    carry = ca.SX.sym("carry", nx + 2 + 2 * int(strided) + int(f32))
    z, u_in, u_next = ca.SX.sym("z", nu), ca.SX.sym("u", nu), ca.SX.sym("u_next", nu)
    x, S, cr = carry[:nx], carry[nx], carry[nx + 1]
    noise, u = c["sigma"] * z, u_in
    if strided:
        delay, stride = carry[nx + 2], carry[nx + 3]
        # arithmetic blends, exact for 0/1 weights: a select here makes gcc turn the time-input
        # loads into masked loads, which stops it vectorising the lane loop
        noise = noise * (delay <= 0)
        u = (1.0 - stride) * u_in + stride * u_next
    v = clip(u + noise, c["u_min"], c["u_max"])
    eps = v - u
    xn = dyn(x, v)
    crn = ca.fmax(cr, crashed_flag(margins, xn, sp.eps_h, nh))
    inv = 1.0 / (c["sigma"] * c["sigma"])
    lr = 0.5 * c["lr"] * (ca.dot(u * inv, u) + 2.0 * ca.dot(u * inv, eps))
    Sn = S + (q(xn, c["p"]) + c["crash"][0] * crn) + lr
    ins = {"carry": carry, "z": z, "u": u_in, **({"u_next": u_next} if strided else {}),
           **({"t": t} if t is not None else {}), **c}
    new = [xn, Sn, crn] + ([carry[nx + 2] - 1, carry[nx + 3]] if strided else [])
    res = [S + phi(x, c["p"]), cr]
    if f32:
        g = carry[carry.numel() - 1]
        # the crash step and the steps before it (a crashed sample's flag no longer changes)
        near = near_crash_flag(margins, xn, sp.eps_h, nh, c["guard"])
        new.append(ca.fmax(g, (1.0 - cr) * near))
        res.append(g)
        name += "_f32"
    step = ca.Function(name + "_step", list(ins.values()), [ca.vertcat(*new), v],
                       list(ins), ["carry_next", "v"], _OPTS)
    final = ca.Function(name + "_final", [carry, c["p"]],
                        [ca.vertcat(*res)], ["carry", "p"], ["result"], _OPTS)
    roles = {"carry": "carry", "z": "noise", "u": "time", "u_next": "time", "t": "time",
             **{k: "const" for k in c}}
    return KernelSpec(name=name, step=step, final=final, roles=roles, precision=precision,
                      wide=(nx,) if f32 else ())  # the cost sum


def candidate_spec(sp: SamplingProblem, precision: str = "float64") -> KernelSpec:
    """RMPPI candidate evaluation (assumptions §9.3): strided MPPI rollouts, no feedback."""
    return mppi_spec(sp, "wb_candidates", strided=True, precision=precision)


def sais_spec(sp: SamplingProblem, name: str = "wb_sais", precision: str = "float64") -> KernelSpec:
    """The SAIS dual rollout of Algorithm 1 (assumptions §10.1); clip_in_cost is a run-time input. A
    float32 kernel (``<name>_f32``) ends its carry with the guard flag of both systems."""
    nx, nu, nh = sp.nx, sp.nu, sp.model.nh
    f32 = is_float32(precision)
    c = kernel_symbols(sp)
    if f32:
        c["guard"] = ca.SX.sym("guard")
    c["inv_var"] = ca.SX.sym("inv_var", nu)  # 1 / sigma^2, computed once per batch
    t = time_symbol(sp)
    dyn, margins, q, phi = model_parts(sp, c, t)
    alpha, clip_cost = ca.SX.sym("alpha"), ca.SX.sym("clip_cost")
    carry = ca.SX.sym("carry", 2 * nx + 6 + int(f32))
    z, u, Kv = ca.SX.sym("z", nu), ca.SX.sym("u", nu), ca.SX.sym("K", nu * nx)
    x, xs = carry[:nx], carry[nx : 2 * nx]
    Sn, Sh, Sr, LR, cr, cn = (carry[2 * nx + i] for i in range(6))
    K = ca.reshape(Kv, nx, nu).T
    eps = c["sigma"] * z
    kfb = ca.mtimes(K, x - xs)
    vr = clip(u + eps + kfb, c["u_min"], c["u_max"])
    vn = clip(u + eps, c["u_min"], c["u_max"])
    # clip_in_cost (assumptions §10.1): effective (clipped) noise and feedback in lines 8, 9 and 12
    # when 1, the raw ones when 0 (exact 0/1 blends)
    et = clip_cost * (vn - u) + (1.0 - clip_cost) * eps
    kt = clip_cost * (vr - u - (vn - u)) + (1.0 - clip_cost) * kfb
    xn, xsn = dyn(x, vr), dyn(xs, vn)
    crn = ca.fmax(cr, crashed_flag(margins, xn, sp.eps_h, nh))
    cnn = ca.fmax(cn, crashed_flag(margins, xsn, sp.eps_h, nh))
    qr = q(xn, c["p"]) + c["crash"][0] * crn
    qn = q(xsn, c["p"]) + c["crash"][0] * cnn
    inv = c["inv_var"]  # a product with 1 / (sigma sigma) would become a division in CasADi
    half = 0.5 * c["lr"]
    Sh = Sh + (qr + half * ca.dot(kt * inv, kt))
    Sn = Sn + qn
    Sr = Sr + (qr + half * ca.dot((u + kt) * inv, u + 2.0 * et + kt))
    LR = LR + half * (ca.dot(u * inv, u) + 2.0 * ca.dot(u * inv, et))
    ins = {"carry": carry, "z": z, "u": u, "K": Kv, **({"t": t} if t is not None else {}), **c,
           "alpha": alpha, "clip_cost": clip_cost}
    new = [xn, xsn, Sn, Sh, Sr, LR, crn, cnn]
    fx, fxs = phi(x, c["p"]), phi(xs, c["p"])
    Shf, Snf, Srf = carry[2 * nx + 1] + fx, carry[2 * nx] + fxs, carry[2 * nx + 2] + fx
    S_nom = 0.5 * Snf + 0.5 * ca.fmax(ca.fmin(Shf, alpha), Snf) + carry[2 * nx + 3]
    res = [S_nom, Srf, Snf, Shf, carry[2 * nx + 3], carry[2 * nx + 4], carry[2 * nx + 5]]
    if f32:
        g = carry[2 * nx + 6]
        near = ca.fmax((1.0 - cr) * near_crash_flag(margins, xn, sp.eps_h, nh, c["guard"]),
                       (1.0 - cn) * near_crash_flag(margins, xsn, sp.eps_h, nh, c["guard"]))
        new.append(ca.fmax(g, near))
        res.append(g)
        name += "_f32"
    step = ca.Function(name + "_step", list(ins.values()),
                       [ca.vertcat(*new), vn, vr],
                       list(ins), ["carry_next", "v_nom", "v_real"], _OPTS)
    final = ca.Function(name + "_final", [carry, c["p"], alpha],
                        [ca.vertcat(*res)], ["carry", "p", "alpha"], ["result"], _OPTS)
    roles = {"carry": "carry", "z": "noise", "u": "time", "K": "time", "t": "time",
             "alpha": "const",
             "clip_cost": "const",
             **{k: "const" for k in c}}
    return KernelSpec(name=name, step=step, final=final, roles=roles, precision=precision,
                      wide=tuple(range(2 * nx, 2 * nx + 4)) if f32 else ())  # cost sums

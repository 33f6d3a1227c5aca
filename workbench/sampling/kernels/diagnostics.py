"""Diagnostic kernels for the Lemma-1 checks (assumptions §11.2), in their own cached library.

* ``wb_sais_diag`` — the SAIS dual rollout of :func:`~workbench.sampling.kernels.specs.sais_spec`
  unchanged (its step Function is called inside this one, so every SAIS output is bitwise the
  main kernel's for the same seed), plus the post-step states of both systems as lane outputs
  (T, nx, N) and the pure state costs Σ_{k=1}^T q(x_k) + φ(x_T) of the real and the nominal
  sample (no crash cost, no control or feedback cost) as two more carries/results.
* ``wb_cost_gradients`` — for per-sample segment end points x (real) and x* (nominal) given as
  lane inputs (T, nx, N): the largest ‖∇q̃‖² and ‖∇φ̃‖² at x* + s (x − x*), s ∈ {0, ¼, ½, ¾, 1},
  over the steps where the time weights ``wq``/``wphi`` are 1, the squared secant ratios
  (q̃(x) − q̃(x*))² / ‖x − x*‖², and counts of points excluded because min h ≤ 0 (squares: no
  sqrt in the lane loop, which would stop it vectorising). q̃(y) =
  q(lift(y), p) is the state cost as a function of the *physical* state y (β = B(h(y)), which is
  what β is on every sample with γ = 0); gradients are CasADi's exact ones, norms Euclidean in
  the physical state. ``wb_cost_gradients_aug`` does the same in the augmented state x̄ = [x; β]
  (β a coordinate, segments and norms in x̄), assumptions §11.2 item 5's alternative.

The main sampler library is left alone: this library is built on first use of diagnostics, so
plain SAIS calls neither compile nor run anything extra.
"""

from __future__ import annotations

import ctypes
import hashlib
from dataclasses import dataclass

import casadi as ca
import numpy as np

from workbench.sampling.kernels.compiled import CompiledKernel
from workbench.sampling.kernels.emit import KernelSpec
from workbench.sampling.kernels.layout import Layout
from workbench.sampling.kernels.library import kernel_source, load_verified
from workbench.sampling.kernels.specs import layouts, sais_spec
from workbench.sampling.problem import SamplingProblem

_OPTS = {"cse": True}
SEGMENT_POINTS = (0.0, 0.25, 0.5, 0.75, 1.0)  # assumptions §11.2 item 6
GRADIENT_RESULTS = ("L2_q", "L2_phi", "sec2_q", "sec2_phi", "excluded_q", "excluded_phi",
                    "points_q", "points_phi")


def diag_layouts(sp: SamplingProblem) -> tuple[Layout, Layout]:
    """(carry, result) of ``wb_sais_diag``: the SAIS layouts + Sx_real, Sx_nom."""
    carry, result = layouts(sp, "sais")
    extra = (("Sx_real", 1), ("Sx_nom", 1))
    return (Layout(name="sais_diag carry", fields=carry.fields + extra),
            Layout(name="sais_diag result", fields=result.fields + extra))


def sais_diag_spec(sp: SamplingProblem, name: str = "wb_sais_diag") -> KernelSpec:
    """SAIS with trajectories and pure state costs (see module docstring)."""
    base = sais_spec(sp, name + "_base")
    nx = sp.nx
    f = sp.functions()
    q, phi = f["q"], f["phi"]
    st = base.step
    nc = base.n_carry
    ins = {n: ca.SX.sym(n, st.size_in(i)) for i, n in enumerate(st.name_in())}
    carry = ca.SX.sym("carry", nc + 2)
    call = dict(ins, carry=carry[:nc])
    out = st.call(call)
    cn = out["carry_next"]
    xn, xsn = cn[:nx], cn[nx : 2 * nx]
    Sxr = carry[nc] + q(xn, ins["p"])
    Sxn = carry[nc + 1] + q(xsn, ins["p"])
    ins["carry"] = carry
    step = ca.Function(name + "_step", list(ins.values()),
                       [ca.vertcat(cn, Sxr, Sxn), out["v_nom"], out["v_real"], xn, xsn],
                       list(ins), ["carry_next", "v_nom", "v_real", "x", "x_nom"], _OPTS)
    p, alpha = ca.SX.sym("p", sp.n_p), ca.SX.sym("alpha")
    res = base.final(carry[:nc], p, alpha)
    x, xs = carry[:nx], carry[nx : 2 * nx]
    final = ca.Function(name + "_final", [carry, p, alpha],
                        [ca.vertcat(res, carry[nc] + phi(x, p), carry[nc + 1] + phi(xs, p))],
                        ["carry", "p", "alpha"], ["result"], _OPTS)
    return KernelSpec(name=name, step=step, final=final, roles=dict(base.roles))


SPACES = ("physical", "augmented")


def composed_costs(sp: SamplingProblem, space: str = "physical"):
    """(y, p, q, φ, min h) as expressions of the point symbol y: ``"physical"`` — y is the
    physical state and β = lift(y) (q̃, φ̃); ``"augmented"`` — y is the full state x̄ (β a
    coordinate), min h from its physical part. The obstacles are the model's own scene
    (``model.scene_value``), compiled in: these are diagnostics of one scene."""
    m = sp.model
    n = m.n_physical
    y = ca.SX.sym("y", n if space == "physical" else sp.nx)
    p = ca.SX.sym("p", sp.n_p)
    xb = m.lift_function(y, m.scene_value) if space == "physical" else y
    f = sp.functions()
    qt, pt = f["q"](xb, p), f["phi"](xb, p)
    if m.nh:
        h = m.margins_function(y[:n], m.scene_value)
        mh = h[0]
        for i in range(1, m.nh):
            mh = ca.fmin(mh, h[i])
    else:
        mh = ca.SX(1.0)
    return y, p, qt, pt, mh


def gradient_spec(sp: SamplingProblem, space: str = "physical",
                  name: str | None = None) -> KernelSpec:
    """Segment gradient maxima, secants and exclusions (see module docstring); ``space`` as
    in :func:`composed_costs` (norms and segments in that space)."""
    if space not in SPACES:
        raise ValueError(f"space = {space!r} is invalid: allowed values are {SPACES}")
    name = name or ("wb_cost_gradients" if space == "physical" else "wb_cost_gradients_aug")
    nx = sp.nx
    n = sp.model.n_physical if space == "physical" else nx
    y, p, qt, pt, mh = composed_costs(sp, space)
    gq_, gp_ = ca.gradient(qt, y), ca.gradient(pt, y)
    # squared norms: sqrt (an errno-setting libm call) would stop gcc vectorising the lane
    # loop; the maxima of squares are squared back in NumPy
    point = ca.Function("point", [y, p], [qt, pt, ca.dot(gq_, gq_), ca.dot(gp_, gp_), mh])
    carry = ca.SX.sym("carry", len(GRADIENT_RESULTS))
    x, xs = ca.SX.sym("x", nx), ca.SX.sym("x_nom", nx)
    wq, wphi = ca.SX.sym("wq"), ca.SX.sym("wphi")
    a, b = xs[:n], x[:n]
    Lq, Lp, sq, sph, eq, ep, nq, npt = (carry[i] for i in range(len(GRADIENT_RESULTS)))
    allok = ca.SX(1.0)
    vals = []
    for s in SEGMENT_POINTS:
        qv, pv, gq, gp, h = point(a + s * (b - a), p)
        ok = h > 0
        allok = allok * ok
        # selects, not products: excluded points may carry inf/NaN gradients
        Lq = ca.fmax(Lq, ca.if_else(ok * wq, gq, 0.0))
        Lp = ca.fmax(Lp, ca.if_else(ok * wphi, gp, 0.0))
        eq = eq + wq * (1 - ok)
        ep = ep + wphi * (1 - ok)
        vals.append((qv, pv))
    d2 = ca.dot(b - a, b - a)
    use = allok * (d2 > 0)
    dq, dp = vals[-1][0] - vals[0][0], vals[-1][1] - vals[0][1]
    sq = ca.fmax(sq, ca.if_else(use * wq, dq * dq / d2, 0.0))
    sph = ca.fmax(sph, ca.if_else(use * wphi, dp * dp / d2, 0.0))
    nq = nq + wq * len(SEGMENT_POINTS)
    npt = npt + wphi * len(SEGMENT_POINTS)
    ins = {"carry": carry, "x": x, "x_nom": xs, "wq": wq, "wphi": wphi, "p": p}
    step = ca.Function(name + "_step", list(ins.values()),
                       [ca.vertcat(Lq, Lp, sq, sph, eq, ep, nq, npt)], list(ins),
                       ["carry_next"], _OPTS)
    final = ca.Function(name + "_final", [carry], [carry], ["carry"], ["result"], _OPTS)
    roles = {"carry": "carry", "x": "lane", "x_nom": "lane", "wq": "time", "wphi": "time",
             "p": "const"}
    return KernelSpec(name=name, step=step, final=final, roles=roles)


@dataclass(frozen=True, eq=False)
class DiagnosticsLibrary:
    sais_diag: CompiledKernel
    gradients: CompiledKernel  # physical space (q̃ = q∘lift)
    gradients_augmented: CompiledKernel  # augmented space (β a coordinate)
    cdll: ctypes.CDLL


_LIBS: dict[str, DiagnosticsLibrary | None] = {}


def diagnostics_library(sp: SamplingProblem) -> DiagnosticsLibrary | None:
    """Build (or load from the cache) the diagnostic kernels; None without a compiler. The
    gradient kernels are compiled for the model's own scene (one library per scene)."""
    scene = hashlib.sha256(np.ascontiguousarray(sp.model.scene_value).tobytes()).hexdigest()
    key = f"{sp.fingerprint()}_{scene[:12]}"
    if key not in _LIBS:
        specs = [sais_diag_spec(sp), gradient_spec(sp), gradient_spec(sp, "augmented")]
        source = kernel_source(specs)
        g = Layout(name="gradients carry", fields=tuple((r, 1) for r in GRADIENT_RESULTS))
        res = Layout(name="gradients result", fields=g.fields)

        def build(cdll) -> DiagnosticsLibrary:
            return DiagnosticsLibrary(
                sais_diag=CompiledKernel(specs[0], cdll, *diag_layouts(sp)),
                gradients=CompiledKernel(specs[1], cdll, g, res),
                gradients_augmented=CompiledKernel(specs[2], cdll, g, res), cdll=cdll)

        _LIBS[key] = load_verified(
            f"diag_{sp.model.name.replace('+', '_')}_{scene[:8]}", source, build,
            lambda lib: (lib.sais_diag, lib.gradients, lib.gradients_augmented))
    return _LIBS[key]

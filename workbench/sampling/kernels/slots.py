"""Sampler kernels that loop over the circle slots of the scene instead of unrolling them.

The straight-line kernels of :mod:`.emit` write every obstacle circle of the run-time scene into
the step body (its margin, its inverse-barrier term, its step of the crash test's min chain), so
the code grows with the number of circles and, past a few hundred, the step no longer fits the
instruction cache (measured: 0.064 ms per circle at 10-30 circles, 0.67 ms per circle at
300-1000, :mod:`benchmarks.growth`). The kernels here split the step into

* part A: the controls and the new physical state of each system (and, for a barrier with
  gamma != 0, the current one), written to per-lane arrays;
* the slot loop ``for (int j = ...; j < n_pairs; ++j)`` over pairs of circle slots, with the
  lane loop inside it (vectorised across samples): per pair and per state, the two margins
  h_a, h_b, the barrier term (h_a + h_b) / (h_a h_b) added to a running sum and the running
  min of the margins;
* part B: the barrier state from the sums (crash rule and cap), the crash flags, the costs.

Their code size does not depend on the number of circles. The operations and their order are
those of the straight-line kernel (:func:`workbench.problem.barrier._barrier_sum` pairs slots
(0, 1), (2, 3), ... and adds the terms from the first; the min chain starts at slot 0), so the
results are bitwise equal: the first pair is peeled from the loop (it starts the sum and the
chain), an odd last slot adds 1 / h after it.

Supported: models whose margins are exactly one per circle slot, every slot the same
expression of the state and its (x, y, r) (the built-in integrators and vehicles with a run-time
scene: double integrator, unicycle, ...), either plain (crash test only) or barrier-embedded
with the inverse barrier summed into one state (``BarrierOptions(kind="inverse",
grouping="sum")``, any gamma); float64. Anything else raises :class:`SlotLoopUnsupported`
naming it; the library then keeps the straight-line kernel.

A :class:`SlotKernelSpec` carries the straight-line :class:`~.emit.KernelSpec` it replaces:
same name, inputs, roles, layouts and ``step`` Function (which
:class:`~workbench.sampling.kernels.compiled.CompiledKernel` and the load-time verification use),
so the library calls either kernel the same way.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca

from workbench.problem.barrier import BarrierOptions, min_margin
from workbench.problem.obstacles import SLOT
from workbench.sampling.kernels.emit import (
    WB_SCHEDULE,
    KernelSpec,
    final_input,
    result_layout,
    result_output,
    rng_source,
    step_input,
    step_output,
    straight_line,
)
from workbench.sampling.kernels.flags import kernel_flags
from workbench.sampling.kernels.specs import candidate_spec, mppi_spec, sais_spec
from workbench.sampling.kernels.vector_math import prelude
from workbench.sampling.kernels.vocabulary import clip
from workbench.sampling.problem import SamplingProblem

_OPTS = {"cse": True}
# scene slots from which a library should use the loop kernels. Measured (one thread, N 1024,
# T 100, SAIS batch, loop / straight-line): 1.02-1.10 at 1-10 slots, 0.92 at 30, 0.66 at 100,
# 0.10 at 1000; the SAIS kernel alone 0.95-1.0 at 10-24
DEFAULT_MIN_SLOTS = 24


class SlotLoopUnsupported(ValueError):
    """The problem or kernel cannot be written with a slot loop (the reason is the message)."""


@dataclass(frozen=True, eq=False)
class SlotKernelSpec:
    """A loop kernel: the straight-line ``spec`` it replaces and the parts of its step.

    ``part_a`` (the step's inputs) -> ``mid`` (controls, new physical states) and the lane
    outputs; ``head`` (mid, first slot or pair) -> acc; ``pair`` (mid, slot pair, acc) -> acc,
    None when there is only one pair; ``tail`` (mid, last slot, acc) -> acc, None for an even
    count; ``part_b`` (the step's inputs, mid, acc) -> the new carry. acc holds per state
    point [barrier sum (barrier models only), min margin]."""

    spec: KernelSpec
    part_a: ca.Function
    head: ca.Function
    pair: ca.Function | None
    tail: ca.Function | None
    part_b: ca.Function
    n_slots: int

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def n_pairs(self) -> int:
        return self.n_slots // 2

    def functions(self) -> list[ca.Function]:
        """Every SX Function the emitted kernel is written from."""
        return [f for f in (self.part_a, self.head, self.pair, self.tail, self.part_b,
                            self.spec.final) if f is not None]


# ---------------------------------------------------------------------------------------------
# what the model must be


@dataclass(frozen=True, eq=False)
class _SlotModel:
    """The pieces of a supported model: physical state size n, per-slot margin g(x_phys, s),
    barrier options (None: plain model)."""

    n: int
    g: ca.Function
    barrier: BarrierOptions | None
    n_slots: int


def unsupported_reason(sp: SamplingProblem, precision: str = "float64") -> str | None:
    """Why ``sp`` cannot have loop kernels of ``precision`` (None: it can)."""
    try:
        _slot_model(sp, precision)
    except SlotLoopUnsupported as exc:
        return str(exc)
    return None


def _slot_model(sp: SamplingProblem, precision: str = "float64") -> _SlotModel:
    m = sp.model
    what = f"slot-loop kernels for {m.name}"
    if precision != "float64":
        raise SlotLoopUnsupported(f"{what}: precision {precision!r} is not supported (float64 "
                                  "only); the straight-line kernel is kept")
    cap = int(m.scene_capacity)
    if cap < 1:
        raise SlotLoopUnsupported(f"{what}: the model has no circle slots in its run-time scene "
                                  "(scene_capacity = 0)")
    if m.nh != cap:
        raise SlotLoopUnsupported(f"{what}: the model has {m.nh} safety margins for {cap} "
                                  "circle slots; margins other than one per circle slot "
                                  "(state limits, other shapes) are not supported")
    n = m.n_physical
    spec = m.barrier
    if spec is not None:
        o = spec.options
        if o.kind != "inverse":
            raise SlotLoopUnsupported(f"{what}: barrier kind {o.kind!r} is not supported "
                                      "(only 'inverse')")
        if tuple(spec.groups) != (tuple(range(m.nh)),):
            raise SlotLoopUnsupported(f"{what}: barrier grouping {o.grouping!r} is not "
                                      "supported (only 'sum': one barrier state over all slots)")
        if m.nx != n + 1:
            raise SlotLoopUnsupported(f"{what}: expected one barrier state after the {n} "
                                      f"physical states, the model has {m.nx - n}")
    elif m.nx != n:
        raise SlotLoopUnsupported(f"{what}: states past the physical ones without a barrier "
                                  "spec are not supported")
    xp = m.x[:n]
    s3 = ca.SX.sym("slot", SLOT)
    scene = m.scene
    ref = ca.substitute(m.h[0], scene[0:SLOT], s3)
    allowed = {str(v) for v in ca.symvar(ca.vertcat(xp, s3))}
    extra = [str(v) for v in ca.symvar(ref) if str(v) not in allowed]
    if extra:
        raise SlotLoopUnsupported(f"{what}: the margin of slot 0 depends on {extra}, not only "
                                  "on the physical state and its own slot (x, y, r)")
    for i in range(1, cap):
        hi = ca.substitute(m.h[i], scene[SLOT * i: SLOT * i + SLOT], s3)
        if not ca.is_equal(hi, ref, 200):
            raise SlotLoopUnsupported(f"{what}: margin {i} is not the same expression of its "
                                      "slot as margin 0 (non-circle or per-slot margins are not "
                                      "supported)")
    g = ca.Function("slot_margin", [xp, s3], [ref], ["x", "slot"], ["h"], _OPTS)
    fns = sp.functions()
    x, v = ca.SX.sym("x", m.nx), ca.SX.sym("v", m.nu)
    phys = fns["dyn"](x, v, scene)[:n]
    if ca.depends_on(phys, scene) or (m.nx > n and ca.depends_on(phys, x[n:])):
        raise SlotLoopUnsupported(f"{what}: the physical dynamics depend on the scene or the "
                                  "barrier state")
    return _SlotModel(n=n, g=g, barrier=spec.options if spec is not None else None,
                      n_slots=cap)


# ---------------------------------------------------------------------------------------------
# the slot functions


def _slot_functions(sm: _SlotModel, n_mid: int, points: list[int]):
    """head, pair, tail Functions over the state points starting at mid offsets ``points``."""
    mid = ca.SX.sym("mid", n_mid)
    barrier = sm.barrier is not None
    per = 2 if barrier else 1
    acc = ca.SX.sym("acc", per * len(points))

    def margin(k: int, s):
        return sm.g(mid[k: k + sm.n], s)

    def pack(sums, mins):
        out = []
        for e in range(len(points)):
            out += ([sums[e]] if barrier else []) + [mins[e]]
        return ca.vertcat(*out)

    def old(e: int):
        return (acc[per * e] if barrier else None), acc[per * e + per - 1]

    s6, s3 = ca.SX.sym("slots", 2 * SLOT), ca.SX.sym("slot", SLOT)
    # head: the sum and the min chain start as in _barrier_sum / min_margin
    sums, mins = [], []
    for k in points:
        if sm.n_slots == 1:
            h = margin(k, s3)
            sums.append(1.0 / h)
            mins.append(min_margin(ca.vertcat(h), range(1)))
        else:
            ha, hb = margin(k, s6[:SLOT]), margin(k, s6[SLOT:])
            sums.append((ha + hb) / (ha * hb))
            mins.append(min_margin(ca.vertcat(ha, hb), range(2)))
    head = ca.Function("slot_head", [mid, s3 if sm.n_slots == 1 else s6],
                       [pack(sums, mins)], ["mid", "slot"], ["acc"], _OPTS)
    pair = tail = None
    if sm.n_slots // 2 > 1:
        sums, mins = [], []
        for e, k in enumerate(points):
            S, M = old(e)
            ha, hb = margin(k, s6[:SLOT]), margin(k, s6[SLOT:])
            if barrier:
                sums.append(S + (ha + hb) / (ha * hb))
            mins.append(ca.fmin(ca.fmin(M, ha), hb))
        pair = ca.Function("slot_pair", [mid, s6, acc], [pack(sums, mins)],
                           ["mid", "slot", "acc"], ["acc_next"], _OPTS)
    if sm.n_slots % 2 and sm.n_slots > 1:
        sums, mins = [], []
        for e, k in enumerate(points):
            S, M = old(e)
            h = margin(k, s3)
            if barrier:
                sums.append(S + 1.0 / h)
            mins.append(ca.fmin(M, h))
        tail = ca.Function("slot_tail", [mid, s3, acc], [pack(sums, mins)],
                           ["mid", "slot", "acc"], ["acc_next"], _OPTS)
    return head, pair, tail


def _beta(S, M, opts):
    """The barrier value of a state from its barrier sum S and min margin M (crash rule, cap),
    the expression of workbench.problem.barrier._barrier_values."""
    return ca.if_else(M <= opts.eps_h, opts.beta_max, ca.fmin(S, opts.beta_max))


class _Acc:
    """Symbols of the accumulated sums and mins, by state point."""

    def __init__(self, n_points: int, barrier: bool):
        self.per = 2 if barrier else 1
        self.sym = ca.SX.sym("acc", self.per * n_points)
        self.barrier = barrier

    def sum(self, e: int):
        return self.sym[self.per * e]

    def min(self, e: int):
        return self.sym[self.per * e + self.per - 1]


def _next_state(sm: _SlotModel, XN, beta, acc: _Acc, e_next: int, e_now: int | None):
    """The new full state: physical XN, and the barrier state from the accumulated values."""
    if sm.barrier is None:
        return XN
    o = sm.barrier
    nxt = _beta(acc.sum(e_next), acc.min(e_next), o)
    if o.gamma != 0.0:
        if e_now is None:
            raise ValueError("a barrier with gamma != 0 needs the accumulated values of the "
                             "current state (e_now)")
        now = _beta(acc.sum(e_now), acc.min(e_now), o)
        nxt = nxt - o.gamma * (beta - now)
    return ca.vertcat(XN, nxt)


def _inv_var(ins: dict):
    """1 / sigma^2: the const input ``inv_var`` when the straight-line step has one (computed
    once per batch), else formed in the step as the straight-line kernel does."""
    return ins["inv_var"] if "inv_var" in ins else 1.0 / (ins["sigma"] * ins["sigma"])


def _inputs(spec: KernelSpec) -> dict[str, ca.SX]:
    """Fresh symbols named and sized like the step's inputs."""
    st = spec.step
    return {n: ca.SX.sym(n, st.numel_in(i)) for i, n in enumerate(st.name_in())}


def _reference(kind: str, sp: SamplingProblem, name: str | None, precision: str) -> KernelSpec:
    if kind == "sais":
        return sais_spec(sp, name or "wb_sais", precision)
    if kind == "candidates":
        return candidate_spec(sp, precision)
    return mppi_spec(sp, name or "wb_mppi", precision=precision)


# ---------------------------------------------------------------------------------------------
# spec builders (the formulas of workbench.sampling.kernels.specs, split around the slots)


def mppi_slot_spec(sp: SamplingProblem, name: str = "wb_mppi", strided: bool = False,
                   precision: str = "float64",
                   reference: KernelSpec | None = None) -> SlotKernelSpec:
    """The loop version of :func:`~workbench.sampling.kernels.specs.mppi_spec` (``strided``:
    of the RMPPI candidate kernel). ``reference``: the straight-line spec (built when None)."""
    sm = _slot_model(sp, precision)
    spec = reference or _reference("candidates" if strided else "mppi", sp, name, precision)
    nx, nu, n = sp.nx, sp.nu, sm.n
    gamma = sm.barrier is not None and sm.barrier.gamma != 0.0
    fns = sp.functions()
    q = fns["q"]

    def common(ins):
        carry, c = ins["carry"], ins
        noise, u = c["sigma"] * ins["z"], ins["u"]
        if strided:
            delay, stride = carry[nx + 2], carry[nx + 3]
            noise = noise * (delay <= 0)
            u = (1.0 - stride) * ins["u"] + stride * ins["u_next"]
        return noise, u

    a = _inputs(spec)
    noise, u = common(a)
    x = a["carry"][:nx]
    v = clip(u + noise, a["u_min"], a["u_max"])
    xn = fns["dyn"](x, v, a["scene"])[:n]
    mids = [v, xn] + ([x[:n]] if gamma else [])
    part_a = ca.Function(spec.name + "_a", list(a.values()), [ca.vertcat(*mids), v],
                         list(a), ["mid", "v"], _OPTS)
    n_mid = nu + n + (n if gamma else 0)
    points = [nu] + ([nu + n] if gamma else [])
    head, pair, tail = _slot_functions(sm, n_mid, points)

    b = _inputs(spec)
    mid = ca.SX.sym("mid", n_mid)
    acc = _Acc(len(points), sm.barrier is not None)
    carry = b["carry"]
    _, u = common(b)
    S, cr = carry[nx], carry[nx + 1]
    V, XN = mid[:nu], mid[nu: nu + n]
    eps = V - u
    xnf = _next_state(sm, XN, carry[n:nx] if nx > n else None, acc, 0, 1 if gamma else None)
    crn = ca.fmax(cr, acc.min(0) <= sp.eps_h)
    inv = _inv_var(b)
    lr = 0.5 * b["lr"] * (ca.dot(u * inv, u) + 2.0 * ca.dot(u * inv, eps))
    Sn = S + (q(xnf, b["p"]) + b["crash"][0] * crn) + lr
    new = [xnf, Sn, crn] + ([carry[nx + 2] - 1, carry[nx + 3]] if strided else [])
    part_b = ca.Function(spec.name + "_b", [*b.values(), mid, acc.sym],
                         [ca.vertcat(*new)], [*b, "mid", "acc"], ["carry_next"], _OPTS)
    return SlotKernelSpec(spec=spec, part_a=part_a, head=head, pair=pair, tail=tail,
                          part_b=part_b, n_slots=sm.n_slots)


def candidate_slot_spec(sp: SamplingProblem, precision: str = "float64",
                        reference: KernelSpec | None = None) -> SlotKernelSpec:
    """The loop version of :func:`~workbench.sampling.kernels.specs.candidate_spec`."""
    return mppi_slot_spec(sp, "wb_candidates", strided=True, precision=precision,
                          reference=reference)


def sais_slot_spec(sp: SamplingProblem, name: str = "wb_sais", precision: str = "float64",
                   reference: KernelSpec | None = None) -> SlotKernelSpec:
    """The loop version of :func:`~workbench.sampling.kernels.specs.sais_spec`."""
    sm = _slot_model(sp, precision)
    spec = reference or _reference("sais", sp, name, precision)
    nx, nu, n = sp.nx, sp.nu, sm.n
    gamma = sm.barrier is not None and sm.barrier.gamma != 0.0
    fns = sp.functions()
    q = fns["q"]

    a = _inputs(spec)
    carry = a["carry"]
    x, xs = carry[:nx], carry[nx: 2 * nx]
    K = ca.reshape(a["K"], nx, nu).T
    eps = a["sigma"] * a["z"]
    kfb = ca.mtimes(K, x - xs)
    vr = clip(a["u"] + eps + kfb, a["u_min"], a["u_max"])
    vn = clip(a["u"] + eps, a["u_min"], a["u_max"])
    xn, xsn = fns["dyn"](x, vr, a["scene"])[:n], fns["dyn"](xs, vn, a["scene"])[:n]
    mids = [vr, vn, kfb, xn, xsn] + ([x[:n], xs[:n]] if gamma else [])
    part_a = ca.Function(spec.name + "_a", list(a.values()), [ca.vertcat(*mids), vn, vr],
                         list(a), ["mid", "v_nom", "v_real"], _OPTS)
    o = 3 * nu
    n_mid = o + 2 * n + (2 * n if gamma else 0)
    points = [o, o + n] + ([o + 2 * n, o + 3 * n] if gamma else [])
    head, pair, tail = _slot_functions(sm, n_mid, points)

    b = _inputs(spec)
    mid = ca.SX.sym("mid", n_mid)
    acc = _Acc(len(points), sm.barrier is not None)
    carry, u, cc = b["carry"], b["u"], b["clip_cost"]
    x, xs = carry[:nx], carry[nx: 2 * nx]
    Sn, Sh, Sr, LR, cr, cn = (carry[2 * nx + i] for i in range(6))
    eps = b["sigma"] * b["z"]
    vr, vn, kfb = mid[:nu], mid[nu: 2 * nu], mid[2 * nu: 3 * nu]
    XN, XSN = mid[o: o + n], mid[o + n: o + 2 * n]
    et = cc * (vn - u) + (1.0 - cc) * eps
    kt = cc * (vr - u - (vn - u)) + (1.0 - cc) * kfb
    xnf = _next_state(sm, XN, x[n:] if nx > n else None, acc, 0, 2 if gamma else None)
    xsnf = _next_state(sm, XSN, xs[n:] if nx > n else None, acc, 1, 3 if gamma else None)
    crn = ca.fmax(cr, acc.min(0) <= sp.eps_h)
    cnn = ca.fmax(cn, acc.min(1) <= sp.eps_h)
    qr = q(xnf, b["p"]) + b["crash"][0] * crn
    qn = q(xsnf, b["p"]) + b["crash"][0] * cnn
    inv = _inv_var(b)
    half = 0.5 * b["lr"]
    Sh = Sh + (qr + half * ca.dot(kt * inv, kt))
    Sn = Sn + qn
    Sr = Sr + (qr + half * ca.dot((u + kt) * inv, u + 2.0 * et + kt))
    LR = LR + half * (ca.dot(u * inv, u) + 2.0 * ca.dot(u * inv, et))
    new = [xnf, xsnf, Sn, Sh, Sr, LR, crn, cnn]
    part_b = ca.Function(spec.name + "_b", [*b.values(), mid, acc.sym],
                         [ca.vertcat(*new)], [*b, "mid", "acc"], ["carry_next"], _OPTS)
    return SlotKernelSpec(spec=spec, part_a=part_a, head=head, pair=pair, tail=tail,
                          part_b=part_b, n_slots=sm.n_slots)


# ---------------------------------------------------------------------------------------------
# the emitter


def emit_slot_kernel(sk: SlotKernelSpec) -> str:
    """C source of ``void <name>(...)``: the same signature, inputs, layouts and results as
    :func:`~workbench.sampling.kernels.emit.emit_kernel` of ``sk.spec`` (the same generator
    calls, so the same draws for a seed), with the circle slots in a loop."""
    spec = sk.spec
    if spec.precision != "float64":
        raise SlotLoopUnsupported(f"{spec.name}: slot-loop kernels are float64 only")
    step, final = spec.step, spec.final
    nc, nz = spec.n_carry, spec.n_noise
    lane, time_, const = spec.inputs("lane"), spec.inputs("time"), spec.inputs("const")
    L = spec.lanes
    names = list(step.name_in())
    n_mid = sk.part_a.numel_out(0)
    n_acc = sk.head.numel_out(0)
    scene = f"cin{const.index('scene')}"

    def load_step(i: int, nz_: int) -> str:
        if i >= len(names):  # part B's extra inputs: mid, acc
            return f"md{nz_}[l]" if i == len(names) else f"ac{nz_}[l]"
        return step_input(spec, names[i], step.numel_in(i), nz_)

    def store_step(o: int, nz_: int, expr: str) -> str:
        return step_output(spec, o, nz_, expr)

    def load_slot(i: int, nz_: int) -> str:
        return (f"md{nz_}[l]", f"sl[{nz_}]", f"ac{nz_}[l]")[i]

    def store_acc(o: int, nz_: int, expr: str) -> str:
        return f"ac{nz_}[l] = {expr};"

    offsets, nr = result_layout(spec)

    def load_final(i: int, nz_: int) -> str:
        return final_input(spec, final.name_in(i), nz_)

    def store_final(o: int, nz_: int, expr: str) -> str:
        return result_output(offsets, nr, o, nz_, expr)

    def store_a(o: int, nz_: int, expr: str) -> str:
        # part A writes the lane outputs (the controls): written from part B, as copies of
        # per-lane arrays, they kept gcc from vectorising part B ("control flow in loop")
        return f"md{nz_}[l] = {expr};" if o == 0 else store_step(o, nz_, expr)

    body_a = straight_line(sk.part_a, load_step, store_a, "a")
    body_b = straight_line(sk.part_b, load_step, store_step, "b")
    body_head = straight_line(sk.head, load_slot, store_acc, "h")
    body_pair = straight_line(sk.pair, load_slot, store_acc, "p") if sk.pair else []
    body_tail = straight_line(sk.tail, load_slot, store_acc, "e") if sk.tail else []
    final_body = straight_line(final, load_final, store_final, "f")
    n_lout = step.n_out() - 1
    ind = "        "
    pair_w = 2 * SLOT

    def lanes(body: list[str], indent: str) -> list[str]:
        return ([f"{indent}#pragma omp simd", f"{indent}for (int l = 0; l < {L}; ++l) {{"]
                + [indent + "  " + s for s in body] + [f"{indent}}}"])

    out = [
        f"/* kernel {spec.name} ({spec.precision}, slot loop over {sk.n_slots} circle slots): "
        f"carry {nc}, noise {nz}, lane {len(lane)}, time {len(time_)}, const {len(const)}, "
        f"lane outputs {n_lout}, results {nr} */",
        f"void {spec.name}(int N, int T, const double* carry0, const double* const* lane_in,",
        "    const double* const* time_in, const double* const* const_in, double* const* lane_out,",
        "    double* result, double* noise, int gen_noise, unsigned long long seed) {",
        "  (void)lane_in; (void)time_in; (void)const_in; (void)lane_out; (void)noise;",
        "  (void)gen_noise; (void)seed;",
        f"  const int nblk = N / {L};",
        f"  #pragma omp parallel for schedule({WB_SCHEDULE})",
        "  for (int b = 0; b < nblk; ++b) {",
        f"    const int n0 = b * {L};",
    ]
    out += [f"    double c{j}[{L}];" for j in range(nc)]
    out += [f"    double md{j}[{L}];" for j in range(n_mid)]
    out += [f"    double ac{j}[{L}];" for j in range(n_acc)]
    out += [f"    const double* lin{j} = lane_in[{j}];" for j in range(len(lane))]
    out += [f"    const double* cin{j} = const_in[{j}];" for j in range(len(const))]
    out += [f"    double* lout{j} = lane_out[{j}];" for j in range(n_lout)]
    out += [f"    for (int l = 0; l < {L}; ++l) {{"]
    out += [f"      c{j}[l] = carry0[(size_t)(n0+l)*{nc}+{j}];" for j in range(nc)]
    out += ["    }"]
    if nz:
        out += [f"    double z{j}[{L}];" for j in range(nz)]
        out += ["    wb_rng_block rng;",
                "    if (gen_noise) wb_block_seed(&rng, seed, (unsigned long long)n0);"]
    out += ["    for (int t = 0; t < T; ++t) {"]
    out += [f"      const double* tin{j} = time_in[{j}];" for j in range(len(time_))]
    if nz:
        gen = "".join(f" wb_block_normals(&rng, z{j});" for j in range(nz))
        wr = "".join(f" noise[((size_t)t*{nz}+{j})*N+n0+l] = z{j}[l];" for j in range(nz))
        rd = "".join(f" z{j}[l] = noise[((size_t)t*{nz}+{j})*N+n0+l];" for j in range(nz))
        out += [
            "      if (gen_noise) {",
            f"       {gen}",
            f"        if (noise) for (int l = 0; l < {L}; ++l) {{{wr} }}",
            "      } else {",
            f"        for (int l = 0; l < {L}; ++l) {{{rd} }}",
            "      }",
        ]
    out += ["      /* part A: controls and new physical states */"]
    out += lanes(body_a, "      ")
    out += ["      /* the circle slots: barrier sums and min margins */",
            "      {", f"        const double* sl = {scene};"]
    out += lanes(body_head, ind)
    if sk.pair is not None:
        out += [f"        for (int j = 1; j < {sk.n_pairs}; ++j) {{",
                f"          const double* sl = {scene} + (size_t){pair_w}*j;"]
        out += lanes(body_pair, ind + "  ")
        out += ["        }"]
    if sk.tail is not None:
        out += ["        {", f"          const double* sl = {scene} + {pair_w * sk.n_pairs};"]
        out += lanes(body_tail, ind + "  ")
        out += ["        }"]
    out += ["      }", "      /* part B: barrier states, crash flags, costs */"]
    out += lanes(body_b, "      ")
    out += ["    }", f"    for (int l = 0; l < {L}; ++l) {{"]
    out += ["      " + s for s in final_body]
    out += ["    }", "  }", "}", ""]
    return "\n".join(out)


# ---------------------------------------------------------------------------------------------
# libraries


def slot_specs(sp: SamplingProblem, specs: list[KernelSpec]) -> list[SlotKernelSpec]:
    """Loop versions of a sampler library's straight-line specs [mppi, sais, candidates]
    (:func:`~workbench.sampling.kernels.library.library_sources`' order)."""
    mppi, sais, cand = specs
    return [mppi_slot_spec(sp, mppi.name, precision=mppi.precision, reference=mppi),
            sais_slot_spec(sp, sais.name, sais.precision, reference=sais),
            candidate_slot_spec(sp, cand.precision, reference=cand)]


def slot_kernel_source(sp: SamplingProblem, specs: list[KernelSpec],
                       vector_math: bool | None = None) -> str:
    """C source of a sampler library with loop kernels: the same generator and declarations as
    :func:`~workbench.sampling.kernels.library.kernel_source`, the kernels from
    :func:`emit_slot_kernel`."""
    sks = slot_specs(sp, specs)
    precision = specs[0].precision
    fns = [f for s in sks for f in s.functions()]
    return rng_source(specs[0].lanes) + "\n" + prelude(
        fns, kernel_flags(precision), specs[0].lanes, vector_math, precision) + "\n".join(
        emit_slot_kernel(s) for s in sks)


def use_slot_loop(sp: SamplingProblem, precision: str = "float64",
                  min_slots: int = DEFAULT_MIN_SLOTS) -> bool:
    """True when ``sp`` has at least ``min_slots`` circle slots and loop kernels of
    ``precision`` support it (:func:`unsupported_reason`)."""
    return sp.model.scene_capacity >= min_slots and unsupported_reason(sp, precision) is None


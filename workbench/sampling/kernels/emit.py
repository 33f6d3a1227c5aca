"""Emit batched C kernels from CasADi SX Functions.

A kernel rolls a per-sample, per-time ``step`` Function over N samples and T steps. The emitter
walks the step's SX instruction list and writes it as straight-line C inside a loop over a block
of :func:`lane_count` samples (so the compiler vectorises across samples), inside the time loop,
inside an OpenMP loop over blocks. Each instruction becomes an SSA temporary, constants are
exact hex-float literals, all stores come after all loads. Instructions shared by all samples
are hoisted: those of const inputs only are evaluated once per block before the time loop,
those of const and time inputs once per step before the lane loop (the same operations;
measured 13% faster on the navigation SAIS rollout, whose 30 circles' r^2 and cost constants
were recomputed every step). With ``-ffp-contract=off`` the result is bitwise equal to
CasADi's own evaluation of the same Function.

Step inputs have roles:

* ``carry``  — the per-sample state carried from step to step (N, nc), exactly one;
* ``noise``  — standard-normal draws (T, nz, N), generated in the kernel or read from a buffer;
* ``lane``   — other per-sample, per-time inputs (T, m, N);
* ``time``   — per-time values shared by all samples (T, m);
* ``const``  — values shared by all samples and steps (m,).

Step outputs: the new carry first, then per-sample per-time outputs written as (T, m, N).
A ``final`` Function maps (carry, consts) to per-sample results (N, nr) after the last step.
Lane-contiguous (T, m, N) layouts keep every load and store of the lane loop contiguous.

Block width (:func:`~workbench.sampling.kernels.flags.lane_count`): one vector register of
samples, four or eight of a float64 kernel, eight or sixteen of a float32 one
(:mod:`.flags`). The width is written into the C (so it is part of the code cache's key);
results never depend on it (every sample's noise is its own stream, and the lane loop computes
each sample alone).

Precision (``KernelSpec.precision``): ``"float64"`` kernels compute in double. ``"float32"``
kernels compute in ``float`` (f-suffixed libm calls, float literals rounded to nearest), twice
the samples per block (twice the SIMD lanes), with the carry entries listed in
``KernelSpec.wide`` (the cost sums) kept in double: an operation is double when
one of its operands is, so a step cost is formed in float and added to a double sum. Constants,
``const`` and ``time`` inputs are available in both types and take the type of the operation that
uses them. Inputs and outputs stay double arrays (converted on load and store); the noise is the
double generator's draw rounded to float, so a float32 kernel sees the float64 kernel's normals.
"""

from __future__ import annotations

import functools
import math
import re
from dataclasses import dataclass
from functools import cached_property
from importlib import resources

import casadi as ca

from workbench.sampling.kernels.flags import LANES, PRECISIONS, lane_count
from workbench.sampling.kernels.grid_lookup import (
    Program,
    UnsupportedCall,
    called_functions,
    grid_calls,
    lookup_c,
    program,
    row_size,
)

ROLES = ("carry", "noise", "lane", "time", "const")
# OpenMP schedule of the block loop: equal shares per thread (busy machines are handled by the
# thread count, workbench/sampling/kernels/threads.py; a dynamic schedule measured no better)
WB_SCHEDULE = "static"

_UNARY = {
    ca.OP_NEG: "(-{0})", ca.OP_SQ: "({0}*{0})", ca.OP_TWICE: "({0}+{0})", ca.OP_INV: "(1.0/{0})",
    ca.OP_SQRT: "sqrt({0})", ca.OP_EXP: "exp({0})", ca.OP_LOG: "log({0})",
    ca.OP_SIN: "sin({0})", ca.OP_COS: "cos({0})", ca.OP_TAN: "tan({0})",
    ca.OP_TANH: "tanh({0})", ca.OP_FABS: "fabs({0})", ca.OP_NOT: "(({0})==0 ? 1.0 : 0.0)",
    ca.OP_FLOOR: "floor({0})", ca.OP_CEIL: "ceil({0})", ca.OP_ATAN: "atan({0})",
    ca.OP_ASSIGN: "{0}", ca.OP_LOG1P: "log1p({0})", ca.OP_EXPM1: "expm1({0})",
    ca.OP_SIGN: "(({0})<0 ? -1.0 : (({0})>0 ? 1.0 : ({0})))",
    # libm functions: correct first (they may keep gcc from vectorising the lane loop)
    ca.OP_ASIN: "asin({0})", ca.OP_ACOS: "acos({0})", ca.OP_ERF: "erf({0})",
    ca.OP_SINH: "sinh({0})", ca.OP_COSH: "cosh({0})", ca.OP_ASINH: "asinh({0})",
    ca.OP_ACOSH: "acosh({0})", ca.OP_ATANH: "atanh({0})",
}
_BINARY = {
    ca.OP_ADD: "({0}+{1})", ca.OP_SUB: "({0}-{1})", ca.OP_MUL: "({0}*{1})",
    ca.OP_DIV: "({0}/{1})", ca.OP_POW: "pow({0},{1})", ca.OP_CONSTPOW: "pow({0},{1})",
    # fmin/fmax as plain selects: libm calls and NaN tests both block gcc's vectoriser. They
    # equal fmin/fmax for all non-NaN inputs; a NaN first argument propagates (C99 would drop
    # it), which the sampler's weights treat as an infinite cost anyway.
    ca.OP_FMIN: "(({1})<({0}) ? ({1}) : ({0}))",
    ca.OP_FMAX: "(({1})>({0}) ? ({1}) : ({0}))",
    ca.OP_ATAN2: "atan2({0},{1})",
    ca.OP_LT: "(({0})<({1}) ? 1.0 : 0.0)", ca.OP_LE: "(({0})<=({1}) ? 1.0 : 0.0)",
    ca.OP_EQ: "(({0})==({1}) ? 1.0 : 0.0)", ca.OP_NE: "(({0})!=({1}) ? 1.0 : 0.0)",
    ca.OP_AND: "((({0})!=0) & (({1})!=0) ? 1.0 : 0.0)",
    ca.OP_OR: "((({0})!=0) | (({1})!=0) ? 1.0 : 0.0)",
    # comparisons as selects: a (double)(a < b) conversion blocks vectorisation in gcc 12
    ca.OP_IF_ELSE_ZERO: "(({0})==0 ? 0.0 : ({1}))", ca.OP_HYPOT: "hypot({0},{1})",
    ca.OP_COPYSIGN: "copysign({0},{1})", ca.OP_FMOD: "fmod({0},{1})",
    ca.OP_REMAINDER: "remainder({0},{1})",
}
# libm calls: emitted as early as their inputs allow, so that fewer values are live across them
# (a SIMD libm call clobbers every vector register, forcing spills of whatever is live)
_CALLS = {ca.OP_SIN, ca.OP_COS, ca.OP_TAN, ca.OP_ASIN, ca.OP_ACOS, ca.OP_ATAN, ca.OP_ATAN2}
_LIBM = ("sqrt", "exp", "log", "sin", "cos", "tan", "tanh", "fabs", "floor", "ceil", "atan",
         "log1p", "expm1", "asin", "acos", "erf", "sinh", "cosh", "asinh", "acosh", "atanh",
         "pow", "atan2", "hypot", "copysign", "fmod", "remainder")
_LIBM_RE = re.compile(r"\b(" + "|".join(_LIBM) + r")\(")


def _float_template(t: str) -> str:
    """The float version of a C template: f-suffixed libm calls and float literals."""
    return re.sub(r"(?<![\w.])(\d+\.\d+)", r"\1f", _LIBM_RE.sub(r"\1f(", t))


_UNARY_F = {op: _float_template(t) for op, t in _UNARY.items()}
_BINARY_F = {op: _float_template(t) for op, t in _BINARY.items()}
_OP_NAMES = {getattr(ca, n): n[3:].lower() for n in dir(ca) if n.startswith("OP_")}
_STRUCTURAL = (ca.OP_INPUT, ca.OP_OUTPUT, ca.OP_CONST)


def op_name(op: int) -> str:
    """CasADi's name of an operation code (e.g. 86 -> 'erfinv')."""
    return _OP_NAMES.get(op, f"op code {op}")


def supported_operations() -> tuple[str, ...]:
    """Names of the CasADi operations the emitter writes as C (and calls of the
    signed-distance grid's interpolant, :mod:`.grid_lookup`)."""
    return tuple(sorted(op_name(op) for op in (*_UNARY, *_BINARY)))


def unsupported_operations(f: ca.Function, prog: Program | None = None) -> tuple[str, ...]:
    """Names of the operations of SX Function ``f`` (its instructions ``prog`` when read
    already) the emitter cannot write (empty if none); a call of a Function other than a grid
    interpolant is named ``call (<function>)``."""
    ops = ({op for op, _, _ in prog} if prog is not None
           else {f.instruction_id(k) for k in range(f.n_instructions())})
    bad = ops - set(_UNARY) - set(_BINARY) - set(_STRUCTURAL) - {ca.OP_CALL}
    names = [op_name(op) for op in bad]
    if ca.OP_CALL in ops:
        names += [f"call ({n})" for n in set(called_functions(f, prog).values())
                  if row_size(n) is None]
    return tuple(sorted(names))


class EmitError(ValueError):
    """The Function uses an operation the emitter does not know."""


def _literal(v: float) -> str:
    if math.isnan(v):
        return "NAN"
    if math.isinf(v):
        return "INFINITY" if v > 0 else "(-INFINITY)"
    return f"{v.hex()}"


def _literal_f(v: float) -> str:
    """A float literal: v rounded to the nearest float (inf beyond float's range)."""
    import numpy as np

    with np.errstate(over="ignore"):
        f = float(np.float32(v))
    return _literal(f) if math.isnan(f) or math.isinf(f) else f"{f.hex()}f"


def straight_line(f: ca.Function, load, store, prefix: str, kind=None,
                  load_f=None, level=None, hoisted: list[list[str]] | None = None,
                  array=None, tables: set[int] | None = None,
                  loaded: dict[int, int] | None = None) -> list[str]:
    """C statements evaluating SX Function ``f``: ``load(i, nz)`` gives the C expression of
    input i element nz, ``store(o, nz, expr)`` the statement writing output o element nz.
    Outputs are collected and written after every load. ``load_f(i, nz)`` (optional) gives a
    float expression of an input (None: the double one converted).

    ``kind`` None: every value is a double. Otherwise ``kind(i, nz)`` types input i element
    nz: ``"d"`` double, ``"f"`` float, ``"p"`` both (a name and a ``_d`` double twin);
    constants are ``"p"``; an operation is double when an operand is, else float when an
    operand is, else ``"p"`` (evaluated in both types).

    ``level(i, nz)`` (optional, with ``hoisted`` a list of two lists) ranks input i element nz:
    0 shared by every sample and step, 1 by every sample of a step, 2 per sample; literals are
    0 and an operation takes its operands' highest rank. Statements of rank 0 and 1 are
    appended to ``hoisted[0]`` and ``hoisted[1]`` (to be emitted outside the time loop and the
    lane loop) instead of being returned: the same operations, evaluated once.

    Calls of the signed-distance grid's interpolant (:mod:`.grid_lookup`) are written as
    bilinear lookups into ``array(i)``, the C pointer of input i's doubles when they are
    shared by every sample (None: not indexable, an error); their values are not loaded one
    by one. ``tables`` (optional) collects the inputs indexed so, ``loaded`` the number of
    leading entries of each input loaded one by one (one past the last)."""
    if not f.is_a("SXFunction"):
        raise EmitError(f"{f.name()}: only SX Functions can be emitted")
    prog = program(f)
    bad = unsupported_operations(f, prog)
    if bad:
        raise EmitError(f"{f.name()} uses the CasADi operation{'s' if len(bad) > 1 else ''} "
                        f"{', '.join(bad)}, which the sampler's C emitter does not support; "
                        f"supported: {', '.join(supported_operations())} and calls of the "
                        "signed-distance grid's interpolant")
    try:
        grids, skip = grid_calls(f, prog)
    except UnsupportedCall as exc:
        raise EmitError(f"{f.name()}: {exc}, which the sampler's C emitter does not "
                        "support") from exc
    typed = kind is not None
    work: dict[int, str] = {}
    typ: dict[str, str] = {}
    body, stores = [], []
    # statement order: (k, 0, k) for instruction k; a libm call moves up to just after its
    # last input: (that input's first key entry, 1, k)
    key: dict[str, tuple[int, int, int]] = {}
    rank: dict[str, int] = {}
    split = level is not None and hoisted is not None

    def operand(name: str, want: str) -> str:
        return name + "_d" if want == "d" and typ.get(name) == "p" else name

    def declare(name: str, t: str, expr_f: str, expr_d: str) -> str:
        if not typed:
            return f"const double {name} = {expr_d};"
        if t == "d":
            return f"const double {name} = {expr_d};"
        if t == "f":
            return f"const float {name} = {expr_f};"
        return f"const float {name} = {expr_f}; const double {name}_d = {expr_d};"

    for k, (op, ins, outs) in enumerate(prog):
        if op == ca.OP_OUTPUT:
            src = work[ins[0]]
            stores.append(store(outs[0], outs[1], operand(src, "d")))
            continue
        name = f"{prefix}{k}"
        if k in skip:  # a grid's value, read by its lookups
            continue
        if k in grids:
            g = grids[k]
            table = array(g.input) if array is not None else None
            if table is None:
                raise EmitError(f"{f.name()}: a signed-distance grid's values must be an "
                                "input shared by every sample (the run-time scene)")
            if tables is not None:
                tables.add(g.input)
            x = work[g.x]
            rank[name] = max(rank[x], level(g.input, g.start) if split else 2)
            t = "d" if not typed else typ.get(x, "d")
            xd = operand(x, "d")
            stmt = lookup_c(name, xd, table, g, "double")
            if t != "d":  # "p": both types, the double one named <name>_d
                stmt = lookup_c(name, x, table, g, "float") + (
                    " " + lookup_c(name + "_d", xd, table, g, "double") if t == "p" else "")
            key[name] = (k, 0, k)
            typ[name] = t
            body.append((key[name], rank[name], stmt))
            work[outs[0]] = name
            continue
        if op == ca.OP_INPUT:
            if loaded is not None:
                loaded[ins[0]] = max(loaded.get(ins[0], 0), ins[1] + 1)
            t = kind(ins[0], ins[1]) if typed else "d"
            rank[name] = level(ins[0], ins[1]) if split else 2
            expr_d = load(ins[0], ins[1])
            alt = load_f(ins[0], ins[1]) if load_f is not None else None
            expr_f = alt if alt is not None else f"(float)({expr_d})"
        elif op == ca.OP_CONST:
            v = f.instruction_constant(k)
            t, expr_d, expr_f = ("p" if typed else "d"), _literal(v), _literal_f(v)
            rank[name] = 0
        else:
            args: list[str | None] = [work[i] for i in ins[: 2 if op in _BINARY else 1]]
            rank[name] = max(rank[a] for a in args if a is not None)
            if op == ca.OP_CONSTPOW and len(ins) < 2:
                args.append(None)
            kinds = {typ.get(a, "d") for a in args if a is not None}
            t = "d" if "d" in kinds or not typed else "f" if "f" in kinds else "p"
            if op in _UNARY:
                tmpl_d, tmpl_f = _UNARY[op], _UNARY_F[op]
            elif op in _BINARY:
                tmpl_d, tmpl_f = _BINARY[op], _BINARY_F[op]
            else:  # unreachable: unsupported_operations checked every instruction
                raise EmitError(f"{f.name()}: CasADi operation {op_name(op)} is not supported")
            expr_d = tmpl_d.format(*[None if a is None else operand(a, "d") for a in args])
            expr_f = tmpl_f.format(*args)
        if op in _CALLS:
            last = max(key[work[i]] for i in ins[: 2 if op in _BINARY else 1])
            key[name] = (last[0], 1, k)
        else:
            key[name] = (k, 0, k)
        typ[name] = t
        body.append((key[name], rank[name], declare(name, t, expr_f, expr_d)))
        work[outs[0]] = name
    out: list[str] = []
    for _, r, stmt in sorted(body):
        if split and hoisted is not None and r < 2:
            hoisted[r].append(stmt)
        else:
            out.append(stmt)
    return out + stores


@dataclass(frozen=True, eq=False)
class KernelSpec:
    """A batched rollout: ``step`` applied T times to N samples, then ``final``."""

    name: str
    step: ca.Function
    final: ca.Function
    roles: dict[str, str]
    precision: str = "float64"
    # carry entries kept in double by a float32 kernel (the cost sums)
    wide: tuple[int, ...] = ()
    # samples per block; 0: lane_count(precision), the compile target's vector width
    block: int = 0

    def inputs(self, role: str) -> list[str]:
        return list(self._inputs[role])

    @cached_property
    def _inputs(self) -> dict[str, tuple[str, ...]]:
        # CasADi's name and size queries cost ~0.1 ms each: asked once per spec
        return {r: tuple(n for n in self.step.name_in() if self.roles[n] == r) for r in ROLES}

    def __post_init__(self) -> None:
        for n in self.step.name_in():
            if self.roles.get(n) not in ROLES:
                raise EmitError(f"{self.name}: input {n!r} needs a role in {ROLES}")
        if len(self.inputs("carry")) != 1 or len(self.inputs("noise")) > 1:
            raise EmitError(f"{self.name}: exactly one carry and at most one noise input")
        carry = self.inputs("carry")[0]
        if self.step.size_out(0) != self.step.size_in(carry):
            raise EmitError(f"{self.name}: the first output must be the new carry")
        for n in self.final.name_in():
            if n != carry and self.roles.get(n) != "const":
                raise EmitError(f"{self.name}: final inputs are the carry and consts, got {n!r}")
        if self.precision not in PRECISIONS:
            raise EmitError(f"{self.name}: precision {self.precision!r} is not one of "
                            f"{PRECISIONS}")
        if any(not 0 <= j < self.n_carry for j in self.wide):
            raise EmitError(f"{self.name}: wide carry entries {self.wide} outside the carry "
                            f"(size {self.n_carry})")
        if not (isinstance(self.block, int) and 0 <= self.block <= 64):
            raise EmitError(f"{self.name}: block = {self.block!r} must be an integer in "
                            "[1, 64] (0: the compile target's lane count)")

    @property
    def lanes(self) -> int:
        """Samples per block (the kernel pads N to a multiple of it): ``block``, or
        :func:`lane_count` of the precision."""
        return self.block or lane_count(self.precision)

    @cached_property
    def n_carry(self) -> int:
        return self.step.numel_in(self.inputs("carry")[0])

    @cached_property
    def n_noise(self) -> int:
        z = self.inputs("noise")
        return self.step.numel_in(z[0]) if z else 0

    @cached_property
    def n_result(self) -> int:
        return sum(self.final.numel_out(i) for i in range(self.final.n_out()))

    def lane_out_sizes(self) -> list[int]:
        return list(self._lane_out_sizes)

    @cached_property
    def _lane_out_sizes(self) -> tuple[int, ...]:
        return tuple(self.step.numel_out(i) for i in range(1, self.step.n_out()))


def step_input(spec: KernelSpec, name: str, m: int, k: int) -> str:
    """C expression of entry ``k`` of the step input ``name`` (``m`` entries) for lane ``l`` of
    the block at step ``t``, read from where its role keeps it."""
    role = spec.roles[name]
    if role == "carry":
        return f"c{k}[l]"
    if role == "noise":
        return f"z{k}[l]"
    if role == "lane":
        return f"lin{spec.inputs('lane').index(name)}[((size_t)t*{m}+{k})*N+n0+l]"
    if role == "time":
        return f"tin{spec.inputs('time').index(name)}[(size_t)t*{m}+{k}]"
    return f"cin{spec.inputs('const').index(name)}[{k}]"


def step_output(spec: KernelSpec, o: int, k: int, expr: str) -> str:
    """C statement storing ``expr`` as entry ``k`` of step output ``o``: the carry (o = 0) or
    the lane output o - 1 at step ``t``."""
    if o == 0:
        return f"c{k}[l] = {expr};"
    m = spec.step.numel_out(o)
    return f"lout{o - 1}[((size_t)t*{m}+{k})*N+n0+l] = {expr};"


def final_input(spec: KernelSpec, name: str, k: int) -> str:
    """C expression of entry ``k`` of the final Function's input ``name`` (carry or const)."""
    if name == spec.inputs("carry")[0]:
        return f"c{k}[l]"
    return f"cin{spec.inputs('const').index(name)}[{k}]"


def result_layout(spec: KernelSpec) -> tuple[list[int], int]:
    """Offsets of the final Function's outputs in a sample's result row, and the row length."""
    offsets, acc = [], 0
    for i in range(spec.final.n_out()):
        offsets.append(acc)
        acc += spec.final.numel_out(i)
    return offsets, acc


def result_output(offsets: list[int], nr: int, o: int, k: int, expr: str) -> str:
    """C statement storing ``expr`` as entry ``k`` of final output ``o`` of lane ``l``."""
    return f"result[(size_t)(n0+l)*{nr}+{offsets[o] + k}] = {expr};"


def emit_kernel(spec: KernelSpec) -> str:
    """C source of ``void <name>(...)`` for the spec (see module docstring for layouts)."""
    step, final = spec.step, spec.final
    carry = spec.inputs("carry")[0]
    nc, nz = spec.n_carry, spec.n_noise
    lane, time_, const = spec.inputs("lane"), spec.inputs("time"), spec.inputs("const")
    f32 = spec.precision == "float32"
    L = spec.lanes
    wide = set(spec.wide)

    def load_step(i: int, nz_: int) -> str:
        return step_input(spec, step.name_in(i), step.numel_in(i), nz_)

    def load_step_f(i: int, nz_: int) -> str | None:
        """Float copies of shared inputs, converted once outside the lane loop."""
        name = step.name_in(i)
        role = spec.roles[name]
        if role == "time":
            return f"tf{time_.index(name)}[{nz_}]"
        if role == "const":
            return f"cf{const.index(name)}[{nz_}]"
        return None

    def kind_of(fn: ca.Function):
        """Input types of a float32 kernel: wide carries double, per-sample values float,
        values shared by all samples (const, time) both."""
        if not f32:
            return None

        def kind(i: int, nz_: int) -> str:
            role = spec.roles.get(fn.name_in(i), "carry")
            if fn.name_in(i) == carry:
                return "d" if nz_ in wide else "f"
            return "p" if role in ("const", "time") else "f"

        return kind

    def store_step(o: int, nz_: int, expr: str) -> str:
        return step_output(spec, o, nz_, expr)

    offsets, nr = result_layout(spec)

    def load_final(i: int, nz_: int) -> str:
        return final_input(spec, final.name_in(i), nz_)

    def load_final_f(i: int, nz_: int) -> str | None:
        name = final.name_in(i)
        return None if name == carry else f"cf{const.index(name)}[{nz_}]"

    def store_final(o: int, nz_: int, expr: str) -> str:
        return result_output(offsets, nr, o, nz_, expr)

    def level_step(i: int, nz_: int) -> int:
        role = spec.roles[step.name_in(i)]
        return 0 if role == "const" else 1 if role == "time" else 2

    def array_of(fn: ca.Function):
        """The const inputs' arrays, which a grid lookup indexes."""

        def array(i: int) -> str | None:
            name = fn.name_in(i)
            return f"cin{const.index(name)}" if spec.roles.get(name) == "const" else None

        return array

    hoisted: list[list[str]] = [[], []]
    tables: dict[str, set[int]] = {"s": set(), "f": set()}
    loaded: dict[str, dict[int, int]] = {"s": {}, "f": {}}
    step_body = straight_line(step, load_step, store_step, "s", kind_of(step), load_step_f,
                              level_step, hoisted, array_of(step), tables["s"], loaded["s"])
    final_body = straight_line(final, load_final, store_final, "f", kind_of(final),
                               load_final_f, array=array_of(final), tables=tables["f"],
                               loaded=loaded["f"])

    def float_copy(name: str) -> int:
        """Entries of the float copy of const input ``name``: all of them, or, when a grid
        lookup reads the input (its values as doubles), those loaded one by one."""
        fns = (("s", step), ("f", final))
        ids = [(t, fn.index_in(name)) for t, fn in fns if fn.has_in(name)]
        if not any(i in tables[t] for t, i in ids):
            return step.numel_in(name)
        return max(1, *(loaded[t].get(i, 0) for t, i in ids))
    n_lout = step.n_out() - 1
    ind = "        "

    def ctype(j: int) -> str:
        return "float" if f32 and j not in wide else "double"

    out = [
        f"/* kernel {spec.name} ({spec.precision}): carry {nc}, noise {nz}, lane {len(lane)}, "
        f"time {len(time_)}, const {len(const)}, lane outputs {n_lout}, results {nr} */",
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
    out += [f"    {ctype(j)} c{j}[{L}];" for j in range(nc)]
    out += [f"    const double* lin{j} = lane_in[{j}];" for j in range(len(lane))]
    out += [f"    const double* cin{j} = const_in[{j}];" for j in range(len(const))]
    if f32:  # float copies of the shared inputs: converted once, alias-free
        for j, n in enumerate(const):
            m = float_copy(n)
            out += [f"    float cf{j}[{m}];",
                    f"    for (int k = 0; k < {m}; ++k) cf{j}[k] = (float)cin{j}[k];"]
    out += [f"    double* lout{j} = lane_out[{j}];" for j in range(n_lout)]
    out += ["    " + st for st in hoisted[0]]  # shared by every sample and step
    out += [f"    for (int l = 0; l < {L}; ++l) {{"]
    out += [f"      c{j}[l] = carry0[(size_t)(n0+l)*{nc}+{j}];" for j in range(nc)]
    out += ["    }"]
    if nz:
        out += [f"    double z{j}[{L}];" for j in range(nz)]
        out += ["    wb_rng_block rng;",
                "    if (gen_noise) wb_block_seed(&rng, seed, (unsigned long long)n0);"]
    out += ["    for (int t = 0; t < T; ++t) {"]
    out += [f"      const double* tin{j} = time_in[{j}];" for j in range(len(time_))]
    if f32:
        for j, n in enumerate(time_):
            m = step.numel_in(n)
            out += [f"      float tf{j}[{m}];",
                    f"      for (int k = 0; k < {m}; ++k) "
                    f"tf{j}[k] = (float)tin{j}[(size_t)t*{m}+k];"]
    out += ["      " + st for st in hoisted[1]]  # shared by every sample of the step
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
    out += ["      #pragma omp simd", f"      for (int l = 0; l < {L}; ++l) {{"]
    out += [ind + s for s in step_body]
    out += ["      }", "    }", f"    for (int l = 0; l < {L}; ++l) {{"]
    out += ["      " + s for s in final_body]
    out += ["    }", "  }", "}", ""]
    return "\n".join(out)


ZIGGURAT_LAYERS = 1024  # the generator's layers: 99.6% of draws pass the rectangle test


def _density(x: float) -> float:
    return math.exp(-0.5 * x * x)


def _ziggurat_x(layers: int, r: float) -> tuple[list[float], float, float]:
    """(x, v, top) of a ziggurat with base edge r: the layer edges x_0 > x_1 = r > ... (Doornik
    2005: x_0 = v / f(r) the base layer's width, tail included), the common layer area v, and
    the area of the top layer x_{n-1} (1 - f(x_{n-1})) that it should equal (0: r too small)."""
    v = r * _density(r) + math.sqrt(0.5 * math.pi) * math.erfc(r / math.sqrt(2.0))
    x = [0.0] * (layers + 1)
    x[0], x[1] = v / _density(r), r
    for i in range(2, layers):
        a = v / x[i - 1] + _density(x[i - 1])
        if a >= 1.0:
            return x, v, 0.0
        x[i] = math.sqrt(-2.0 * math.log(a))
    return x, v, x[layers - 1] * (1.0 - _density(x[layers - 1]))


@functools.cache
def ziggurat_tables(layers: int = ZIGGURAT_LAYERS) -> tuple[tuple[float, ...],
                                                              tuple[float, ...],
                                                              tuple[float, ...], float]:
    """Ziggurat tables of the standard normal with ``layers`` layers of equal area (Marsaglia &
    Tsang 2000; Doornik 2005 layout): (x, ratio, f, r) with x the layer edges (layers + 1
    values, x_layers = 0), ratio_i = x_{i+1} / x_i the rectangle test, f_i = exp(-x_i^2 / 2)
    the wedge test, r the tail edge (solved by bisection: the top layer's area equals v)."""
    lo, hi = 1.0, 6.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        x, v, top = _ziggurat_x(layers, mid)
        if top > v:
            hi = mid
        else:
            lo = mid
    x, _, _ = _ziggurat_x(layers, hi)
    x[layers] = 0.0
    ratio = tuple(x[i + 1] / x[i] for i in range(layers))
    return tuple(x), ratio, tuple(_density(v) for v in x), hi


def rng_source(lanes: int = LANES) -> str:
    """C of the per-sample generator (the package file ``rng.c``) behind its ziggurat tables,
    which are computed here (:func:`ziggurat_tables`) and written as data; ``lanes`` samples
    per block (the kernels' :attr:`KernelSpec.lanes`; draws never depend on it)."""
    n = ZIGGURAT_LAYERS
    x, ratio, f, r = ziggurat_tables(n)

    def table(name: str, vals) -> str:
        return (f"static const double {name}[{len(vals)}] = {{"
                f"{', '.join(_literal(v) for v in vals)}}};")

    tables = "\n".join([
        f"#define WB_ZIG_LAYERS {n}", table("wb_zig_x", x), table("wb_zig_r", ratio),
        table("wb_zig_f", f), f"#define WB_ZIG_R {_literal(r)}", f"#define WB_LANES {int(lanes)}",
        ""])
    return tables + (resources.files("workbench.sampling.kernels") / "rng.c").read_text()

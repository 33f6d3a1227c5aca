"""The signed-distance grid's interpolant calls in an emitted kernel, written as inline C.

A grid margin (:func:`workbench.problem.sdf_grid.grid_sx`) reads the grid's values through two
SX calls of CasADi's linear interpolant ``wb_row_{n}`` over the n = nx ny values (x-fastest):
argument a coordinate x along the values, and the values, one output. The emitter writes each
such call as a lookup into the input array holding the values (the run-time scene, shared by
every sample and step): segment ``i = clamp(floor(x), 0, n - 2)`` (a NaN coordinate gives
segment 0 and a NaN value), weight ``a = x - i``, and the interpolant's own sum
``(1 - a) V[i] + a V[i + 1]`` in its order, so the result equals CasADi's evaluation bitwise.
The two loads have per-sample indices (gathers, or their emulation where the target prefers
it), the rest vectorises like any other step operation (a double kernel forms the index without
an int32 conversion, which would halve the vector width of its whole lane loop).

Only calls of these interpolants whose values are one contiguous run of a shared input are
written; any other call (another Function, a derivative of the interpolant, values computed
or compiled into the model) raises :class:`UnsupportedCall` naming it.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import casadi as ca

ROW_FUNCTION = re.compile(r"wb_row_(\d+)")


class UnsupportedCall(ValueError):
    """A call the emitter cannot write (the reason is the message)."""


def row_size(name: str) -> int | None:
    """n of a row interpolant's name ``wb_row_{n}``, else None."""
    m = ROW_FUNCTION.fullmatch(name)
    return int(m[1]) if m else None


Program = list[tuple[int, list[int], list[int]]]


def program(f: ca.Function) -> Program:
    """(operation, inputs, outputs) of every instruction of SX Function ``f``, read once."""
    return [(f.instruction_id(k), f.instruction_input(k), f.instruction_output(k))
            for k in range(f.n_instructions())]


def called_functions(f: ca.Function, prog: Program | None = None) -> dict[int, str]:
    """Names of the Functions called by SX Function ``f``, by instruction index."""
    ops = ((k, op) for k, (op, _, _) in enumerate(prog)) if prog is not None else (
        (k, f.instruction_id(k)) for k in range(f.n_instructions()))
    ks = [k for k, op in ops if op == ca.OP_CALL]
    if not ks:
        return {}
    ins = f.instructions_sx()
    return {k: ins[k].which_function().name() for k in ks}


@dataclass(frozen=True)
class GridCall:
    """A row lookup: work entry ``x`` of the coordinate; the values are entries ``start ..
    start + n - 1`` of the Function's input ``input``."""

    n: int
    x: int
    input: int
    start: int


def grid_calls(f: ca.Function, prog: Program) -> tuple[dict[int, GridCall], set[int]]:
    """The grid lookups of ``f`` (its :func:`program` ``prog``) by instruction index, and the
    input instructions whose values only serve as a lookup's table (not loaded one by one)."""
    names = called_functions(f, prog)
    if not names:
        return {}, set()
    producer: dict[int, int] = {}  # work entry -> instruction that last wrote it
    plain: set[int] = set()  # instructions used other than as table entries
    table_use: set[int] = set()
    calls: dict[int, GridCall] = {}
    for k, (op, ins, outs) in enumerate(prog):
        if op == ca.OP_CALL:
            n = row_size(names[k])
            if n is None or len(ins) != 1 + n or len(outs) != 1:
                raise UnsupportedCall(f"a call of {names[k]} (only the signed-distance grid's "
                                      "interpolant is written as C)")
            if min(ins) < 0:
                raise UnsupportedCall(f"a call of {names[k]} with a structurally zero argument")
            plain.add(producer[ins[0]])
            src = [producer[w] for w in ins[1:]]
            first = prog[src[0]][1]
            if not all(prog[s][0] == ca.OP_INPUT and prog[s][1] == [first[0], first[1] + n]
                       for n, s in enumerate(src)):
                raise UnsupportedCall(f"a call of {names[k]} whose values are not one "
                                      "contiguous run of an input (a grid compiled into the "
                                      "model, or computed values); pass the grid in the "
                                      "run-time scene")
            table_use.update(src)
            calls[k] = GridCall(n, ins[0], first[0], first[1])
        elif op == ca.OP_OUTPUT:
            plain.add(producer[ins[0]])
        elif op not in (ca.OP_INPUT, ca.OP_CONST):
            plain.update(producer[w] for w in ins[:2] if w in producer)
        if op != ca.OP_OUTPUT:
            for w in outs:
                producer[w] = k
    return calls, table_use - plain


def lookup_c(name: str, x: str, table: str, g: GridCall, ctype: str) -> str:
    """C declarations computing the lookup ``g`` as ``const <ctype> <name>`` from the
    coordinate ``x`` (a C expression of type ``ctype``) and ``table`` (a C pointer to the
    input's doubles; entry ``g.start`` is node 0): segment ``i = clamp(floor(x), 0, n - 2)``,
    weight ``a = x - i``, the interpolant's sum (1 - a) V[i] + a V[i + 1] in its order (a NaN x
    gives segment 0 and a NaN value; beyond the row the end segment's line continues)."""
    f = "f" if ctype == "float" else ""
    one, zero = ("1.0f", "0.0f") if f else ("1.0", "0.0")
    hi = f"{float(g.n - 2)!r}{f}"
    cvt = "(float)" if f else ""
    i, at, a = f"{name}_i", f"{name}_k", f"{name}_a"
    cell = (f"const {ctype} {name}_fi = floor{f}({x}); const {ctype} {i} = {name}_fi >= "
            f"{zero} ? ({name}_fi <= {hi} ? {name}_fi : {hi}) : {zero};")
    if f:
        index = f"const int {at} = (int){i};"
    else:  # the index as the low bits of i + 2^52 (exact below 2^52), see the module
        index = (f"const double {at}x = {i} + 0x1p52; int64_t {at}; "
                 f"__builtin_memcpy(&{at}, &{at}x, 8); {at} -= 0x4330000000000000LL;")
    return " ".join([
        cell, index, f"const {ctype} {a} = {x} - {i};",
        f"const {ctype} {name} = (({one}-{a})*{cvt}{table}[{g.start} + {at}]) + "
        f"({a}*{cvt}{table}[{g.start + 1} + {at}]);",
    ])

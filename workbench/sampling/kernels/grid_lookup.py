"""The signed-distance grid's interpolant calls in an emitted kernel, written as inline C.

A grid margin (:func:`workbench.problem.sdf_grid.grid_sx`) is an SX call of CasADi's linear
interpolant ``wb_grid_{nx}x{ny}`` on the unit grid: arguments the unit coordinates (u, v) and
the nx ny node values (x-fastest), one output. The emitter writes each such call as a bilinear
lookup into the input array holding the values (the run-time scene, shared by every sample and
step): cell ``i = clamp(floor(u), 0, nx - 2)`` (a NaN coordinate gives cell 0 and a NaN value),
``j`` likewise, weights ``a = u - i``, ``b = v - j`` (outside the grid the boundary cell's
bilinear form continues, as the interpolant does), and the interpolant's own sum, corner by
corner in its order, so the result equals CasADi's evaluation bitwise. The four loads have
per-sample indices (gathers, or their emulation where the target prefers it), the rest
vectorises like any other step operation (a double kernel forms the index without an int32
conversion, which would halve the vector width of its whole lane loop).

Only calls of these interpolants whose values are one contiguous run of a shared input are
written; any other call (another Function, a derivative of the interpolant, values computed
or compiled into the model) raises :class:`UnsupportedCall` naming it.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import casadi as ca

GRID_FUNCTION = re.compile(r"wb_grid_(\d+)x(\d+)")


class UnsupportedCall(ValueError):
    """A call the emitter cannot write (the reason is the message)."""


def grid_shape(name: str) -> tuple[int, int] | None:
    """(nx, ny) of a grid interpolant's name ``wb_grid_{nx}x{ny}``, else None."""
    m = GRID_FUNCTION.fullmatch(name)
    return (int(m[1]), int(m[2])) if m else None


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
    """A grid lookup: work entries ``u``, ``v`` of the coordinates; the values are entries
    ``start .. start + nx ny - 1`` of the Function's input ``input``."""

    shape: tuple[int, int]
    u: int
    v: int
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
            shape = grid_shape(names[k])
            if shape is None or len(ins) != 2 + shape[0] * shape[1] or len(outs) != 1:
                raise UnsupportedCall(f"a call of {names[k]} (only the signed-distance grid's "
                                      "interpolant is written as C)")
            if min(ins) < 0:
                raise UnsupportedCall(f"a call of {names[k]} with a structurally zero argument")
            plain.update(producer[w] for w in ins[:2])
            src = [producer[w] for w in ins[2:]]
            first = prog[src[0]][1]
            if not all(prog[s][0] == ca.OP_INPUT and prog[s][1] == [first[0], first[1] + n]
                       for n, s in enumerate(src)):
                raise UnsupportedCall(f"a call of {names[k]} whose values are not one "
                                      "contiguous run of an input (a grid compiled into the "
                                      "model, or computed values); pass the grid in the "
                                      "run-time scene")
            table_use.update(src)
            calls[k] = GridCall(shape, ins[0], ins[1], first[0], first[1])
        elif op == ca.OP_OUTPUT:
            plain.add(producer[ins[0]])
        elif op not in (ca.OP_INPUT, ca.OP_CONST):
            plain.update(producer[w] for w in ins[:2] if w in producer)
        if op != ca.OP_OUTPUT:
            for w in outs:
                producer[w] = k
    return calls, table_use - plain


def lookup_c(name: str, u: str, v: str, table: str, g: GridCall, ctype: str) -> str:
    """C declarations computing the lookup ``g`` as ``const <ctype> <name>`` from coordinates
    ``u``, ``v`` (C expressions of type ``ctype``) and ``table`` (a C pointer to the input's
    doubles; entry ``g.start`` is node (0, 0))."""
    nx, ny = g.shape
    f = "f" if ctype == "float" else ""
    one, zero = ("1.0f", "0.0f") if f else ("1.0", "0.0")
    cvt = "(float)" if f else ""

    def cell(c: str, x: str, n: int) -> str:
        hi = f"{float(n - 2)!r}{f}"
        return (f"const {ctype} {name}_f{c} = floor{f}({x}); "
                f"const {ctype} {name}_{c} = {name}_f{c} >= {zero} ? ({name}_f{c} <= {hi} ? "
                f"{name}_f{c} : {hi}) : {zero};")

    at = f"{name}_k"
    if f:
        index = f"const int {at} = (int){name}_i + {nx}*(int){name}_j;"
    else:
        # the node index as the low bits of i + nx j + 2^52 (exact below 2^52): gcc converts
        # double to int32 only, in half-width vectors, and would then run the whole lane loop
        # of a double kernel at half width
        index = (f"const double {at}x = ({name}_i + {float(nx)!r}*{name}_j) + 0x1p52; "
                 f"int64_t {at}; __builtin_memcpy(&{at}, &{at}x, 8); "
                 f"{at} -= 0x4330000000000000LL;")

    def val(off: int) -> str:
        return f"{cvt}{table}[{g.start + off} + {at}]"

    a, b = f"{name}_a", f"{name}_b"
    return " ".join([
        cell("i", u, nx), cell("j", v, ny),
        index,
        f"const {ctype} {a} = {u} - {name}_i; const {ctype} {b} = {v} - {name}_j;",
        f"const {ctype} {name} = (((({one}-{a})*({one}-{b}))*{val(0)} + "
        f"(({a}*({one}-{b}))*{val(1)})) + ((({one}-{a})*{b})*{val(nx)})) + "
        f"(({a}*{b})*{val(nx + 1)});",
    ])

"""Vector trigonometry for the generated kernels: glibc's libmvec.

The emitter writes ``sin(x)`` etc. as libm calls. Scalar libm calls keep gcc from vectorising the
lane loop, so a model with trigonometry (a unicycle, a car) ran about 2x slower per sample-step
than the double integrator. glibc ships SIMD variants of these functions (libmvec, linked through
``-lm`` as needed); declaring a function ``__attribute__((simd("notinbranch")))`` lets gcc call
the variant for the machine's vector width (``_ZGVdN4v_sin`` with AVX2) inside the lane loop.

Accuracy: libmvec does not promise correct rounding. glibc's test suite bounds its x86_64
variants at a few ulp; we require and test **at most** :data:`MAX_ULP` **ulp** against the scalar
libm that CasADi itself calls (``tests/sampling/kernels/test_vector_math.py``, over wide argument
ranges). The probe below checks the same bound on the machine before the variants are used;
where it fails (no libmvec, another libc or compiler, an unexpected result) the kernels keep the
scalar calls, which equal CasADi's evaluation bitwise. ``WORKBENCH_VECTOR_MATH=0`` forces the
scalar calls.

Only libraries whose kernels use one of :data:`VECTOR_FUNCTIONS` get the declarations; the
double integrator's source is unchanged.

Float32 kernels call the float functions (``sinf``…; ``_ZGVdN8v_sinf`` with AVX2): the probe
and the bound are the same, in float ulps, against the double libm value at the float argument
rounded to float (``precision="float32"`` below).
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from functools import cache

import casadi as ca
import numpy as np

import workbench.environment as environment
from workbench.codegen import CompileError, build_library
from workbench.sampling.kernels.compiled import CompiledKernel
from workbench.sampling.kernels.emit import KernelSpec, emit_kernel, rng_source

MAX_ULP = 4
ENV = environment.VECTOR_MATH
# CasADi operation -> (libm name, arity)
VECTOR_FUNCTIONS = {
    ca.OP_SIN: ("sin", 1), ca.OP_COS: ("cos", 1), ca.OP_TAN: ("tan", 1),
    ca.OP_ASIN: ("asin", 1), ca.OP_ACOS: ("acos", 1), ca.OP_ATAN: ("atan", 1),
    ca.OP_ATAN2: ("atan2", 2),
}
_ARGS = {1: "{t}", 2: "{t}, {t}"}


def _suffix(precision: str) -> str:
    return "f" if precision == "float32" else ""


def _ctype(precision: str) -> str:
    return "float" if precision == "float32" else "double"


def enabled() -> bool:
    """``WORKBENCH_VECTOR_MATH``, a switch (:func:`workbench.environment.switch`): off for
    scalar libm calls, bitwise equal to CasADi; on (the default) for libmvec where the probe
    passes."""
    return environment.switch(ENV, True)


def declarations(names: Iterable[str], precision: str = "float64") -> str:
    """C declarations giving gcc the SIMD variants of libm functions ``names`` (their float
    versions ``sinf``… for ``precision="float32"``). ``const``: no side effects (the kernels
    build with -fno-math-errno; -fno-builtin-sin/cos take away the knowledge gcc has of the
    builtins, and a call that may clobber memory stops the vectoriser)."""
    arity = {n: a for n, a in VECTOR_FUNCTIONS.values()}
    t, f = _ctype(precision), _suffix(precision)
    return "".join(f'__attribute__((simd("notinbranch"), const)) {t} {n}{f}('
                   f'{_ARGS[arity[n]].format(t=t)});\n' for n in sorted(set(names)))


def used(functions: Iterable[ca.Function]) -> tuple[str, ...]:
    """libm names of the vectorisable operations the SX Functions use."""
    ops = {f.instruction_id(k) for f in functions for k in range(f.n_instructions())}
    return tuple(sorted(VECTOR_FUNCTIONS[op][0] for op in ops & set(VECTOR_FUNCTIONS)))


def simd_variants(binary: bytes, precision: str = "float64") -> set[str]:
    """Names of the functions whose SIMD variants (``_ZGV<isa>N<lanes>v…_<name>``, ``…_<name>f``
    for float32) a compiled library calls."""
    names = [n for n, _ in VECTOR_FUNCTIONS.values()]
    f = _suffix(precision).encode()
    return {n for n in names
            if re.search(rb"_ZGV[a-z]N\d+v+_" + n.encode() + f + rb"\x00", binary)}


def ulp_distance(a, b) -> np.ndarray:
    """Distance in units in the last place between float64 arrays (0 where both are the same
    NaN class or equal; inf where only one is NaN or the signs differ away from zero)."""
    a, b = np.broadcast_arrays(np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64))

    def ordered(x):  # monotone map of doubles onto integers (both zeros -> 0)
        i = x.view(np.int64)
        return np.where(i < 0, np.int64(-(2**63)) - i, i)

    oa, ob = ordered(a), ordered(b)
    same = (oa >= 0) == (ob >= 0)
    d = np.where(same, np.abs(np.where(same, oa - ob, 0)).astype(np.float64),
                 np.abs(oa).astype(np.float64) + np.abs(ob).astype(np.float64))
    nan_a, nan_b = np.isnan(a), np.isnan(b)
    return np.where(nan_a | nan_b, np.where(nan_a & nan_b, 0.0, np.inf), d)


def ulp_distance32(a, b) -> np.ndarray:
    """:func:`ulp_distance` in float32 units, of the float32 values of ``a`` and ``b``."""
    a, b = np.broadcast_arrays(np.asarray(a, dtype=np.float32), np.asarray(b, dtype=np.float32))

    def ordered(x):
        i = x.view(np.int32).astype(np.int64)
        return np.where(i < 0, np.int64(-(2**31)) - i, i)

    oa, ob = ordered(a), ordered(b)
    d = np.abs(oa - ob).astype(np.float64)
    nan_a, nan_b = np.isnan(a), np.isnan(b)
    return np.where(nan_a | nan_b, np.where(nan_a & nan_b, 0.0, np.inf), d)


def probe_inputs() -> dict[str, np.ndarray]:
    """Arguments of the probe (and of the accuracy test): wide, signed, with special values."""
    rng = np.random.default_rng(7)
    wide = np.concatenate([rng.uniform(-10, 10, 4000), rng.uniform(-1e4, 1e4, 2000),
                           rng.uniform(-1e-6, 1e-6, 1000), 10.0 ** rng.uniform(-300, 5, 1000),
                           [0.0, -0.0, np.pi, -np.pi / 2, 1e300, np.inf, -np.inf, np.nan]])
    unit = np.concatenate([rng.uniform(-1, 1, 4000), [1.0, -1.0, 0.0, 1 - 2**-52]])
    y = rng.uniform(-10, 10, wide.size)
    y[:8] = [0.0, -0.0, 1.0, -1.0, np.inf, -np.inf, 1e-300, -1e300]
    return {"x": wide, "u": np.resize(unit, wide.size), "y": y}


def reference(name: str, x, u, y) -> np.ndarray:
    """The scalar libm values the probe compares with (NumPy calls the same libm)."""
    with np.errstate(all="ignore"):
        if name in ("asin", "acos"):
            return getattr(np, "arc" + name[1:])(u)
        if name == "atan":
            return np.arctan(x)
        if name == "atan2":
            return np.arctan2(x, y)
        return getattr(np, name)(x)


def probe_spec(precision: str = "float64"):
    """A kernel whose lane outputs are every vectorisable function of lane inputs x, u, y
    (asin and acos of u in [-1, 1])."""
    c, w = ca.SX.sym("carry"), ca.SX.sym("w")
    x, u, y = ca.SX.sym("x"), ca.SX.sym("u"), ca.SX.sym("y")
    args = {"asin": (u,), "acos": (u,), "atan2": (x, y)}
    vals = [getattr(ca, n)(*args.get(n, (x,))) for n, _ in VECTOR_FUNCTIONS.values()]
    # the carry and a time input are read after the calls, as in a model
    name = "wb_vector_math_probe" + ("_f32" if precision == "float32" else "")
    step = ca.Function(name + "_step", [c, x, u, y, w],
                       [c + vals[0] * w, ca.vertcat(*vals)],
                       ["carry", "x", "u", "y", "w"], ["carry_next", "values"])
    final = ca.Function(name + "_final", [c], [c], ["carry"], ["result"])
    return KernelSpec(name=name, step=step, final=final,
                      roles={"carry": "carry", "x": "lane", "u": "lane", "y": "lane",
                             "w": "time"}, precision=precision)


@cache
def unavailable(flags: tuple[str, ...], lanes: int, precision: str = "float64") -> str | None:
    """Why the kernels cannot use libmvec with these compiler flags (None: they can).

    Builds a probe with the kernels' flags, checks that gcc called a SIMD variant of every
    function and that each result is within :data:`MAX_ULP` ulp of scalar libm (float32: float
    ulps from the double libm value at the float argument, rounded to float)."""
    spec = probe_spec(precision)
    names = [n for n, _ in VECTOR_FUNCTIONS.values()]
    source = rng_source(spec.lanes) + "\n" + declarations(names, precision) + emit_kernel(spec)
    f32 = precision == "float32"
    try:
        lib = build_library("vector_math_probe" + ("_f32" if f32 else ""), [], source,
                            extra_flags=flags)
    except CompileError as exc:
        return f"the probe does not build: {str(exc).splitlines()[0]}"
    if lib is None:
        return "no C compiler"
    scalar = sorted(set(names) - simd_variants(lib.image.read_bytes(), precision))
    if scalar:
        return f"the compiler kept scalar calls for {', '.join(scalar)}"
    inp = probe_inputs()
    if f32:  # the values the float kernel computes with
        with np.errstate(over="ignore"):
            inp = {k: v.astype(np.float32).astype(np.float64) for k, v in inp.items()}
    lane_in = {k: inp[k][None, None, :] for k in ("x", "u", "y")}
    out = CompiledKernel(spec, lib.cdll)(np.zeros((inp["x"].size, 1)), consts={},
                                         time_in={"w": np.ones((1, 1))},
                                         lane_in=lane_in).lane_out[0][0]
    dist = ulp_distance32 if f32 else ulp_distance
    for j, name in enumerate(names):
        err = float(np.max(dist(out[j], reference(name, inp["x"], inp["u"], inp["y"]))))
        if err > MAX_ULP:
            return (f"libmvec {name}{_suffix(precision)} is {err:.0f} ulp from scalar libm "
                    f"(allowed {MAX_ULP})")
    return None


def prelude(functions: Iterable[ca.Function], flags: tuple[str, ...], lanes: int,
            vector_math: bool | None = None, precision: str = "float64") -> str:
    """Declarations to put before kernels built from ``functions``: the SIMD variants of the
    trigonometric functions they use (float versions for float32 kernels), when wanted
    (``vector_math``; None: :func:`enabled`) and the probe passes; else empty (scalar libm
    calls)."""
    want = enabled() if vector_math is None else vector_math  # a bad value fails for every model
    names = used(functions)
    if not names or not want or unavailable(tuple(flags), lanes, precision) is not None:
        return ""
    return "/* libmvec SIMD variants (workbench/sampling/kernels/vector_math.py) */\n" + \
        declarations(names, precision)

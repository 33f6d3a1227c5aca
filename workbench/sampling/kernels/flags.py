"""Compiler flags, precisions and block width of the sampler kernels.

The lowest module of the kernels package: :mod:`.emit`, :mod:`.vector_math` and the library
loader (:mod:`.library`) read their flags and widths from here.

Block width (:func:`lane_count`): one vector register of samples, 256 or 512 bits
(:func:`vector_bits`: 512 when the kernels' compile target has AVX-512, else 256; the
environment variable ``WORKBENCH_VECTOR_BITS`` = 256 or 512 overrides it): four or eight samples
per block of a float64 kernel, eight or sixteen of a float32 one.
"""

from __future__ import annotations

import functools
import os
import subprocess

import workbench.environment as environment
from workbench.codegen.toolchain import find_toolchain
from workbench.validation import fail

LANES = 4  # samples per block of a float64 kernel on 256-bit vectors (the narrowest block)
PRECISIONS = ("float64", "float32")
_BITS = {"float64": 64, "float32": 32}
VECTOR_BITS_ENV = environment.VECTOR_BITS
VECTOR_BITS = (256, 512)

# -fsched-pressure -fschedule-insns: register-pressure-aware scheduling of the long
# straight-line step; measured 1.5x faster (fewer spills), results unchanged (no FP reordering).
# -fno-math-errno: libm calls do not set errno (results unchanged), so gcc may call the SIMD
# variants of the trigonometric functions inside the lane loop (vector_math.py);
# -fno-builtin-sin/cos: else gcc merges sin(a) and cos(a) into one sincos call, which it cannot
# vectorise (every heading-driven model has both).
KERNEL_FLAGS = ("-fopenmp", "-march=native", "-fsched-pressure", "-fschedule-insns",
                "-fno-math-errno", "-fno-builtin-sin", "-fno-builtin-cos")
KERNEL_FLAGS_F32 = ("-fno-builtin-sinf", "-fno-builtin-cosf")  # added for float32 kernels


def is_float32(precision: str) -> bool:
    """Whether ``precision`` (one of :data:`PRECISIONS`, else an error naming it) is float32."""
    if precision not in PRECISIONS:
        raise fail("precision", precision, f"allowed values are {PRECISIONS}")
    return precision == "float32"


def kernel_flags(precision: str = "float64") -> tuple[str, ...]:
    """Compiler flags of a kernel library (float32: the float builtins sinf/cosf off too)."""
    return KERNEL_FLAGS + (KERNEL_FLAGS_F32 if is_float32(precision) else ())


@functools.cache
def _target_has_avx512(flags: tuple[str, ...]) -> bool:
    """Whether the compiler's target for ``flags`` (the kernels' -march) has AVX-512F."""
    tc = find_toolchain()
    if tc is None:
        return False
    try:
        out = subprocess.run([tc.cc, *tc.flags, *flags, "-dM", "-E", "-x", "c", os.devnull],
                             capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return out.returncode == 0 and "#define __AVX512F__ 1" in out.stdout


def vector_bits() -> int:
    """The vector width (bits) the kernels block their samples for: ``WORKBENCH_VECTOR_BITS``
    (256 or 512) when set, else 512 when the kernels' compile target (their ``-march`` flag and
    ``WORKBENCH_CFLAGS``) has AVX-512F, else 256. Eight doubles per block on AVX-512 measured
    1.15x faster than four on the navigation SAIS rollout (AMD Zen 4)."""
    v = environment.choice(VECTOR_BITS_ENV, environment.VECTOR_BITS_ALLOWED,
                           environment.VECTOR_BITS_UNSET)
    if v is not None:
        return int(v)
    march = tuple(f for f in KERNEL_FLAGS if f.startswith("-m"))
    return 512 if _target_has_avx512(march) else 256


def lane_count(precision: str) -> int:
    """Samples per block of a kernel of ``precision``: one vector of :func:`vector_bits` (4 or
    8 float64 samples; float32: twice float64's)."""
    if precision not in _BITS:
        raise ValueError(f"precision = {precision!r} is invalid: allowed values are "
                         f"{PRECISIONS}")
    return vector_bits() // _BITS[precision]

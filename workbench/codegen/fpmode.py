"""The process's floating-point mode, and a guard that keeps a library load from changing it.

A shared library's constructors run when it is loaded; one linked with ``crtfastmath.o`` (what
``-ffast-math``, ``-Ofast`` or ``-mdaz-ftz`` link) sets flush-to-zero and denormals-are-zero for
the whole process, which changes every later floating-point result, NumPy's included.
:func:`mode` observes the mode by arithmetic (valid on any CPU): whether subnormal results are
flushed to zero, whether subnormal inputs are read as zero, and the rounding direction.
:func:`guard` saves the C floating-point environment (``fegetenv``) before a load, and when the
mode differs afterwards restores it (``fesetenv``) and raises :class:`FloatingPointModeError`.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import NamedTuple

import numpy as np


class FloatingPointModeError(RuntimeError):
    """Loading a library changed the process's floating-point mode."""


class Mode(NamedTuple):
    """What the arithmetic of this thread does now."""

    flush_to_zero: bool  # subnormal results become 0
    denormals_are_zero: bool  # subnormal inputs are read as 0
    rounding: str  # "nearest", "upward", "downward" or "toward zero"

    def describe(self) -> str:
        return (f"flush-to-zero {'on' if self.flush_to_zero else 'off'}, denormals-are-zero "
                f"{'on' if self.denormals_are_zero else 'off'}, rounding {self.rounding}")


NORMAL = Mode(False, False, "nearest")
_ROUNDING = {(False, False, True): "nearest", (True, False, True): "upward",
             (False, True, False): "downward", (False, False, False): "toward zero"}


def mode() -> Mode:
    """The current mode, from float64 arithmetic on values NumPy cannot fold away."""
    one, tiny = np.array([1.0]), np.array([5e-324])  # tiny: the smallest subnormal
    small, half = np.array([2.2250738585072014e-308]), np.array([0.5])
    ulp_half, ulp_3q = np.array([2.0 ** -53]), np.array([3 * 2.0 ** -54])
    up = bool((one + ulp_half)[0] > 1.0)  # a tie: nearest-even and below keep 1
    down = bool((-one - ulp_half)[0] < -1.0)
    near = bool((one + ulp_3q)[0] > 1.0)  # 0.75 ulp: rounds up only to nearest (or upward)
    return Mode(flush_to_zero=bool((small * half)[0] == 0.0),
                denormals_are_zero=bool((tiny * one)[0] == 0.0),
                rounding=_ROUNDING.get((up, down, near), "unknown"))


@functools.cache
def _libm() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("m")
    try:
        lib = ctypes.CDLL(name)
        lib.fegetenv.argtypes = lib.fesetenv.argtypes = [ctypes.c_void_p]
    except (OSError, AttributeError, TypeError):
        return None
    return lib


def _save() -> ctypes.Array | None:
    libm = _libm()
    buf = ctypes.create_string_buffer(512)  # larger than fenv_t on every platform
    return buf if libm is not None and libm.fegetenv(buf) == 0 else None


@contextmanager
def guard(what: Path | str) -> Iterator[None]:
    """Run the block (a library load) and check that the floating-point mode is unchanged;
    else restore the saved environment and raise :class:`FloatingPointModeError` naming
    ``what``, the modes before and after, and whether restoring succeeded."""
    saved, before = _save(), mode()
    yield
    after = mode()
    if after == before:
        return
    libm = _libm()
    if saved is not None and libm is not None:
        libm.fesetenv(saved)
    now = mode()
    state = ("restored" if now == before else
             f"could not be restored (it is now {now.describe()}; restart the process)")
    raise FloatingPointModeError(
        f"loading {what} changed this process's floating-point mode from {before.describe()} "
        f"to {after.describe()}; the mode was {state} and the library is not used. A library "
        "linked with crtfastmath.o (-ffast-math, -Ofast, -mdaz-ftz) or whose start-up code "
        "calls fesetround/fesetenv does this; build it without them")

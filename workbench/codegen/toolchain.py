"""Compiler discovery and the flags that enter the cache key.

Environment: ``WORKBENCH_CC`` (compiler; when it cannot be run, a warning names it and the
compiler used instead), ``WORKBENCH_CFLAGS`` (extra flags, appended to the required and default
ones; flags that change floating-point semantics are refused), ``WORKBENCH_COMPILE_TIMEOUT``
(seconds one compile may take before the compiler is killed; default 600),
``WORKBENCH_NO_CODEGEN=1`` (force the CasADi virtual machine / NumPy fallbacks).
"""

from __future__ import annotations

import functools
import math
import os
import shlex
import shutil
import subprocess
import warnings
from dataclasses import dataclass

from workbench.validation import fail, real

# Seconds one compile may take (WORKBENCH_COMPILE_TIMEOUT overrides it): a hung compiler is
# killed instead of hanging the build forever.
DEFAULT_COMPILE_TIMEOUT = 600.0

# Needed to build a loadable shared library at all; never removed by WORKBENCH_CFLAGS.
REQUIRED_FLAGS = ("-fPIC", "-shared")
# No -ffast-math: barriers rely on inf/nan. -ffp-contract=off keeps results equal to CasADi's VM.
DEFAULT_FLAGS = (
    "-O3", *REQUIRED_FLAGS, "-ffp-contract=off", "-fno-trapping-math",
    "-fno-semantic-interposition",
)
# Flags that change floating-point results or semantics, with the reason they are refused.
_INF_NAN = "barrier values and crash tests rely on inf/NaN, which it assumes away"
_REORDER = "it reorders or rewrites arithmetic, so results no longer equal CasADi's evaluation"
FORBIDDEN_FLAGS = {
    "-ffast-math": _INF_NAN + "; " + _REORDER,
    "-Ofast": "it implies -ffast-math: " + _INF_NAN,
    "-funsafe-math-optimizations": _REORDER,
    "-ffinite-math-only": _INF_NAN,
    "-fno-honor-infinities": _INF_NAN,
    "-fno-honor-nans": _INF_NAN,
    "-fassociative-math": _REORDER,
    "-freciprocal-math": _REORDER,
    "-fno-signed-zeros": _REORDER,
    "-fapprox-func": _REORDER,
    "-fcx-limited-range": _REORDER,
    "-ffp-contract=fast": "fused multiply-adds change rounding: " + _REORDER,
    "-ffp-contract=on": "fused multiply-adds change rounding: " + _REORDER,
    "-ffp-model=fast": _INF_NAN + "; " + _REORDER,
    "-ffp-model=aggressive": _INF_NAN + "; " + _REORDER,
    "-mfpmath=387": "x87 extended precision changes rounding: " + _REORDER,
}


@dataclass(frozen=True)
class Toolchain:
    """A C compiler, its version line and the flags used for every build. ``timeout``: seconds
    one compile may take (None: :func:`compile_timeout`); it is not part of :meth:`key`."""

    cc: str
    version: str
    flags: tuple[str, ...]
    timeout: float | None = None

    def __post_init__(self) -> None:
        if self.timeout is not None:
            object.__setattr__(self, "timeout", real("Toolchain.timeout", self.timeout, 0.0,
                                                     strict=True))

    def key(self) -> str:
        return "\n".join([self.cc, self.version, *self.flags])

    def describe(self) -> str:
        return f"{self.cc} ({self.version}) with {' '.join(self.flags)}"


@functools.cache
def _version(cc: str) -> str | None:
    try:
        out = subprocess.run([cc, "--version"], capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return out.stdout.splitlines()[0].strip() if out.returncode == 0 and out.stdout else None


def build_flags(extra: str | None) -> tuple[str, ...]:
    """The default flags followed by ``extra`` (WORKBENCH_CFLAGS); refuses flags that change
    floating-point semantics, naming the flag and the reason."""
    if not extra:
        return DEFAULT_FLAGS
    try:
        words = tuple(shlex.split(extra))
    except ValueError as exc:
        raise fail("WORKBENCH_CFLAGS", extra, f"cannot be split into flags ({exc})") from exc
    for w in words:
        reason = FORBIDDEN_FLAGS.get(w)
        if reason is None and w.startswith("-ffp-contract=") and w != "-ffp-contract=off":
            reason = "fused multiply-adds change rounding: " + _REORDER
        if reason is not None:
            raise fail("WORKBENCH_CFLAGS", extra,
                       f"{w} changes floating-point semantics and is refused: {reason}")
    return DEFAULT_FLAGS + words


def compile_timeout() -> float:
    """``WORKBENCH_COMPILE_TIMEOUT`` (seconds, a finite number > 0) or
    :data:`DEFAULT_COMPILE_TIMEOUT`."""
    text = os.environ.get("WORKBENCH_COMPILE_TIMEOUT", "").strip()
    if not text:
        return DEFAULT_COMPILE_TIMEOUT
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise fail("WORKBENCH_COMPILE_TIMEOUT", text, "must be a finite number of seconds > 0 "
                   f"(unset: {DEFAULT_COMPILE_TIMEOUT:g} s)")
    return value


_WARNED: set[tuple[str, str]] = set()


def find_toolchain() -> Toolchain | None:
    """The compiler to use, or None when codegen is disabled or no compiler is found."""
    if os.environ.get("WORKBENCH_NO_CODEGEN", "") not in ("", "0"):
        return None
    flags = build_flags(os.environ.get("WORKBENCH_CFLAGS"))
    timeout = compile_timeout()
    wanted = os.environ.get("WORKBENCH_CC")
    names = [wanted] if wanted else []
    names += [n for n in (os.environ.get("CC"), "cc", "gcc", "clang") if n]
    for name in names:
        path = shutil.which(name)
        if path and (version := _version(path)):
            tc = Toolchain(cc=path, version=version, flags=flags, timeout=timeout)
            if wanted and name != wanted and (wanted, path) not in _WARNED:
                _WARNED.add((wanted, path))
                warnings.warn(f"WORKBENCH_CC = {wanted!r} is not a working C compiler (not found "
                              f"on PATH or '{wanted} --version' failed); using {tc.describe()}",
                              RuntimeWarning, stacklevel=2)
            return tc
    if wanted and (wanted, "") not in _WARNED:
        _WARNED.add((wanted, ""))
        warnings.warn(f"WORKBENCH_CC = {wanted!r} is not a working C compiler and no other "
                      "compiler was found", RuntimeWarning, stacklevel=2)
    return None

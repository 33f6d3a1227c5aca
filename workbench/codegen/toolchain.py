"""Compiler discovery and the flags that enter the cache key.

Environment (parsed by :mod:`workbench.environment`): ``WORKBENCH_CC`` (compiler; one that cannot
be run is refused, naming it), ``WORKBENCH_CFLAGS`` (extra flags,
appended to the required and default ones; what :func:`check_flags` refuses is an error),
``WORKBENCH_COMPILE_TIMEOUT`` (seconds one compile may take before the compiler is killed;
default 600), ``WORKBENCH_NO_CODEGEN`` (a switch: on forces the CasADi virtual machine / NumPy
fallbacks).
"""

from __future__ import annotations

import functools
import os
import shutil
import subprocess
from dataclasses import dataclass

import workbench.environment as env
from workbench.environment import DEFAULT_COMPILE_TIMEOUT
from workbench.validation import fail, real

__all__ = ["DEFAULT_COMPILE_TIMEOUT", "DEFAULT_FLAGS", "FORBIDDEN_FLAGS", "REQUIRED_FLAGS",
           "Toolchain", "build_flags", "check_environment", "check_flags", "compile_timeout",
           "find_toolchain"]

# Needed to build a loadable shared library at all; never removed by WORKBENCH_CFLAGS.
REQUIRED_FLAGS = ("-fPIC", "-shared")
# No -ffast-math: barriers rely on inf/nan. -ffp-contract=off keeps results equal to CasADi's VM.
DEFAULT_FLAGS = (
    "-O3", *REQUIRED_FLAGS, "-ffp-contract=off", "-fno-trapping-math",
    "-fno-semantic-interposition",
)
# Flags that change floating-point results or semantics, with the reason they are refused.
_FP_MODE = ("it sets flush-to-zero and denormals-are-zero for the whole process when the "
            "library loads, changing every later floating-point result")
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
    "-mdaz-ftz": _FP_MODE,
}
# Words that would put code or flags into every library that the checks above cannot see: an
# object file or archive (crtfastmath.o, which -ffast-math links, sets flush-to-zero when the
# library loads), a library, a response file, a linker pass-through, another start-up file set.
_INPUT = ("it adds code or flags these checks cannot see to every library (an object file such "
          "as crtfastmath.o changes the floating-point mode of the whole process when the "
          "library loads)")
_INPUT_PREFIXES = ("@", "-Wl,", "-Xlinker", "-Xassembler", "-Xpreprocessor", "-l", "-L", "-B",
                   "-specs", "--specs", "-nostartfiles", "-nostdlib", "-include", "-imacros",
                   "-x", "-fplugin")


@dataclass(frozen=True)
class Toolchain:
    """A C compiler, its version line and the flags used for every build. ``timeout``: seconds
    one compile may take (None: :func:`compile_timeout`); it is not part of :meth:`key`."""

    cc: str
    version: str
    flags: tuple[str, ...]
    timeout: float | None = None

    def __post_init__(self) -> None:
        check_flags("Toolchain.flags", tuple(self.flags))
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


def _refusal(word: str) -> str | None:
    """Why ``word`` may not be passed to the compiler (after the word), or None."""
    reason = FORBIDDEN_FLAGS.get(word)
    if reason is None and word.startswith("-ffp-contract=") and word != "-ffp-contract=off":
        reason = "fused multiply-adds change rounding: " + _REORDER
    if reason is not None:
        return f"changes floating-point semantics and is refused: {reason}"
    if "fastmath" in word.lower() or word.startswith(_INPUT_PREFIXES) or not word.startswith("-"):
        return f"is refused: {_INPUT}"
    return None


def check_flags(field: str, flags: tuple[str, ...], shown: object = None) -> tuple[str, ...]:
    """``flags`` unchanged; else an error naming ``field`` (with the value ``shown``, default
    ``flags``), the first refused flag and why: flags that change floating-point semantics
    (:data:`FORBIDDEN_FLAGS`, any ``-ffp-contract`` but ``off``) or the process's floating-point
    mode (``-mdaz-ftz``), and words that add inputs (object files, archives, libraries,
    response files ``@FILE``, ``-Wl,``/``-Xlinker`` pass-throughs, ``-l``, ``-L``, ``-B``,
    ``-specs``, ``-include``, ``-x``, ``-fplugin``, anything naming crtfastmath)."""
    for w in flags:
        reason = _refusal(w)
        if reason is not None:
            raise fail(field, flags if shown is None else shown, f"{w} {reason}")
    return flags


def build_flags(extra: str | None = None) -> tuple[str, ...]:
    """The default flags followed by ``extra`` (default: ``$WORKBENCH_CFLAGS``, split like a
    shell would); refuses what :func:`check_flags` refuses with an
    :class:`~workbench.environment.EnvironmentVariableError` naming the variable and flag."""
    text = env.raw(env.CFLAGS) if extra is None else extra
    words = env.split(env.CFLAGS, text) if text else ()
    try:
        check_flags(env.CFLAGS, words, text)
    except ValueError as exc:
        raise env.EnvironmentVariableError(str(exc)) from None
    return DEFAULT_FLAGS + words


def compile_timeout() -> float:
    """``WORKBENCH_COMPILE_TIMEOUT`` (seconds, a finite number > 0) or
    :data:`DEFAULT_COMPILE_TIMEOUT`."""
    return env.seconds(env.COMPILE_TIMEOUT, DEFAULT_COMPILE_TIMEOUT)


def check_environment() -> None:
    """Read every ``WORKBENCH_*`` variable (:func:`workbench.environment.check`) and refuse the
    flags of ``WORKBENCH_CFLAGS`` that :func:`check_flags` refuses, and a ``WORKBENCH_CC`` that
    is not a working compiler (its ``--version`` is the only thing run)."""
    env.check()
    build_flags()
    if env.command(env.CC):
        find_toolchain()


def find_toolchain() -> Toolchain | None:
    """The compiler to use, or None when codegen is disabled or no compiler is found.

    A ``WORKBENCH_CC`` that is not a working compiler is refused (it is never replaced by
    another compiler)."""
    if env.switch(env.NO_CODEGEN, False):
        return None
    flags = build_flags()
    timeout = compile_timeout()
    wanted = env.command(env.CC)
    if wanted:
        path = shutil.which(wanted)
        version = _version(path) if path else None
        if not path or not version:
            raise env.invalid(env.CC, wanted, "must name a working C compiler ("
                              + ("not found on PATH" if not path else f"'{path} --version' failed")
                              + "); unset it to use the first of $CC, cc, gcc, clang")
        return Toolchain(cc=path, version=version, flags=flags, timeout=timeout)
    for name in (os.environ.get("CC"), "cc", "gcc", "clang"):
        path = shutil.which(name) if name else None
        if path and (version := _version(path)):
            return Toolchain(cc=path, version=version, flags=flags, timeout=timeout)
    return None

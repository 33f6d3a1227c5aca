"""Compiler discovery and the flags that enter the cache key.

Environment: ``WORKBENCH_CC`` (compiler), ``WORKBENCH_CFLAGS`` (replaces the default flags),
``WORKBENCH_NO_CODEGEN=1`` (force the CasADi virtual machine / NumPy fallbacks).
"""

from __future__ import annotations

import functools
import os
import shlex
import shutil
import subprocess
from dataclasses import dataclass

# No -ffast-math: barriers rely on inf/nan. -ffp-contract=off keeps results equal to CasADi's VM.
DEFAULT_FLAGS = (
    "-O3", "-fPIC", "-shared", "-ffp-contract=off", "-fno-trapping-math",
    "-fno-semantic-interposition",
)


@dataclass(frozen=True)
class Toolchain:
    """A C compiler, its version line and the flags used for every build."""

    cc: str
    version: str
    flags: tuple[str, ...]

    def key(self) -> str:
        return "\n".join([self.cc, self.version, *self.flags])


@functools.cache
def _version(cc: str) -> str | None:
    try:
        out = subprocess.run([cc, "--version"], capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return out.stdout.splitlines()[0].strip() if out.returncode == 0 and out.stdout else None


def find_toolchain() -> Toolchain | None:
    """The compiler to use, or None when codegen is disabled or no compiler is found."""
    if os.environ.get("WORKBENCH_NO_CODEGEN", "") not in ("", "0"):
        return None
    names = [os.environ["WORKBENCH_CC"]] if os.environ.get("WORKBENCH_CC") else []
    names += [n for n in (os.environ.get("CC"), "cc", "gcc", "clang") if n]
    for name in names:
        path = shutil.which(name)
        if path and (version := _version(path)):
            flags = os.environ.get("WORKBENCH_CFLAGS")
            return Toolchain(path, version, tuple(shlex.split(flags)) if flags else DEFAULT_FLAGS)
    return None

"""The ``WORKBENCH_*`` environment variables, each read strictly in one place.

Every variable is parsed here; a value that is not allowed raises :class:`EnvironmentVariableError`
(a ValueError) naming the variable, the value and what is allowed; a bad value never turns into
the default. Unset and empty (or only blanks) mean the default. Switches accept,
case-insensitively, ``1 true yes on`` for on and ``0 false no off`` for off (:data:`TRUE`,
:data:`FALSE`). :func:`check` reads them all, so a command fails before any work with the
variable named. Checks that need the variable's meaning are made where it is used and raise the
same error (the refused flags of ``WORKBENCH_CFLAGS``: :mod:`workbench.codegen.toolchain`).
"""

from __future__ import annotations

import math
import os
import re
import shlex
from pathlib import Path

from workbench.validation import UserError

TRUE = ("1", "true", "yes", "on")
FALSE = ("0", "false", "no", "off")

CACHE_DIR = "WORKBENCH_CACHE_DIR"
CC = "WORKBENCH_CC"
CFLAGS = "WORKBENCH_CFLAGS"
COMPILE_TIMEOUT = "WORKBENCH_COMPILE_TIMEOUT"
NO_CODEGEN = "WORKBENCH_NO_CODEGEN"
VECTOR_MATH = "WORKBENCH_VECTOR_MATH"
VECTOR_BITS = "WORKBENCH_VECTOR_BITS"
STUDIES = "WORKBENCH_STUDIES"
PLUGINS = "WORKBENCH_PLUGINS"
DEFAULT_COMPILE_TIMEOUT = 600.0  # seconds one compile may take
VECTOR_BITS_ALLOWED = ("256", "512")
VECTOR_BITS_UNSET = "512 when the compile target has AVX-512F, else 256"
VARIABLES = (CACHE_DIR, CC, CFLAGS, COMPILE_TIMEOUT, NO_CODEGEN, VECTOR_MATH, VECTOR_BITS,
             STUDIES, PLUGINS)

_MODULE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*")


class EnvironmentVariableError(UserError):
    """A ``WORKBENCH_*`` variable holds a value that is not allowed (the message names it)."""


def _fail(name: str, value: str, allowed: str) -> EnvironmentVariableError:
    return EnvironmentVariableError(f"{name} = {value!r} is invalid: {allowed}")


def invalid(name: str, value: str, allowed: str) -> EnvironmentVariableError:
    """The error for variable ``name`` holding ``value``, saying what is allowed (for checks
    made where the value is used, e.g. a compiler flag that is refused)."""
    return _fail(name, value, allowed)


def raw(name: str) -> str | None:
    """The variable's text with surrounding blanks removed; None when unset or blank."""
    text = os.environ.get(name)
    if text is None or not text.strip():
        return None
    return text.strip()


def switch(name: str, default: bool) -> bool:
    """A switch: one of :data:`TRUE` or :data:`FALSE` (any case), or ``default`` when unset."""
    text = raw(name)
    if text is None:
        return default
    low = text.lower()
    if low in TRUE or low in FALSE:
        return low in TRUE
    raise _fail(name, text, f"allowed values are {', '.join(TRUE)} (on) and {', '.join(FALSE)} "
                f"(off), in any case; unset: {'on' if default else 'off'}")


def choice(name: str, allowed: tuple[str, ...], unset: str) -> str | None:
    """One of ``allowed`` exactly, or None when unset (``unset`` says what that means)."""
    text = raw(name)
    if text is None or text in allowed:
        return text
    raise _fail(name, text, f"allowed values are {', '.join(allowed)} (unset: {unset})")


def seconds(name: str, default: float) -> float:
    """A finite number of seconds > 0, or ``default`` when unset."""
    text = raw(name)
    if text is None:
        return default
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise _fail(name, text, f"must be a finite number of seconds > 0 (unset: {default:g} s)")
    return value


def split(name: str, text: str) -> tuple[str, ...]:
    """``text`` (the value of ``name``) split into words like a shell would (quotes group)."""
    try:
        return tuple(shlex.split(text))
    except ValueError as exc:
        raise _fail(name, text, f"cannot be split into words like a shell would ({exc})") from exc


def words(name: str) -> tuple[str, ...]:
    """The variable's shell-like words, or () when unset."""
    text = raw(name)
    return () if text is None else split(name, text)


def modules(name: str) -> tuple[str, ...]:
    """Comma-separated Python module names (dotted identifiers; empty entries skipped)."""
    text = raw(name)
    if text is None:
        return ()
    out = tuple(p.strip() for p in text.split(",") if p.strip())
    for m in out:
        if not _MODULE.fullmatch(m):
            raise _fail(name, text, f"{m!r} is not a module name: give comma-separated dotted "
                        "Python module names such as my_studies.pendulum")
    return out


def path(name: str) -> Path | None:
    """A directory path (``~`` expanded, resolved; it need not exist but must not be an
    existing non-directory), or None when unset."""
    text = raw(name)
    if text is None:
        return None
    if "\0" in text:
        raise _fail(name, text, "a path cannot contain a NUL character")
    where = Path(text).expanduser().resolve()
    if where.exists() and not where.is_dir():
        raise _fail(name, text, f"{where} is an existing file, not a directory (point {name} "
                    "at a directory)")
    return where


def command(name: str) -> str | None:
    """A program name or path (one word), or None when unset."""
    text = raw(name)
    if text is not None and len(text.split()) != 1:
        raise _fail(name, text, "must be one program name or path (put flags in "
                    f"{CFLAGS})")
    return text


def check() -> None:
    """Read every ``WORKBENCH_*`` variable of this module; the first bad one raises
    :class:`EnvironmentVariableError`. Module names are checked as names, not imported."""
    path(CACHE_DIR)
    command(CC)
    words(CFLAGS)
    seconds(COMPILE_TIMEOUT, DEFAULT_COMPILE_TIMEOUT)
    switch(NO_CODEGEN, False)
    switch(VECTOR_MATH, True)
    choice(VECTOR_BITS, VECTOR_BITS_ALLOWED, VECTOR_BITS_UNSET)
    modules(STUDIES)
    modules(PLUGINS)

"""Input checks that fail fast with a message naming the field, the value and what is allowed.

Sizes have documented upper bounds, checked when a config is built, so that a typo such as
``realisations=10**12`` fails at once instead of allocating until memory runs out:
:data:`MAX_TASKS` tasks per study run, :data:`MAX_STEPS` steps per episode (or calibration run),
:data:`MAX_BATCH` entries (samples x horizon x controls) per sampled batch.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Sequence
from numbers import Integral, Real
from pathlib import Path

import numpy as np

MAX_TASKS = 10**7  # tasks of one study run
MAX_STEPS = 10**7  # plant steps of one episode or calibration run
MAX_BATCH = 2**31  # entries n_samples * horizon * nu of one sampled batch
_TINY = float(np.finfo(np.float64).tiny)  # the smallest normal float64, 2.2e-308


class UserError(ValueError):
    """An input or setting the user gave that is not allowed (a config value, a command-line
    argument, an environment variable, a study's registration); the message names it, the
    value and what is allowed. The ``workbench`` command prints the message and exits 2."""


def _show(value: object) -> str:
    if isinstance(value, str) or (isinstance(value, tuple | list) and any(
            isinstance(v, bool | np.bool_) for v in value)):
        text = repr(value)  # as written: NumPy would show True as 1
    else:
        text = np.array2string(np.asarray(value), precision=6, threshold=12)
    return text if len(text) <= 120 else text[:117] + "..."


def fail(field: str, value: object, allowed: str) -> ValueError:
    """Build the one error shape used everywhere: field, value, what is allowed."""
    return ValueError(f"{field} = {_show(value)} is invalid: {allowed}")


def as_array(field: str, value: object, shape: Sequence[int | None], *, finite: bool = True):
    """Return ``value`` as a float64 array of ``shape`` (None = any size) or raise ValueError."""
    try:
        arr = np.array(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise fail(field, value, "expected a numeric array") from exc
    if arr.ndim == 0 and len(shape) == 1 and shape[0] == 1:
        arr = arr.reshape(1)
    ok = arr.ndim == len(shape) and all(
        s is None or s == n for s, n in zip(shape, arr.shape, strict=True))
    if not ok:
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise fail(field, value, f"expected shape {want}, got {arr.shape}")
    if finite and not np.all(np.isfinite(arr)):
        raise fail(field, value, "all entries must be finite")
    return arr


def _isfinite(value: Real) -> bool:
    """``np.isfinite`` of the number as given (NumPy's stubs do not list ``numbers.Real``)."""
    return bool(np.isfinite(value))  # type: ignore[call-overload]


def _isnan(value: Real) -> bool:
    """``np.isnan`` of the number as given (NumPy's stubs do not list ``numbers.Real``)."""
    return bool(np.isnan(value))  # type: ignore[call-overload]


def integer(field: str, value: object, minimum: int | None = None,
            maximum: int | None = None) -> int:
    """An integer (Python or NumPy; never ``bool``) within [minimum, maximum]."""
    if (not isinstance(value, Integral) or isinstance(value, bool | np.bool_)
            or (minimum is not None and value < minimum)
            or (maximum is not None and not value <= maximum)):
        rng = ("" if minimum is None and maximum is None else
               f" >= {minimum}" if maximum is None else
               f" <= {maximum}" if minimum is None else f" in [{minimum}, {maximum}]")
        raise fail(field, value, f"must be an integer{rng}")
    return int(value)


def real(field: str, value: object, minimum: float | None = None, *, strict: bool = False,
         maximum: float | None = None) -> float:
    """A finite real number (never ``bool``); above ``minimum`` (``strict``: strictly), at most
    ``maximum``."""
    if isinstance(value, Real) and not isinstance(value, bool | np.bool_) and _isfinite(value):
        # (numbers.Real declares < and <= only; value is finite here)
        above = minimum is None or (not value <= minimum if strict else not value < minimum)
        if above and (maximum is None or value <= maximum):
            return float(value)
    parts = ([f"{'>' if strict else '>='} {minimum:g}"] if minimum is not None else []) + (
        [f"<= {maximum:g}"] if maximum is not None else [])
    raise fail(field, value, "must be a finite number" + (" " + " and ".join(parts)
                                                          if parts else ""))


def scale(field: str, value: object, power: int = 1) -> float:
    """A positive scale (a standard deviation with ``power=2``, a temperature with ``power=1``)
    whose ``power``-th power and its reciprocal are both normal float64 numbers, so that
    ``value**power`` neither underflows to 0 (a degenerate distribution, weights of 0/0) nor
    overflows: ``value`` in [tiny^(1/power), tiny^(-1/power)], tiny = 2.2e-308 (about
    [2.2e-308, 4.5e307] for power 1, [1.5e-154, 6.7e153] for power 2)."""
    if isinstance(value, Real) and not isinstance(value, bool | np.bool_):
        with np.errstate(all="ignore"):
            try:
                v = np.float64(value)
            except OverflowError:  # an int beyond float64
                v = np.float64(np.inf)
            p = v**power
            inv = 1.0 / p if p != 0 else np.inf
        if (np.isfinite(v) and v > 0 and np.isfinite(p) and p >= _TINY
                and np.isfinite(inv) and inv >= _TINY):
            return float(value)
    lo, hi = _TINY ** (1.0 / power), _TINY ** (-1.0 / power)
    what = "the value" if power == 1 else "its square" if power == 2 else f"value^{power}"
    raise fail(field, value, f"must be a finite number in [{lo:.4g}, {hi:.4g}] ({what} and "
               "its reciprocal must be normal float64 numbers: no underflow to 0, no overflow)")


def at_most(field: str, value: object, total: int, limit: int, what: str) -> None:
    """Refuse a size: ``total`` (``what``, computed from ``value`` of ``field`` and others) must
    be <= ``limit``."""
    if total > limit:
        raise fail(field, value, f"gives {what} = {total}, above the limit {limit}; lower it")


def real_or_inf(field: str, value: object) -> float:
    """A real number (never ``bool``) or +inf: NaN and -inf are rejected."""
    if (not isinstance(value, Real) or isinstance(value, bool | np.bool_) or _isnan(value)
            or value == -np.inf):
        raise fail(field, value, "must be a number or +inf")
    return float(value)


def flag(field: str, value: object) -> bool:
    """A ``bool`` (Python or NumPy), nothing else: 0 and 1 are not flags."""
    if not isinstance(value, bool | np.bool_):
        raise fail(field, value, "must be true or false")
    return bool(value)


def positive(field: str, value: float, *, allow_zero: bool = False) -> float:
    """A finite real number > 0 (``allow_zero``: >= 0): :func:`real` with minimum 0."""
    return real(field, value, 0.0, strict=not allow_zero)


def one_of(field: str, value: str, allowed: Sequence[str]) -> str:
    """Check a choice among named options."""
    if value not in allowed:
        raise fail(field, value, f"allowed values are {', '.join(map(repr, allowed))}")
    return value


def bounds(field_lo: str, lo: np.ndarray, field_hi: str, hi: np.ndarray) -> None:
    """Check lo <= hi elementwise (infinite bounds allowed, NaN never)."""
    if np.any(np.isnan(lo)) or np.any(np.isnan(hi)):
        raise fail(field_lo if np.any(np.isnan(lo)) else field_hi, lo, "bounds must not be NaN")
    bad = np.flatnonzero(lo > hi)
    if bad.size:
        i = int(bad[0])
        raise ValueError(
            f"{field_lo}[{i}] = {lo[i]:g} is above {field_hi}[{i}] = {hi[i]:g}: "
            f"each lower bound must be <= its upper bound"
        )


def writable_dir(field: str, path) -> Path:
    """Check that ``path`` is (or can be created as) a directory this process can write:
    returns it as a Path (a leading ``~`` expanded), or raises ValueError naming ``field``.
    Creates the directory."""
    p = Path(os.path.expanduser(str(path)))
    if str(p).startswith("~"):
        raise fail(field, str(path), "starts with ~ but names no user with a home folder")
    if p.exists() and not p.is_dir():
        raise fail(field, str(p), "is an existing file, not a directory")
    for parent in p.parents:
        if parent.exists():
            if not parent.is_dir():
                raise fail(field, str(p), f"its parent {parent} is a file, not a directory")
            break
    try:
        p.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=p):
            pass
    except OSError as exc:
        raise fail(field, str(p), f"is not a writable directory ({exc.strerror or exc})") from exc
    return p

"""Atomic result files and run manifests.

Files are written atomically (a temporary file beside the target, renamed into place) with the
permissions an ordinary ``open`` would give: ``0666 & ~umask`` (directories ``0777 & ~umask``),
so that others can read a report when the umask allows it. JSON files are strict JSON
(RFC 8259): a non-finite number (NaN, +-inf) is written as ``null``.

A write that the system refuses (disk full, quota exceeded, file-size limit, read-only file
system, no permission) raises :class:`StorageError`, which names the file and the reason; the
temporary file is removed and the target keeps its previous content (or stays absent).
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import json
import math
import os
import platform
import subprocess
import tempfile
from collections.abc import Mapping
from importlib import metadata
from pathlib import Path

import numpy as np


def current_umask() -> int:
    """The process's umask, read without changing it where the system allows (Linux:
    /proc/self/status); elsewhere set and restored at once."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    old = os.umask(0o022)
    os.umask(old)
    return old


_HINTS = {
    errno.ENOSPC: "the disk is full; free some space",
    errno.EDQUOT: "the disk quota is exceeded; free some space or raise the quota",
    errno.EFBIG: "the file is larger than the file system or the process's file-size limit "
                 "(ulimit -f) allows",
    errno.EROFS: "the file system is read-only",
    errno.EACCES: "this user may not write there",
    errno.EPERM: "this user may not write there",
    errno.EIO: "the device reported an input/output error",
}


class StorageError(OSError):
    """A result file could not be written: the message names the file, the system's reason
    (with its errno name, e.g. ENOSPC) and what it means. ``errno`` and ``filename`` are those
    of the underlying OSError; ``path`` is the file that was being written."""

    def __init__(self, path: Path | str, exc: OSError, advice: str = ""):
        super().__init__(exc.errno, exc.strerror or str(exc), str(path))
        self.path = Path(path)
        self.cause = exc
        name = errno.errorcode.get(exc.errno or 0, "")
        hint = _HINTS.get(exc.errno or 0, "")
        self.message = (f"cannot write {self.path}: {exc.strerror or exc}"
                        + (f" ({name})" if name else "") + (f": {hint}" if hint else "")
                        + (f"; {advice}" if advice else ""))

    def __str__(self) -> str:
        return self.message

    def __reduce__(self):
        return (_storage_error, (str(self.path), self.cause, self.message))

    def with_advice(self, advice: str) -> StorageError:
        """The same error with a sentence on what to do appended."""
        err = StorageError(self.path, self.cause)
        err.message = f"{self.message}; {advice}"
        return err


def _storage_error(path: str, exc: OSError, message: str) -> StorageError:
    err = StorageError(path, exc)
    err.message = message
    return err


def make_dirs(path: Path) -> None:
    """Create ``path`` and its parents with mode ``0777 & ~umask`` (as ``mkdir -p``)."""
    Path(path).mkdir(mode=0o777, parents=True, exist_ok=True)


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write to a temporary file beside ``path`` and rename it into place; the file gets mode
    ``0666 & ~umask``, as a plain ``open(path, "wb")`` would give it. Raises
    :class:`StorageError` (naming ``path``) when the system refuses the write; no temporary
    file is left behind and ``path`` keeps its previous content."""
    path = Path(path)
    tmp = None
    try:
        make_dirs(path.parent)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        try:
            os.fchmod(fd, 0o666 & ~current_umask())  # mkstemp creates 0600
        except OSError:  # a file system without modes: keep what it gives
            pass
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.replace(tmp, path)
        tmp = None
    except StorageError:
        raise
    except OSError as exc:
        raise StorageError(path, exc) from exc
    finally:
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def numpy_default(o):
    """The ``default`` of :func:`json.dumps` for NumPy values: arrays as lists, scalars as
    Python numbers; anything else is a TypeError naming its type."""
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def strict_json(obj):
    """``obj`` as strict-JSON-ready data: NumPy arrays and scalars as Python values, tuples as
    lists, dataclasses as dicts, and every non-finite float (NaN, +-inf) as ``None`` (JSON
    ``null``). A reader of such a file gets None where the writer had NaN or inf."""
    if isinstance(obj, bool | np.bool_):
        return bool(obj)
    if isinstance(obj, float | np.floating):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, np.ndarray):
        return strict_json(obj.tolist())
    if isinstance(obj, np.generic):
        return strict_json(obj.item())
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: strict_json(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, Mapping):
        return {k.item() if isinstance(k, np.generic) else k: strict_json(v)
                for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [strict_json(v) for v in obj]
    return obj


def dumps_json(obj, **kw) -> str:
    """Strict JSON text of ``obj`` (:func:`strict_json`: NaN and inf as null)."""
    return json.dumps(strict_json(obj), allow_nan=False, default=numpy_default, **kw)


def atomic_write_json(path: Path, obj) -> None:
    """Write ``obj`` as strict JSON (NaN and inf as null, see :func:`strict_json`)."""
    atomic_write_text(path, dumps_json(obj, indent=2) + "\n")


def manifest() -> dict[str, object]:
    """Git revision, package versions and platform for a run's provenance."""
    try:
        rev = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True,
                             cwd=Path(__file__).parent, timeout=10).stdout.strip() or None
    except (OSError, subprocess.TimeoutExpired):
        rev = None
    versions: dict[str, str | None] = {}
    for pkg in ("casadi", "numpy", "scipy", "osqp", "qpsolvers", "daqp", "pandas", "matplotlib",
                "pyarrow", "tqdm", "dask", "distributed"):
        try:
            versions[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            versions[pkg] = None
    return {"git_revision": rev, "versions": versions, "python": platform.python_version(),
            "platform": platform.platform()}

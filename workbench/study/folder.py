"""A run folder belongs to one run.

Two hidden files mark it: ``.workbench-run.json`` (the marker: the study, what the run is -- its
study, version, seed, config, fingerprint and task list, the same fields as the start of
``manifest.json`` -- with a SHA-256 of that, and when the folder was claimed) and
``.workbench-run.lock`` (locked while a run or a report rebuild uses the folder).

:func:`claim` takes a folder for a run before anything else is written to it:

- a new or empty folder is claimed: the marker is written first;
- a folder whose marker names the same run is continued (finished tasks are kept);
- a folder whose marker names another study, or the same study with another config (or a study
  version that declares other tasks), is refused; the error names the differing keys and says
  what to do: choose another ``--out``, delete the folder, or continue the stored run with its
  own config (``--config FOLDER/config.toml``). Nothing in the folder is changed;
- a folder without a marker but with the ``manifest.json`` that earlier versions wrote is
  treated the same way, the manifest standing in for the marker (the marker is then added);
- any other folder holding files is refused, naming some of them: a run never writes over files
  it did not write (a user's own ``config.toml``, ``report.md`` or ``summary.json``);
- a marker or manifest that is not valid JSON (truncated, edited) is an error naming the file.

Within a claimed folder the run writes ``manifest.json``, ``config.toml``, ``run.json``,
``summary.json``, ``errors.json``, the tables, ``report.md`` and its figures and ``tasks/``; it
deletes nothing else.

The lock (``flock``, exclusive, non-blocking) makes a second run or report rebuild on the same
folder fail at once, naming the process that holds it; the system releases it when its holder
ends, however it ends (``kill -9`` included), so a stopped run never leaves a stale lock. It is
re-entrant within one thread (:func:`workbench.study.runner.run` holds it while
:func:`workbench.study.run_study` takes it again); another thread of the same process is
refused like another process. On network file systems ``flock`` may lock only per machine.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
import socket
import threading
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from workbench.study.config_io import ConfigError
from workbench.study.io import StorageError, atomic_write_json, current_umask, dumps_json
from workbench.validation import fail

MARKER = ".workbench-run.json"
LOCK = ".workbench-run.lock"
MANIFEST = "manifest.json"
IDENTITY_KEYS = ("study", "version", "seed", "config", "fingerprint", "n_tasks", "tasks_sha256")
_OURS = {MARKER, LOCK}

_HELD: dict[str, list] = {}  # real path -> [fd, depth, thread id]
_GUARD = threading.Lock()


class RunFolderError(ConfigError):
    """A folder that this run may not use (another run's, a user's, in use, unreadable)."""


# ---------------------------------------------------------------------- reading JSON files
def read_json(path: Path, what: str, advice: str) -> Any:
    """The JSON content of ``path``; a missing, unreadable or invalid file is a
    :class:`RunFolderError` naming the file, saying what is wrong and ``advice``."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError as exc:
        raise RunFolderError(f"{path}: no {what} ({advice})") from exc
    except (OSError, UnicodeDecodeError) as exc:
        reason = getattr(exc, "strerror", None) or str(exc)
        raise RunFolderError(f"{path}: cannot read the {what} ({reason}); {advice}") from exc
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        state = "empty" if not text.strip() else "not valid JSON"
        raise RunFolderError(f"{path} is {state} ({exc.msg} at line {exc.lineno}, column "
                             f"{exc.colno}): the {what} was cut short or edited; {advice}"
                             ) from exc


# ---------------------------------------------------------------------- identity of a run
def canonical(identity: Mapping[str, Any]) -> dict[str, Any]:
    """The identity fields as strict JSON data (inf and NaN as null), the form they are
    stored in."""
    return json.loads(dumps_json({k: identity.get(k) for k in IDENTITY_KEYS}))


def digest(identity: Mapping[str, Any]) -> str:
    """SHA-256 of the canonical identity (sorted keys, no spaces)."""
    text = dumps_json(canonical(identity), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def _flat(obj: Any, prefix: str) -> dict[str, Any]:
    if isinstance(obj, dict):
        out: dict[str, Any] = {}
        for k, v in obj.items():
            out.update(_flat(v, f"{prefix}.{k}" if prefix else str(k)))
        return out or {prefix: {}}
    return {prefix: obj}


def _show(v: Any) -> str:
    text = "absent" if v is _ABSENT else json.dumps(v)
    return text if len(text) <= 40 else text[:37] + "..."


_ABSENT = object()


def differences(stored: Mapping[str, Any], wanted: Mapping[str, Any]) -> list[str]:
    """The keys in which two identities differ, as ``key: A in the folder, B now``."""
    a, b = _flat(canonical(stored), ""), _flat(canonical(wanted), "")
    out = []
    for key in sorted(set(a) | set(b), key=lambda k: (k.startswith(("n_tasks", "tasks")), k)):
        va, vb = a.get(key, _ABSENT), b.get(key, _ABSENT)
        if va == vb or (va is None and vb is _ABSENT) or (vb is None and va is _ABSENT):
            continue
        if key == "tasks_sha256":
            out.append("the task list differs")
        else:
            out.append(f"{key}: {_show(va)} in the folder, {_show(vb)} now")
    return out


def _refuse_other_run(root: Path, stored: Mapping[str, Any], wanted: Mapping[str, Any],
                      source: Path) -> RunFolderError:
    study = wanted.get("study")
    if stored.get("study") != study:
        what = (f"{root} holds a run of the study {stored.get('study')!r} (see {source.name}), "
                f"not of {study!r}")
    else:
        diffs = differences(stored, wanted)
        shown = "; ".join(diffs[:8]) + (f"; and {len(diffs) - 8} more" if len(diffs) > 8
                                         else "")
        config = [d for d in diffs if d.startswith(("config", "seed"))]
        kind = ("another config" if config else
                "the same config, but this version of the study declares other tasks")
        what = f"{root} holds a run of {study!r} with {kind} ({shown or source.name})"
    config_toml = root / "config.toml"
    resume = (f"; or continue the stored run with its own config: --config {config_toml}"
              if config_toml.is_file() and stored.get("study") == study else "")
    return RunFolderError(
        f"{what}. A run folder belongs to one run, so that results of two configs are never "
        f"mixed or overwritten: choose another folder with --out, or delete {root} to start "
        f"over{resume}")


# ---------------------------------------------------------------------- the lock
def _holder(fd: int) -> str:
    try:
        return os.pread(fd, 200, 0).decode(errors="replace").strip()
    except OSError:
        return ""


def _acquire(root: Path) -> int:
    path = root / LOCK
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666 & ~current_umask())
    except OSError as exc:
        raise StorageError(path, exc, "the run folder must be writable") from exc
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = _holder(fd)
        os.close(fd)
        raise RunFolderError(
            f"{root} is in use by another run ({holder or 'another process'}): two runs in "
            "one folder would mix their results; wait for that run to end, or choose another "
            "folder with --out") from None
    except OSError as exc:  # a file system without flock
        os.close(fd)
        raise StorageError(path, exc, "cannot lock the run folder") from exc
    with contextlib.suppress(OSError):  # who holds it, for the message above (best effort)
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()} on {socket.gethostname()}\n".encode(), 0)
    return fd


@contextlib.contextmanager
def locked(root: Path | str) -> Iterator[Path]:
    """Hold the folder's lock (re-entrant within this thread); :class:`RunFolderError` at
    once when another process or thread holds it. ``root`` must exist."""
    root = Path(root)
    key = os.path.realpath(root)
    me = threading.get_ident()
    with _GUARD:
        held = _HELD.get(key)
        if held is not None:
            if held[2] != me:
                raise RunFolderError(f"{root} is in use by another run in this process: two "
                                     "runs in one folder would mix their results; choose "
                                     "another folder with --out")
            held[1] += 1
        else:
            _HELD[key] = held = [_acquire(root), 1, me]
    try:
        yield root
    finally:
        with _GUARD:
            held[1] -= 1
            if held[1] == 0:
                del _HELD[key]
                with contextlib.suppress(OSError):
                    fcntl.flock(held[0], fcntl.LOCK_UN)
                os.close(held[0])


# ---------------------------------------------------------------------- claiming a folder
def _foreign(root: Path) -> list[str]:
    """Entries of ``root`` that no run wrote (an empty ``tasks`` folder is a run's)."""
    out = []
    for p in sorted(root.iterdir(), key=lambda p: p.name):
        if p.name in _OURS:
            continue
        if p.name == "tasks" and p.is_dir() and not any(p.iterdir()):
            continue
        out.append(p.name + ("/" if p.is_dir() else ""))
    return out


def _write_marker(root: Path, identity: Mapping[str, Any], adopted: bool) -> dict:
    data = {"written_by": "workbench (workbench.study.folder)", "format": 1,
            "study": identity.get("study"), "identity_sha256": digest(identity),
            "identity": canonical(identity),
            "claimed_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "adopted_from_manifest": adopted,
            "note": "this folder belongs to one study run: workbench refuses to write a run "
                    "with another config into it; delete the folder to reuse its path"}
    atomic_write_json(root / MARKER, data)
    return data


def _marker_ok(data: Any) -> bool:
    return (isinstance(data, dict) and isinstance(data.get("identity_sha256"), str)
            and isinstance(data.get("identity"), dict))


def check_owner(root: Path, identity: Mapping[str, Any]) -> dict:
    """Apply the rules of this module to ``root`` (which exists and whose lock is held):
    the marker of the run (written if the folder is new or an earlier version's run of the
    same config), or :class:`RunFolderError`."""
    advice = (f"delete {root} to start over, or choose another folder with --out")
    marker = root / MARKER
    if marker.exists():
        data = read_json(marker, "run marker", advice)
        if not _marker_ok(data):
            raise RunFolderError(f"{marker} is not a run marker this version can read; "
                                 f"{advice}")
        if data["identity_sha256"] == digest(identity):
            return data
        raise _refuse_other_run(root, data["identity"], identity, marker)
    manifest = root / MANIFEST
    if manifest.exists():
        data = read_json(manifest, "run's manifest", advice)
        if isinstance(data, dict) and {"study", "config", "tasks_sha256"} <= set(data):
            if digest(data) == digest(identity):
                return _write_marker(root, identity, adopted=True)
            raise _refuse_other_run(root, data, identity, manifest)
    foreign = _foreign(root)
    if foreign:
        shown = ", ".join(foreign[:5]) + (f" and {len(foreign) - 5} more" if len(foreign) > 5
                                          else "")
        raise RunFolderError(
            f"{root} holds files that no workbench run wrote ({shown}); a run never writes "
            "over files it did not write: choose a new or empty folder with --out, or move "
            "those files away")
    return _write_marker(root, identity, adopted=False)


@contextlib.contextmanager
def claim(root: Path | str, identity: Mapping[str, Any]) -> Iterator[dict]:
    """Create ``root`` if needed, lock it and check (or write) its marker for the run
    ``identity`` (:func:`workbench.study.store.study_manifest` of the study); yields the
    marker's data. Nothing else is written."""
    root = Path(root)
    if root.exists() and not root.is_dir():
        raise fail("out", str(root), "must be a directory (it is a file)")
    try:
        root.mkdir(mode=0o777, parents=True, exist_ok=True)
    except OSError as exc:
        raise fail("out", str(root), f"cannot create the run directory ({exc})") from exc
    with locked(root):
        yield check_owner(root, identity)

"""One directory per study run.

Layout of ``root``::

    .workbench-run.json    the folder's owner (:mod:`workbench.study.folder`), written first
    manifest.json          study, config, seed, versions, git revision, machine, evaluator and
                           code hash of this invocation (rewritten by each invocation)
    tasks/<id>.npz         one finished task, written atomically: record (with the evaluator
                           and code hash of the process that computed it), table rows, arrays
    tasks/<id>.error.json  a task that raised: its description and traceback (retried on rerun)
    <table>.parquet/.csv   tidy tables, rows in the study's task order (written when complete)
    errors.json            the errors of the last run (absent when there were none)

A task counts as finished only if its ``.npz`` loads and carries the expected id. A write
that fails (disk full, file-size limit, ...) raises :class:`~workbench.study.io.StorageError`
naming the file; no part of the file is left.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import platform
import time
import zipfile
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from workbench.study.folder import MANIFEST, RunFolderError, read_json
from workbench.study.io import atomic_write_bytes, atomic_write_json, manifest, numpy_default
from workbench.study.tasks import Outputs, Study, TaskOutput, columns, describe
from workbench.validation import fail

_RECORD, _TABLE, _ARRAY = "record", "table:", "array:"


@dataclass(frozen=True)
class TaskRecord:
    """A task's outcome as sent back by a worker: ``output`` when it finished, ``error`` (the
    traceback text) when it raised. ``provenance``: evaluator and code hash of the process that
    ran it (:func:`workbench.study.provenance.current`), stored with the task. ``elapsed_s`` and
    ``worker`` are not part of the results."""

    task_id: str
    output: TaskOutput | None = None
    error: str | None = None
    elapsed_s: float = 0.0
    worker: str = ""
    provenance: Mapping[str, str] | None = None

    @property
    def ok(self) -> bool:
        return self.error is None


@dataclass(frozen=True)
class TaskError:
    """A task that raised: its id, description and traceback."""

    task_id: str
    task: Mapping[str, Any]
    traceback: str

    def headline(self) -> str:
        last = self.traceback.strip().splitlines()[-1] if self.traceback.strip() else "?"
        return f"task {self.task_id} {dict(self.task)}: {last}"


@dataclass
class RunStore:
    """Files of one study run under ``root``."""

    root: Path

    def __post_init__(self) -> None:
        self.root = Path(self.root)
        if self.root.exists() and not self.root.is_dir():
            raise fail("out", str(self.root), "must be a directory (it is a file)")
        try:
            (self.root / "tasks").mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise fail("out", str(self.root), f"cannot create the run directory ({exc})") from exc
        if not os.access(self.root, os.W_OK):
            raise fail("out", str(self.root), "must be a writable directory")

    # ------------------------------------------------------------------ manifest
    def write_manifest(self, study: Study, execution: Mapping[str, Any],
                       provenance: Mapping[str, Any] | None = None) -> dict:
        """Provenance of this invocation, written before any task runs: the study's part
        (:func:`study_manifest`), how it executes, the evaluator and code hash of this process,
        versions and machine."""
        data = {**study_manifest(study), "execution": dict(execution),
                "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                **({"provenance": dict(provenance)} if provenance is not None else {}),
                **manifest(), "machine": machine()}
        atomic_write_json(self.root / MANIFEST, data)
        return data

    def manifest(self) -> dict:
        """The manifest; an unreadable or invalid file is an error naming it."""
        data = read_json(self.root / MANIFEST, "run's manifest",
                         f"rerun the study into {self.root} to rewrite it, or delete the folder")
        if not isinstance(data, dict):
            raise RunFolderError(f"{self.root / MANIFEST} is not a run's manifest (a JSON "
                                 "object); rerun the study to rewrite it")
        return data

    # ------------------------------------------------------------------ tasks
    def task_path(self, task_id: str) -> Path:
        return self.root / "tasks" / f"{task_id}.npz"

    def error_path(self, task_id: str) -> Path:
        return self.root / "tasks" / f"{task_id}.error.json"

    def save(self, task: Any, record: TaskRecord) -> None:
        """Write a finished task atomically (one file: record, rows, arrays)."""
        out = record.output
        if out is None:
            raise ValueError(f"task {record.task_id}: only a finished task (a record with an "
                             "output) can be saved; use save_error for one that raised")
        header = {"task_id": record.task_id, "task": describe(task), "meta": dict(out.meta),
                  "tables": {t: list(cols) for t, cols in out.tables.items()},
                  "arrays": list(out.arrays),
                  "provenance": dict(record.provenance) if record.provenance else None}
        entries: dict[str, Any] = {_RECORD: np.array(json.dumps(header, default=numpy_default))}
        for t, cols in out.tables.items():
            for c, v in cols.items():
                entries[f"{_TABLE}{t}:{c}"] = np.asarray(v)
        for name, v in out.arrays.items():
            entries[f"{_ARRAY}{name}"] = np.asarray(v)
        buf = io.BytesIO()
        np.savez_compressed(buf, **entries)
        atomic_write_bytes(self.task_path(record.task_id), buf.getvalue())
        self.error_path(record.task_id).unlink(missing_ok=True)

    def save_error(self, task: Any, record: TaskRecord) -> TaskError:
        err = TaskError(record.task_id, describe(task), record.error or "")
        atomic_write_json(self.error_path(record.task_id),
                          {"task_id": err.task_id, "task": err.task, "traceback": err.traceback,
                           "worker": record.worker})
        return err

    def _load(self, task_id: str, header_only: bool = False) -> dict[str, Any] | None:
        try:
            with np.load(self.task_path(task_id), allow_pickle=False) as data:
                names = [_RECORD] if header_only else data.files
                entries = {name: data[name] for name in names}
            header = json.loads(str(entries[_RECORD]))
        except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile):
            return None
        if header.get("task_id") != task_id:
            return None
        entries[_RECORD] = header
        return entries

    def is_done(self, task_id: str) -> bool:
        """True if the task's file loads and carries its id (a corrupt file does not count)."""
        return self._load(task_id, header_only=True) is not None

    def headers(self, ids: Iterable[str]) -> dict[str, dict[str, Any]]:
        """The stored record (task, meta, tables, provenance) of each finished task in
        ``ids``."""
        out = {}
        for i in ids:
            entries = self._load(i, header_only=True)
            if entries is not None:
                out[i] = entries[_RECORD]
        return out

    def provenance(self, task_id: str) -> dict[str, str] | None:
        """Evaluator and code hash of the process that computed a finished task (None for a
        task stored before they were recorded)."""
        return self._require(task_id)[_RECORD].get("provenance")

    def meta(self, task_id: str) -> dict[str, Any]:
        return self._require(task_id)[_RECORD]["meta"]

    def arrays(self, task_id: str) -> dict[str, np.ndarray]:
        """The arrays a finished task kept (e.g. trajectories)."""
        entries = self._require(task_id)
        return {k[len(_ARRAY):]: v for k, v in entries.items() if k.startswith(_ARRAY)}

    def _require(self, task_id: str) -> dict:
        entries = self._load(task_id)
        if entries is None:
            raise fail("task_id", task_id, f"no finished task with this id in {self.root}")
        return entries

    def errors(self) -> list[TaskError]:
        """The errors recorded by the last run (``errors.json``)."""
        path = self.root / "errors.json"
        if not path.exists():
            return []
        return [TaskError(e["task_id"], e["task"], e["traceback"])
                for e in json.loads(path.read_text())]

    def write_errors(self, errors: list[TaskError]) -> None:
        path = self.root / "errors.json"
        if errors:
            atomic_write_json(path, [{"task_id": e.task_id, "task": e.task,
                                      "traceback": e.traceback} for e in errors])
        else:
            path.unlink(missing_ok=True)

    def outputs(self, task_id: str) -> dict[str, dict[str, np.ndarray]] | None:
        """A finished task's tables (column -> values), None if it is not finished."""
        entries = self._load(task_id)
        if entries is None:
            return None
        return {t: {c: entries[f"{_TABLE}{t}:{c}"] for c in cols}
                for t, cols in entries[_RECORD]["tables"].items()}

    def outputs_of(self, ids: Mapping[Any, str]) -> Outputs:
        """:meth:`outputs` by task, for tasks with these ids (a staged study reads them)."""
        return lambda task: self.outputs(ids[task])

    # ------------------------------------------------------------------ tidy tables
    def build_tables(self, study: Study, tasks: Iterable[Any] | None = None
                     ) -> dict[str, pa.Table]:
        """Concatenate the rows of ``tasks`` (default: every task of the study), in the
        study's task order, task columns first."""
        parts: dict[str, list[pa.Table]] = {}
        chosen = None if tasks is None else set(tasks)
        for task, tid in zip(study.tasks, study.task_ids(), strict=True):
            if chosen is not None and task not in chosen:
                continue
            stored = self.outputs(tid)
            if stored is None:
                raise fail("task_id", tid, f"no finished task with this id in {self.root}")
            for t, data in stored.items():
                n = len(next(iter(data.values()))) if data else 0
                head = {"task_id": np.full(n, tid),
                        **{c: np.full(n, v) for c, v in columns(task).items()}}
                clash = set(head) & set(data)
                if clash:
                    raise fail(f"tables[{t!r}]", sorted(clash),
                               "a task output column has the name of a task column")
                parts.setdefault(t, []).append(pa.table({**head, **data}))
        out = {}
        for t, tables in parts.items():
            try:
                out[t] = pa.concat_tables(tables)
            except pa.ArrowInvalid as exc:
                raise fail(f"tables[{t!r}]", t, f"tasks disagree on its columns ({exc})") from exc
        return out

    def write_tables(self, tables: Mapping[str, pa.Table]) -> list[Path]:
        """``<name>.parquet`` (byte-stable for the same data) and ``<name>.csv`` per table."""
        paths = []
        for name, table in tables.items():
            sink = pa.BufferOutputStream()
            pq.write_table(table, sink, compression="zstd")
            atomic_write_bytes(self.root / f"{name}.parquet", sink.getvalue().to_pybytes())
            buf = io.StringIO()
            table.to_pandas().to_csv(buf, index=False)
            atomic_write_bytes(self.root / f"{name}.csv", buf.getvalue().encode())
            paths.append(self.root / f"{name}.parquet")
        return paths

    def table(self, name: str) -> pd.DataFrame:
        """A tidy table written by a complete run."""
        path = self.root / f"{name}.parquet"
        if not path.exists():
            raise fail("table", name, f"no {path.name} in {self.root} (has the run completed?)")
        return pq.read_table(path).to_pandas()

    def finished(self, ids: Iterable[str]) -> set[str]:
        return {i for i in ids if self.is_done(i)}


def study_manifest(study: Study) -> dict[str, Any]:
    """The part of a run's manifest that the study alone fixes (no time, host or back end):
    equal for two invocations iff they run the same tasks with the same config."""
    ids = study.task_ids()
    return {"study": study.name, "version": study.version, "seed": study.seed,
            "config": study.config, "fingerprint": study.fingerprint, "n_tasks": len(ids),
            "tasks_sha256": tasks_sha256(ids)}


def tasks_sha256(ids: Iterable[str]) -> str:
    """The hash of a run's task ids in their declared order (what the manifest records)."""
    return hashlib.sha256("\n".join(ids).encode()).hexdigest()


def machine() -> dict[str, Any]:
    """Host facts for the manifest: CPU model, core count, architecture."""
    model = None
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"node": platform.node(), "machine": platform.machine(), "cpu_model": model,
            "cpu_count": os.cpu_count()}

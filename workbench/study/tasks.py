"""Declaring a study: frozen task descriptions, a pure task function, and per-task streams.

A task is a frozen dataclass whose fields (str, int, float, bool, or nested frozen dataclasses
of those) say everything that distinguishes it from the other tasks of the study (e.g. method,
seed index, cell). The task function ``run_task(task, ctx) -> TaskOutput`` must be a module-level
callable (or a ``functools.partial`` of one) so that it can be sent to worker processes.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import pickle
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from numbers import Integral
from typing import Any, cast

import numpy as np

from workbench.validation import fail

Outputs = Callable[[Any], Mapping[str, Mapping[str, np.ndarray]] | None]
"""A finished task's tables by task (None while it is not finished): what ``stages`` reads."""

SCALARS = (str, int, float, bool, np.integer, np.floating, np.bool_)


def _fields(task: Any, prefix: str = "") -> dict[str, Any]:
    if not dataclasses.is_dataclass(task) or isinstance(task, type):
        raise fail("task", task, "must be a frozen dataclass instance")
    if not cast(Any, task).__dataclass_params__.frozen:  # not in the DataclassInstance protocol
        raise fail("task", task, f"{type(task).__name__} must be declared frozen=True")
    out: dict[str, Any] = {}
    for f in dataclasses.fields(task):
        value = getattr(task, f.name)
        if dataclasses.is_dataclass(value):
            out.update(_fields(value, f"{prefix}{f.name}."))
        elif isinstance(value, SCALARS):
            out[prefix + f.name] = value.item() if isinstance(value, np.generic) else value
        else:
            raise fail(f"{type(task).__name__}.{prefix}{f.name}", value,
                       "task fields must be str, int, float, bool or frozen dataclasses of those")
    return out


def describe(task: Any) -> dict[str, Any]:
    """The task as a flat, JSON-able mapping ``{"type": ..., field: value}``."""
    return {"type": type(task).__qualname__, **_fields(task)}


def columns(task: Any) -> dict[str, Any]:
    """The task's columns in the tidy tables: ``task.columns()`` if defined, else its flat
    fields with nested names shortened to the last part (a clash is an error)."""
    if hasattr(task, "columns"):
        return dict(task.columns())
    out: dict[str, Any] = {}
    for name, value in _fields(task).items():
        short = name.rsplit(".", 1)[-1]
        if short in out:
            raise fail(f"{type(task).__name__}.{name}", value,
                       f"column name {short!r} is used twice; define columns() on the task")
        out[short] = value
    return out


def _json(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=True)


def _digest(obj: Any) -> str:
    return hashlib.sha256(_json(obj).encode()).hexdigest()


def stream_key(task: Any) -> tuple[int, ...]:
    """The words that, with the study seed, identify a task's random streams:
    ``task.stream_key()`` if defined, else four 32-bit words of a hash of its description."""
    if hasattr(task, "stream_key"):
        key = tuple(task.stream_key())
        if not key or any(isinstance(k, bool) or not isinstance(k, Integral) or k < 0
                          for k in key):
            raise fail(f"{type(task).__name__}.stream_key()", key,
                       "must be a non-empty tuple of integers >= 0")
        return tuple(int(k) for k in key)
    h = _digest(describe(task))
    return tuple(int(h[i:i + 8], 16) for i in range(0, 32, 8))


def seed_sequence(seed: int, key: tuple[int, ...]) -> np.random.SeedSequence:
    """SeedSequence(seed, spawn_key=key): the same as spawning child key[0] of the root, then
    child key[1] of that, and so on, without creating the siblings."""
    return np.random.SeedSequence(seed, spawn_key=tuple(key))


@dataclass(frozen=True)
class TaskContext:
    """What a task gets besides its description: its id, its random stream, the thread budget
    (1 in worker processes: call e.g. ``SamplerLibrary.set_threads(ctx.threads)``)."""

    task_id: str
    seed: int
    key: tuple[int, ...]
    threads: int = 1

    def seed_sequence(self, *sub: int) -> np.random.SeedSequence:
        """The task's SeedSequence, or an independent child stream ``sub``."""
        return seed_sequence(self.seed, self.key + tuple(sub))

    def rng(self, *sub: int) -> np.random.Generator:
        return np.random.default_rng(self.seed_sequence(*sub))


@dataclass(frozen=True)
class TaskOutput:
    """A task's result. ``tables``: {table: {column: 1-D array}} rows of the tidy tables (all
    columns of a table the same length); ``arrays``: named arrays kept per task (trajectories);
    ``meta``: JSON-able diagnostics."""

    tables: Mapping[str, Mapping[str, np.ndarray]] = field(default_factory=dict)
    arrays: Mapping[str, np.ndarray] = field(default_factory=dict)
    meta: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name, cols in self.tables.items():
            lengths = {c: np.asarray(v).shape for c, v in cols.items()}
            if any(len(s) != 1 for s in lengths.values()) or len(set(lengths.values())) > 1:
                raise fail(f"tables[{name!r}]", lengths, "columns must be 1-D of equal length")
        named = [(f"tables[{t!r}][{c!r}]", v) for t, cols in self.tables.items()
                 for c, v in cols.items()] + [(f"arrays[{a!r}]", v) for a, v in self.arrays.items()]
        for name, v in named:
            if np.asarray(v).dtype.kind not in "biufcUS":
                raise fail(name, np.asarray(v).dtype, "must be numbers, booleans or strings "
                           "(object arrays cannot be stored without pickle)")


@dataclass(frozen=True)
class Study:
    """A study: its name, tasks (in dispatch order: put slow tasks first), task function, root
    seed, config (JSON-able, for the manifest) and fingerprint (JSON-able: every input the
    results depend on beyond the task description; it enters each task id, so changing it
    recomputes). ``version``: bump when the meaning of stored results changes.
    ``worker_init``: called once in each worker process before its first task."""

    name: str
    tasks: tuple[Any, ...]
    run_task: Callable[[Any, TaskContext], TaskOutput]
    seed: int
    config: Mapping[str, Any] = field(default_factory=dict)
    fingerprint: Mapping[str, Any] = field(default_factory=dict)
    version: int = 1
    worker_init: Callable[[], None] | None = None
    stages: Callable[[Outputs], Iterable[Any]] | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name.replace("_", "").isalnum():
            raise fail("name", self.name, "must be a non-empty name of letters, digits and _")
        if isinstance(self.seed, bool) or not isinstance(self.seed, Integral) or self.seed < 0:
            raise fail("seed", self.seed, "must be an integer >= 0")
        object.__setattr__(self, "tasks", tuple(self.tasks))
        if not self.tasks:
            raise fail("tasks", self.tasks, "must be a non-empty sequence of task descriptions")
        for obj, name in ((self.run_task, "run_task"), (self.worker_init, "worker_init")):
            if obj is None:
                continue
            if not callable(obj):
                raise fail(name, obj, "must be callable")
            try:
                pickle.dumps(obj)
            except Exception as exc:
                raise fail(name, obj, "must be picklable (a module-level function or a "
                           "functools.partial of one)") from exc
        for name in ("fingerprint", "config"):
            try:
                json.dumps(getattr(self, name), sort_keys=True)
            except (TypeError, ValueError) as exc:
                raise fail(name, getattr(self, name), "must be JSON-serialisable") from exc
        # the id's JSON up to the task (keys sorted: fingerprint, seed, study, task, version),
        # written once; every task's id is then hashed once (a large study's fingerprint was
        # serialised again for each of its tasks, at every call)
        object.__setattr__(self, "_id_head", ('{"fingerprint":' + _json(self.fingerprint)
                                              + ',"seed":' + _json(self.seed) + ',"study":'
                                              + _json(self.name) + ',"task":').encode())
        object.__setattr__(self, "_ids", tuple(self.task_id(t) for t in self.tasks))
        ids = self.task_ids()
        if len(set(ids)) != len(ids):
            seen: set[str] = set()
            dup = next(t for t, i in zip(self.tasks, ids, strict=True)
                       if i in seen or seen.add(i))
            raise fail("tasks", dup, "declared twice; each task must be unique")

    def task_id(self, task: Any) -> str:
        """16 hex digits naming a task's result: study, version, seed, fingerprint, task."""
        h = hashlib.sha256(self._id_head)  # type: ignore[attr-defined]
        h.update(f'{_json(describe(task))},"version":{_json(self.version)}}}'.encode())
        return h.hexdigest()[:16]

    def task_ids(self) -> list[str]:
        """Every task's id, in the order of ``tasks`` (computed once)."""
        return list(self._ids)  # type: ignore[attr-defined]

    def stage(self, outputs: Outputs) -> list[Any]:
        """The tasks to have finished now, in dispatch order: every task without ``stages``;
        with it, ``stages(outputs)``, where ``outputs(task)`` is a finished task's tables
        (None while it is not finished). A staged study (e.g. a group-sequential one that
        adds rounds only while a comparison is undecided) is run until ``stages`` asks for
        no unfinished task; it must depend only on the outputs, so a rerun asks for the
        same tasks. Tasks it names must be among ``tasks`` (the run's identity)."""
        if self.stages is None:
            return list(self.tasks)
        wanted = set(self.stages(outputs))
        unknown = wanted - set(self.tasks)
        if unknown:
            raise fail("stages", next(iter(unknown)), "names a task that the study does not "
                       "declare; stages must choose among its tasks")
        return [t for t in self.tasks if t in wanted]

    def context(self, task: Any, threads: int = 1) -> TaskContext:
        return TaskContext(self.task_id(task), self.seed, stream_key(task), threads)

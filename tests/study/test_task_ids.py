"""A task's id is the hash of one JSON document (study, version, seed, fingerprint, task):
the id written from a prefix serialised once equals that document's hash, for tasks and
fingerprints of every JSON kind."""

from __future__ import annotations

import hashlib
import json
import pickle
from dataclasses import dataclass

import numpy as np

from workbench.study.tasks import Study, describe


@dataclass(frozen=True)
class Inner:
    flag: bool
    z: float


@dataclass(frozen=True)
class T:
    i: int
    name: str
    x: float
    nested: Inner


def _run(task, ctx):  # never called
    raise AssertionError


def _oracle(d: Study, task) -> str:
    doc = {"study": d.name, "version": d.version, "seed": d.seed, "fingerprint": d.fingerprint,
           "task": describe(task)}
    text = json.dumps(doc, sort_keys=True, separators=(",", ":"), allow_nan=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def test_ids_equal_the_hash_of_the_whole_document():
    rng = np.random.default_rng(7)
    tasks = [T(int(i), f"n{i}é\"", float(rng.normal()) if i % 5 else float("nan"),
               Inner(i % 2 == 0, 1.5 * i)) for i in range(40)]
    fps = [{}, {"b": [1, 2.5, "x"], "a": {"y": None, "x": float("inf")}, "ü": 3}]
    for fp in fps:
        d = Study("my_study", tuple(tasks), _run, seed=12, fingerprint=fp, version=3)
        want = [_oracle(d, t) for t in tasks]
        assert d.task_ids() == want and [d.task_id(t) for t in tasks] == want
        again = pickle.loads(pickle.dumps(d))
        assert again.task_ids() == want and again.task_id(tasks[3]) == want[3]
    # a changed field changes every id (a broken prefix that dropped the fingerprint would not)
    a = Study("s", tuple(tasks), _run, seed=1, fingerprint={"k": 1})
    b = Study("s", tuple(tasks), _run, seed=1, fingerprint={"k": 2})
    assert not set(a.task_ids()) & set(b.task_ids())

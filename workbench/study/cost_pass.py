"""The cost pass: every method's CPU time per control step, measured alone, so that the order
of methods by cost does not depend on how the study's episodes were run.

The episodes of a study run beside each other (``--workers``) and their CPU times move with the
neighbours (a shared cache, a slower clock: the same method's mean moved by up to 1.4x between
runs with 0, 1 and 2 workers). The cost pass runs once per run, in the coordinating process after
every task has finished. Each method replays the same short episode (its ``run``: a generator
that does one control step per ``next``) in ``rounds`` rounds after one warm-up round that is
not recorded. Within a round the methods advance in lock step: step k of every method, in a
random order, then step k + 1, so that two methods' steps are never more than one step of each
method apart and whatever the machine does meets them alike. Methods are compared by round: the
log-ratio of two methods' mean CPU time per step in the same round.

:func:`run_pass` measures and stores ``cost_pass.parquet`` / ``.csv`` (one row per method, round
and step: ``wall_ms``, ``cpu_ms``) with ``cost_pass.json`` (what was replayed, the rounds, the
thread count, the load average, the run's task hash); :func:`load_pass` reads them back (a report
rebuilt from stored results measures nothing); :func:`pass_costs` gives each method's CPU ms per
step with its 95 % interval and its wall-clock tail; :func:`pass_order` the order with ties.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa

from workbench.study.io import atomic_write_json
from workbench.study.latency import Latency
from workbench.study.stats import t_interval
from workbench.study.store import RunStore, tasks_sha256
from workbench.validation import fail, integer

FILE = "cost_pass"

Run = Callable[[], Iterator[object]]
"""A method's episode: a new generator per call that does one control step per ``next`` (the
same steps every call)."""


@dataclass(frozen=True)
class CostPlan:
    """What a study's cost pass replays: ``runs`` (method -> a :data:`Run`, the same episode
    every call), ``rounds`` recorded rounds (>= 2: intervals come from the spread over rounds),
    ``seed`` (the rounds' random orders), ``what`` (the episode and the core count in words,
    for the report) and ``setting`` (a context entered around the whole pass, e.g. one that
    fixes the kernels' thread count)."""

    runs: Mapping[str, Run]
    rounds: int
    seed: int
    what: str
    setting: Callable[[], AbstractContextManager] = nullcontext

    def __post_init__(self) -> None:
        if not self.runs:
            raise fail("CostPlan.runs", {}, "need at least one method")
        integer("CostPlan.rounds", self.rounds, 2)
        integer("CostPlan.seed", self.seed, 0)


@dataclass(frozen=True)
class PassCost:
    """One method's cost in the pass: CPU ms per step (mean of its rounds' means) with the 95 %
    t-interval over rounds, and the wall-clock tail over every recorded step."""

    method: str
    cpu_ms: float
    cpu_low: float
    cpu_high: float
    wall: Latency
    rounds: int


@dataclass(frozen=True)
class CostPass:
    """A stored pass: the per-step table and what was measured."""

    table: pd.DataFrame
    meta: dict

    def costs(self) -> dict[str, PassCost]:
        return pass_costs(self.table)

    def order(self) -> tuple[tuple[str, ...], ...]:
        return pass_order(self.table)


def run_pass(plan: CostPlan, out: Path, tasks_sha256: str) -> CostPass:
    """Measure ``plan`` (a warm-up round, then ``plan.rounds`` rounds in random orders from
    ``plan.seed``, all inside ``plan.setting()``) and store it in ``out``."""
    rng = np.random.default_rng(plan.seed)
    names = list(plan.runs)
    rows: list[pd.DataFrame] = []
    load0, t0 = os.getloadavg()[0], time.perf_counter()
    with plan.setting():
        _lock_step(plan, names, rng)  # warm-up: first calls, page faults, lazy set-up
        for r in range(plan.rounds):
            times = _lock_step(plan, names, rng)
            rows += [pd.DataFrame({"method": name, "round": r,
                                   "step": np.arange(len(times[name])),
                                   "wall_ms": [1e3 * w for w, _ in times[name]],
                                   "cpu_ms": [1e3 * c for _, c in times[name]]})
                     for name in names]
    table = pd.concat(rows, ignore_index=True)
    meta = {"what": plan.what, "rounds": plan.rounds,
            "methods": names, "seed": plan.seed, "wall_time_s": time.perf_counter() - t0,
            "load_average_1min": [load0, os.getloadavg()[0]], "tasks_sha256": tasks_sha256}
    RunStore(out).write_tables({FILE: pa.Table.from_pandas(table, preserve_index=False)})
    atomic_write_json(out / f"{FILE}.json", meta)
    return CostPass(table, meta)


def _lock_step(plan: CostPlan, names: list[str],
               rng: np.random.Generator) -> dict[str, list[tuple[float, float]]]:
    """One round: every method's episode anew, advanced one step at a time in a random order
    per step until all have ended; the (wall, CPU) seconds of each step by method."""
    live = {name: iter(plan.runs[name]()) for name in names}
    times: dict[str, list[tuple[float, float]]] = {name: [] for name in names}
    while live:
        for k in rng.permutation(len(names)):
            name = names[k]
            if name not in live:
                continue
            c, t = time.process_time(), time.perf_counter()
            try:
                next(live[name])
            except StopIteration:
                del live[name]
                continue
            times[name].append((time.perf_counter() - t, time.process_time() - c))
    return times


def load_pass(out: Path, tasks_sha256: str | None = None) -> CostPass | None:
    """The pass stored in ``out`` (None when there is none, or when it was measured for other
    tasks than ``tasks_sha256``)."""
    try:
        meta = json.loads((out / f"{FILE}.json").read_text())
        table = RunStore(out).table(FILE)
    except (OSError, ValueError):
        return None
    if tasks_sha256 is not None and meta.get("tasks_sha256") != tasks_sha256:
        return None
    return CostPass(table, meta)


def stored_pass(finished) -> CostPass | None:
    """The cost pass of a finished run (a :class:`~workbench.study.spec.Finished`), None when it
    has none (a study without one, or a run stored before it measured one)."""
    return load_pass(finished.out, tasks_sha256(finished.ids.values()))


def _round_means(table: pd.DataFrame) -> pd.DataFrame:
    """CPU ms per step by method (rows) and round (columns)."""
    return table.groupby(["method", "round"])["cpu_ms"].mean().unstack("round")


def pass_costs(table: pd.DataFrame) -> dict[str, PassCost]:
    """Per method, cheapest first: CPU ms per step and its 95 % interval over rounds, and the
    wall-clock p50 / p95 / p99 / max over every recorded step."""
    means = _round_means(table)
    out = {}
    for name in means.mean(axis=1).sort_values().index:
        m, lo, hi = t_interval(means.loc[name].dropna().to_numpy(float))
        wall = table.loc[table["method"] == name, "wall_ms"]
        out[str(name)] = PassCost(str(name), m, lo, hi, Latency.of(wall, f"{name} wall_ms"),
                                  int(means.loc[name].notna().sum()))
    return out


# costs closer than this (relative) are never ordered: between three passes of the
# sampling-safety quick profile on a 2-core VM, one pair's cost ratio read 1.00, 0.96 and 1.00
RESOLUTION = 0.03


def separated(table: pd.DataFrame, a: str, b: str, resolution: float = RESOLUTION) -> bool:
    """Whether the pass shows ``a`` and ``b`` apart by more than ``resolution``: the 95 %
    t-interval of the mean per-round log-ratio of their CPU times (rounds pair the two) lies
    wholly beyond ``log(1 + resolution)`` on one side of 0."""
    means = _round_means(table)
    return apart(np.log(means.loc[a].to_numpy(float)) - np.log(means.loc[b].to_numpy(float)),
                 resolution)


def apart(log_ratios: np.ndarray, resolution: float = RESOLUTION) -> bool:
    """:func:`separated` on the per-round log-ratios (non-finite ones left out)."""
    d = np.asarray(log_ratios, dtype=float)
    d = d[np.isfinite(d)]
    if d.size < 2:
        return False
    _, lo, hi = t_interval(d)
    edge = math.log1p(resolution)
    return bool(lo > edge or hi < -edge)


def pass_order(table: pd.DataFrame) -> tuple[tuple[str, ...], ...]:
    """Methods by CPU time per step in the pass, cheapest first, in tie groups: a method joins
    the group before it when the paired comparison by rounds (:func:`separated`, at
    :data:`RESOLUTION`) does not separate it from some member of that group."""
    logs = np.log(_round_means(table))  # once: each pair below is a difference of two rows
    groups: list[list[str]] = []
    for name in pass_costs(table):
        if groups and any(not apart((logs.loc[name] - logs.loc[g]).to_numpy(float))
                          for g in groups[-1]):
            groups[-1].append(name)
        else:
            groups.append([name])
    return tuple(tuple(g) for g in groups)


def order_text(order: tuple[tuple[str, ...], ...],
               label: Callable[[str], str] | Mapping[str, str] = str) -> str:
    """``a < {b, c} < d``: an order with its ties, in words."""
    def name(m: str) -> str:
        return str(label.get(m, m)) if isinstance(label, Mapping) else str(label(m))

    def one(g: tuple[str, ...]) -> str:
        names = [name(m) for m in g]
        return names[0] if len(names) == 1 else "{" + ", ".join(names) + "}"

    return " < ".join(one(g) for g in order)

"""Step times of a controller, measured so that methods can be compared.

Two clocks per control step (:func:`workbench.sim.closed_loop` records both):

* **wall time** (``time.perf_counter``): what a robot waits for. It grows when other processes
  share the cores.
* **CPU time** (``time.process_time``, the process's time over all its threads, the kernels'
  OpenMP team included): the compute work of the step. Work done on other cores counts once per
  core, so a step on two threads reports the sum of both; what the neighbours do does not count.
  The studies' cost column is the mean CPU time per step.

:class:`Latency` holds the tail (median, 95th and 99th percentile, maximum) of one clock;
:func:`latency_table` the study reports' table of it per method; :func:`cost_order` orders
methods by mean CPU time with ties where the 95 % intervals of the means overlap.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from workbench.study.report import md_table
from workbench.study.stats import t_interval
from workbench.validation import fail

PERCENTILES = (50.0, 95.0, 99.0)


def _times(name: str, values) -> np.ndarray:
    v = np.asarray(values, dtype=float).ravel()
    if v.size == 0:
        raise fail(name, [], "need at least one step time")
    if not np.all(np.isfinite(v)) or np.any(v < 0):
        raise fail(name, v[~np.isfinite(v) | (v < 0)][:3], "step times must be finite and >= 0")
    return v


@dataclass(frozen=True)
class Latency:
    """Mean, median, 95th and 99th percentile and maximum of ``n`` step times [ms] (percentiles
    by linear interpolation between order statistics, numpy's default)."""

    n: int
    mean_ms: float
    p50_ms: float
    p95_ms: float
    p99_ms: float
    max_ms: float

    @classmethod
    def of(cls, ms, name: str = "step times") -> Latency:
        v = _times(name, ms)
        p50, p95, p99 = (float(q) for q in np.percentile(v, PERCENTILES))
        return cls(int(v.size), float(v.mean()), p50, p95, p99, float(v.max()))

    def row(self, digits: int = 2) -> list[str]:
        """p50, p95, p99 and max as table cells."""
        return [f"{x:.{digits}f}" for x in (self.p50_ms, self.p95_ms, self.p99_ms, self.max_ms)]


def step_table(wall_s, cpu_s) -> dict[str, np.ndarray]:
    """A task's per-step timing rows: ``step``, ``wall_ms``, ``cpu_ms``."""
    w, c = _times("wall_s", wall_s), _times("cpu_s", cpu_s)
    if w.shape != c.shape:
        raise fail("cpu_s", c, f"need one CPU time per step ({c.size} given for {w.size} "
                   "steps)")
    return {"step": np.arange(w.size), "wall_ms": 1e3 * w, "cpu_ms": 1e3 * c}


def mean_interval(values) -> tuple[float, float, float]:
    """Mean and 95 % t-interval of the mean (a single value: the value, nan interval)."""
    return t_interval(_times("values", values))


def cost_order(cpu_ms: Mapping[str, Sequence[float] | np.ndarray]) -> tuple[tuple[str, ...], ...]:
    """Methods by mean CPU time per step, cheapest first, in tie groups: sorted by mean, a
    method joins the group before it when its 95 % interval of the mean overlaps the interval
    of any method in that group (no interval: tied only on an equal mean)."""
    rows = sorted(((mean_interval(v), k) for k, v in cpu_ms.items()), key=lambda r: r[0][0])
    groups: list[list[str]] = []
    top = -math.inf  # the highest upper end in the current group
    for (m, lo, hi), name in rows:
        lo = m if math.isnan(lo) else lo
        hi = m if math.isnan(hi) else hi
        if groups and lo <= top:
            groups[-1].append(name)
            top = max(top, hi)
        else:
            groups.append([name])
            top = hi
    return tuple(tuple(g) for g in groups)


def orders_agree(*orders: tuple[tuple[str, ...], ...]) -> bool:
    """Whether no two tie-grouped orders (:func:`cost_order`) put one method strictly before
    another in one and strictly after it in another."""
    ranks = [{name: i for i, group in enumerate(o) for name in group} for o in orders]
    names = set().union(*ranks)
    for a in names:
        for b in names:
            before = [r[a] < r[b] for r in ranks if a in r and b in r]
            after = [r[a] > r[b] for r in ranks if a in r and b in r]
            if any(before) and any(after):
                return False
    return True


def latency_table(times: Mapping[str, tuple[Sequence[float] | np.ndarray, Sequence[float]
                                             | np.ndarray]]) -> list[list[str]]:
    """Rows of the reports' latency table: per method (``name -> (wall_ms, cpu_ms)`` over all
    its steps), the CPU mean and the wall-clock p50 / p95 / p99 / max, and the steps counted."""
    out = []
    for name, (wall, cpu) in times.items():
        w, c = Latency.of(wall, f"{name} wall_ms"), Latency.of(cpu, f"{name} cpu_ms")
        out.append([name, f"{c.mean_ms:.2f}", f"{w.mean_ms:.2f}", *w.row(), str(w.n)])
    return out


LATENCY_HEADER = ["method", "CPU ms/step (mean)", "wall ms (mean)", "wall p50", "wall p95",
                  "wall p99", "wall max", "steps"]
LATENCY_NOTE = ("CPU ms/step: process CPU time of a control step (all its threads; independent "
                "of other processes). Wall p50 / p95 / p99 / max: percentiles of the wall-clock "
                "step time over every step of every episode (they grow with the load; the first "
                "step of an episode is included).")


def tail_lines(steps, by: Sequence[str], label=None) -> list[str]:
    """The report section on step cost and tail from a ``step_times`` table (columns ``by``,
    ``wall_ms``, ``cpu_ms``): one row per group of ``by`` (``label(key)`` names it, default the
    values joined), every step of every episode pooled; empty when the table has no rows."""
    if steps is None or not len(steps):
        return []
    times = {}
    for key, g in steps.groupby(list(by), sort=False):
        key = key if isinstance(key, tuple) else (key,)
        name = label(key) if label else ", ".join(str(k) for k in key)
        times[name] = (g["wall_ms"].to_numpy(), g["cpu_ms"].to_numpy())
    return ["## What a step costs: CPU time and the wall-clock tail", "",
            *md_table(LATENCY_HEADER, latency_table(times)), "", LATENCY_NOTE, ""]

"""Typed summary of a sampling-safety run, from the tidy tables ``episodes``, ``timing`` and
``activity``.

Metrics, each defined once here: safety = share of episodes without a crash (Wilson 95 %
interval); collision-free sample fraction = per control step, the share of the samples the
update was weighted over whose rollout never crashed (for the robust controllers: the real
samples, with feedback), averaged over the episode's steps, then over realisations (95 %
t-interval over realisations); ESS likewise; final error = distance to the goal at the end,
over safe episodes; cost = CPU time per control step in the run's cost pass (no episode running,
kernels on one thread, methods in lock step: :mod:`workbench.study.cost_pass`), beside each cell's
mean process CPU time per step in the episodes and the wall-clock step time's mean, p50, p95,
p99 and maximum over every step of the cell (:mod:`workbench.study.latency`). Paired comparisons use
the same realisations (common random numbers): McNemar's exact test on safety, a paired
t-interval on the collision-free fraction. Mechanism health
(:func:`~workbench.scenarios.mechanism_health.study_health`): per variance, whether each
mechanism never acted or acted on every step, and whether a method was less safe than the one
it wraps.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, is_dataclass

import numpy as np
import pandas as pd
from scipy import stats

from studies.navigation.paired import Paired
from studies.sampling_safety.config import StudyConfig
from workbench.scenarios.maps import generate
from workbench.scenarios.mechanism_health import StudyHealth, study_health
from workbench.scenarios.model_system import resolve_system
from workbench.study import Rate, RunStore, Spread
from workbench.study.cost_pass import CostPass, PassCost
from workbench.study.latency import Latency


def mean_interval(values, lo: float = -math.inf,
                  hi: float = math.inf) -> tuple[float, float, float]:
    """Mean and 95 % t-interval of a sample (nan interval for fewer than 2 values), the
    interval cut to the quantity's range [lo, hi] (a fraction cannot leave [0, 1])."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return math.nan, math.nan, math.nan
    m = float(v.mean())
    if v.size < 2:
        return m, math.nan, math.nan
    half = float(stats.t.ppf(0.975, v.size - 1) * v.std(ddof=1) / math.sqrt(v.size))
    return m, max(m - half, lo), min(m + half, hi)


@dataclass(frozen=True)
class Cell:
    """One (controller, variance) cell over its realisations."""

    controller: str
    variance: float
    n: int
    safety: float
    ci_low: float
    ci_high: float
    safe: Rate
    reached: Rate  # within the goal radius at some step, over all realisations
    final_error: Spread  # over safe realisations
    final_error_low: float
    final_error_high: float
    collision_free_sample_fraction: float
    cf_low: float
    cf_high: float
    ess_mean: float
    ess_low: float
    ess_high: float
    mean_step_ms: float  # wall clock
    median_step_ms: float
    activity: dict[str, float]  # mechanism -> mean activity over steps and realisations
    cpu_ms: float  # the cost: mean process CPU time per step
    wall: Latency  # wall-clock step times over every step of every realisation
    cpu: Latency

    @classmethod
    def of(cls, controller: str, variance: float, rows: pd.DataFrame, timing: pd.DataFrame,
           activity: pd.DataFrame, steps: pd.DataFrame) -> Cell:
        safe_mask = ~rows["crashed"].to_numpy(bool)
        safe = Rate.of(safe_mask)
        err = rows["final_error"].to_numpy(float)[safe_mask]
        fe = mean_interval(err, 0.0)
        cf = mean_interval(rows["collision_free_fraction"], 0.0, 1.0)
        ess = mean_interval(rows["ess_mean"], 1.0)
        act = {k: float(g["activity"].mean()) for k, g in activity.groupby("mechanism")}
        return cls(controller, float(variance), safe.n, safe.value, safe.low, safe.high, safe,
                   Rate.of(rows["reached"].to_numpy(bool)), Spread.of(err), fe[1], fe[2],
                   *cf, *ess, float(timing["mean_step_ms"].mean()),
                   float(timing["median_step_ms"].median()), act,
                   float(steps["cpu_ms"].mean()), Latency.of(steps["wall_ms"], "wall_ms"),
                   Latency.of(steps["cpu_ms"], "cpu_ms"))


@dataclass(frozen=True)
class PairedFraction:
    """Collision-free sample fraction of ``first`` minus ``second`` on the same realisations:
    mean paired difference and its 95 % t-interval."""

    first: str
    second: str
    variance: float
    n: int
    difference: float
    low: float
    high: float


REFERENCES = ("bas_mppi", "sa_rmppi")  # every controller is paired with these


@dataclass(frozen=True)
class SamplingSafetySummary:
    config: dict
    dt: float  # the control period [s]
    cells: tuple[Cell, ...]
    paired: tuple[Paired, ...]
    paired_fraction: tuple[PairedFraction, ...]
    health: StudyHealth  # mechanism checks per variance, paired by realisation
    # the cost pass (no episode running, workbench.study.cost_pass): cheapest first; empty for
    # a run stored without one
    cost: tuple[PassCost, ...] = ()
    cost_order: tuple[tuple[str, ...], ...] = ()
    cost_what: str = ""

    def cost_ms(self, controller: str) -> float:
        """The controller's cost: CPU ms per step in the cost pass, or, for a run without one,
        the mean over its cells of the episodes' mean CPU ms per step."""
        hit = next((c for c in self.cost if c.method == controller), None)
        if hit is not None:
            return hit.cpu_ms
        ms = [c.cpu_ms for c in self.cells if c.controller == controller]
        return sum(ms) / len(ms) if ms else math.nan

    @property
    def cost_source(self) -> str:
        return ("the cost pass (no episode running, kernels on one thread)" if self.cost
                else "the episodes' mean CPU time (this run has no cost pass)")

    def cell(self, controller: str, variance: float) -> Cell | None:
        return next((c for c in self.cells
                     if (c.controller, c.variance) == (controller, variance)), None)

    def pair(self, first: str, second: str, variance: float) -> Paired | None:
        return next((p for p in self.paired
                     if (p.first, p.second, p.variance) == (first, second, variance)), None)

    def pair_fraction(self, first: str, second: str, variance: float) -> PairedFraction | None:
        return next((p for p in self.paired_fraction
                     if (p.first, p.second, p.variance) == (first, second, variance)), None)


def summarise(config, store: RunStore, cost: CostPass | None = None) -> SamplingSafetySummary:
    ep, timing, act = store.table("episodes"), store.table("timing"), store.table("activity")
    per_step = store.table("step_times")
    cells = []
    for (c, v), rows in ep.groupby(["controller", "variance"], sort=False):
        tids = set(rows["task_id"])
        cells.append(Cell.of(c, v, rows, timing[timing["task_id"].isin(tids)],
                             act[act["task_id"].isin(tids)],
                             per_step[per_step["task_id"].isin(tids)]))
    paired, fractions = [], []
    for v in config.variances:
        at = ep[ep["variance"] == v]
        for ref in REFERENCES:
            ry = at[at["controller"] == ref]
            if not len(ry):
                continue
            for c in config.controllers:
                rx = at[at["controller"] == c]
                if c == ref or not len(rx):
                    continue
                paired.append(Paired.of(c, ref, v, rx[["realisation", "crashed"]],
                                        ry[["realisation", "crashed"]]))
                m = rx.merge(ry, on="realisation", suffixes=("_1", "_2"))
                d = (m["collision_free_fraction_1"] - m["collision_free_fraction_2"]).to_numpy()
                fractions.append(PairedFraction(c, ref, float(v), int(d.size),
                                                *mean_interval(d, -1.0, 1.0)))
    return SamplingSafetySummary(ran_settings(config), ran_dt(config), tuple(cells),
                                 tuple(paired), tuple(fractions),
                                 study_health(ep, act, cell=("variance",)),
                                 tuple(cost.costs().values()) if cost else (),
                                 cost.order() if cost else (),
                                 str(cost.meta.get("what", "")) if cost else "")


def ran_settings(config: StudyConfig) -> dict:
    """The config as it ran: every value left to the system replaced by the system's, with
    the system's label and where each of its defaults came from."""
    r = config.resolved()
    d = config.as_dict()
    d.update({k: asdict(v) if is_dataclass(v) else v
              for k, v in ((f, getattr(r, f)) for f in ("scene", "sampler", "q_beta",
                                                         "feedback", "goal_radius"))})
    sysm = resolve_system(r.entry)
    d.update(system_name=sysm.name, system_label=sysm.label, model_scene=sysm.scene is not None,
             origins=[list(o) for o in sysm.origins], disturbed=list(sysm.disturbed),
             level_scale=sysm.level_scale)
    return d


def ran_dt(config: StudyConfig) -> float:
    r = config.resolved()
    if r.family is not None:
        return float(generate(r.family, r.map_seed).scene().dt)
    return float(r.scene.scene().dt if r.scene is not None
                 else resolve_system(r.entry).scene.dt)

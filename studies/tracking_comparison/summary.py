"""Typed summary of a run, built from the tidy table ``rollouts`` (one row per rollout).

Metrics, each defined once here: unsafe = min over steps k = 0..N of h(x_k) < 0 (left the safe
set at any step); reached(r) = final distance to the target <= r; failure(r) = unsafe or not
reached(r).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from studies.tracking_comparison.config import StudyConfig
from studies.tracking_comparison.tasks import Plan
from workbench.study import Rate, RunStore, Spread


def unsafe(rows: pd.DataFrame) -> np.ndarray:
    return rows["min_h"].to_numpy() < 0


def reached(rows: pd.DataFrame, radius: float) -> np.ndarray:
    return rows["final_distance"].to_numpy() <= radius


def failure(rows: pd.DataFrame, radius: float) -> np.ndarray:
    return unsafe(rows) | ~reached(rows, radius)


@dataclass(frozen=True)
class SeedOutcome:
    seed_index: int
    n: int
    unsafe: float
    failure: float


@dataclass(frozen=True)
class Outcome:
    """One method's rollouts at one point: both rates with Wilson intervals, and diagnostics."""

    method: str
    n: int
    unsafe: Rate
    failure: Rate
    not_reached: Rate
    n_unsafe_and_not_reached: int
    n_grazing: int  # 0 <= min h < 1e-6
    final_distance: Spread
    min_h: Spread
    min_h_p05: float
    infeasible_qp_steps: int
    rollouts_with_infeasible_qp: int
    unsafe_with_infeasible_qp: int
    fallback_steps: int
    qp_steps: int
    per_seed: tuple[SeedOutcome, ...]
    per_seed_unsafe: Spread
    per_seed_failure: Spread

    @classmethod
    def of(cls, method: str, rows: pd.DataFrame, radius: float) -> Outcome:
        u, f, r = unsafe(rows), failure(rows, radius), reached(rows, radius)
        min_h, infeasible = rows["min_h"].to_numpy(), rows["infeasible_qp_steps"].to_numpy()
        seeds = tuple(SeedOutcome(int(s), len(g), float(unsafe(g).mean()),
                                  float(failure(g, radius).mean()))
                      for s, g in rows.groupby("seed_index"))
        return cls(method, len(rows), Rate.of(u), Rate.of(f), Rate.of(~r),
                   int((u & ~r).sum()), int(((min_h >= 0) & (min_h < 1e-6)).sum()),
                   Spread.of(rows["final_distance"]), Spread.of(min_h),
                   float(np.quantile(min_h, 0.05)), int(infeasible.sum()),
                   int((infeasible > 0).sum()), int((u & (infeasible > 0)).sum()),
                   int(rows["fallback_steps"].sum()), int(rows["qp_steps"].sum()), seeds,
                   Spread.of([s.unsafe for s in seeds]), Spread.of([s.failure for s in seeds]))


@dataclass(frozen=True)
class SweepPoint:
    parameter: str
    value: float | str
    outcomes: tuple[Outcome, ...]

    def get(self, method: str) -> Outcome | None:
        return next((o for o in self.outcomes if o.method == method), None)


@dataclass(frozen=True)
class RadiusPoint:
    """Failure at success radius ``radius`` ("main": the main rollouts; "ecbf_noise_after": the
    sweep's ECBF rollouts with the noise after the filter)."""

    source: str
    method: str
    radius: float
    failure: Rate


@dataclass(frozen=True)
class NominalOutcome:
    method: str
    info: dict
    path_task: str  # task id of the stored noise-free path


@dataclass(frozen=True)
class TrackingSummary:
    config: dict
    methods: tuple[Outcome, ...]
    nominal: tuple[NominalOutcome, ...]
    sweep: tuple[SweepPoint, ...]
    radius: tuple[RadiusPoint, ...]
    mc_paths: dict[str, str]  # method -> task id of the seed-0 main batch (stored paths)

    def method(self, name: str) -> Outcome | None:
        return next((o for o in self.methods if o.method == name), None)

    def point(self, parameter: str, value) -> SweepPoint | None:
        return next((p for p in self.sweep if p.parameter == parameter and p.value == value),
                    None)


def _rows(table: pd.DataFrame, tasks, ids: dict) -> pd.DataFrame:
    return table[table["task_id"].isin([ids[t] for t in tasks])]


def summarise(config: StudyConfig, plan: Plan, store: RunStore, ids: dict) -> TrackingSummary:
    """The summary of a complete run; ``ids`` maps each task to its id."""
    table = store.table("rollouts")
    r0 = config.target_radius
    methods = tuple(Outcome.of(m, _rows(table, ts, ids), r0) for m, ts in plan.main.items())
    sweep = tuple(SweepPoint(name, value, tuple(Outcome.of(m, _rows(table, ts, ids), r0)
                                                for m, ts in per.items()))
                  for name, value, per in plan.sweep)
    radius = [RadiusPoint("main", m, r, Rate.of(failure(_rows(table, ts, ids), r)))
              for m, ts in plan.main.items() for r in config.radii]
    after = next((per for name, v, per in plan.sweep if (name, v) == ("ecbf_noise", "after")),
                 None)
    if after and "ecbf" in after:
        rows = _rows(table, after["ecbf"], ids)
        radius += [RadiusPoint("ecbf_noise_after", "ecbf", r, Rate.of(failure(rows, r)))
                   for r in config.radii]
    nominal = tuple(NominalOutcome(m, {k: v for k, v in store.meta(ids[t]).items()
                                       if k != "solve_time_s"}, ids[t])  # timing: not a result
                    for m, t in plan.nominal.items())
    return TrackingSummary(config.as_dict(), methods, nominal, sweep, tuple(radius),
                           {m: ids[ts[0]] for m, ts in plan.main.items()})

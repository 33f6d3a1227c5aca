"""Typed summary of a run, from the tidy tables ``episodes`` and ``timing``.

Metrics, each defined once here: safe = no crash in the episode; RMSE (assumptions §12.2) =
sqrt(mean over SAFE realisations of the squared final distance to the goal); rmse_all = the same
over all realisations (a crashed run's final position is its crash point); rmse_time =
sqrt(mean over safe realisations of the time-averaged squared distance); rmse_reached = over
safe realisations that ended within the goal radius; reached = final distance
<= goal radius (over safe realisations); fractions of control steps are pooled over the cell.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pandas as pd

from studies.navigation.paired import Paired
from studies.navigation.wording import NAMES
from workbench.sampling.feedback import FALLBACK_REASONS
from workbench.study import Rate, RunStore, Spread, fmt_rate, to_jsonable
from workbench.study.io import atomic_write_json
from workbench.study.spec import Summary

GATES = (0, 1)  # the generated map's first two circles form the central vertical passage
EARLY = 1 / 3  # a crash with less than this fraction of the start-goal distance covered


def _rmse(sq: np.ndarray) -> float:
    return float(math.sqrt(np.mean(sq))) if sq.size else math.nan


@dataclass(frozen=True)
class Cell:
    """One (controller, alpha rule, variance) cell over its realisations."""

    controller: str
    rule: str
    variance: float
    main: bool
    n: int
    safety: float
    ci_low: float
    ci_high: float
    safe: Rate
    rmse: float
    rmse_all: float
    rmse_time: float
    rmse_reached: float  # over safe realisations that ended within the goal radius
    reached: Rate
    time_to_goal_s: Spread
    final_error_safe: Spread
    mean_speed: Spread
    crashes_at_gates: int
    crashes_early: int
    mean_step_ms: float
    median_step_ms: float
    nominal_differs_fraction: float
    alpha_fallback_rate: float
    ksafe_fallback_rate: float
    ksafe_fallbacks: dict[str, int]
    nominal_unsafe_fraction: float
    ess_nom_mean: float
    ess_real_mean: float
    cpu_ms: float = float("nan")  # the cost: mean process CPU time per step

    @classmethod
    def of(cls, key: tuple[str, str, float], rows: pd.DataFrame, timing: pd.DataFrame,
           main: bool) -> Cell:
        safe_mask = ~rows["crashed"].to_numpy(bool)
        safe = Rate.of(safe_mask)
        err = rows["final_error"].to_numpy(float)
        s = rows[safe_mask]
        crashed = rows[~safe_mask]
        steps = max(int(rows["steps"].sum()), 1)
        reached_safe = s["final_error"].to_numpy(float) <= s["goal_radius"].to_numpy(float)
        t_goal = s["time_to_goal_s"].to_numpy(float)
        return cls(
            *key, main, safe.n, safe.value, safe.low, safe.high, safe,
            _rmse(err[safe_mask] ** 2), _rmse(err ** 2),
            _rmse(s["mean_sq_distance"].to_numpy(float)),
            _rmse(s["final_error"].to_numpy(float)[reached_safe] ** 2), Rate.of(reached_safe),
            Spread.of(t_goal[np.isfinite(t_goal)]), Spread.of(err[safe_mask]),
            Spread.of(rows["mean_speed"]),
            int(crashed["crash_obstacle"].isin(GATES).sum()),
            int((crashed["progress"] < EARLY).sum()),
            float(timing["mean_step_ms"].mean()), float(timing["median_step_ms"].median()),
            int(rows["nominal_differs_steps"].sum()) / steps,
            int(rows["alpha_fallback_steps"].sum()) / steps,
            int(rows["ksafe_fallback_steps"].sum()) / steps,
            {r: int(rows[f"ksafe_{r}"].sum()) for r in FALLBACK_REASONS},
            int(rows["nominal_unsafe_steps"].sum()) / steps,
            float(rows["ess_nom_mean"].mean()), float(rows["ess_real_mean"].mean()),
            float(timing["mean_cpu_ms"].mean()))


PAIRS = (("sa_rmppi", "bas_mppi"), ("sa_rmppi", "rmppi"), ("rmppi", "bas_mppi"),
         ("bas_mppi", "mppi_crash"))


@dataclass(frozen=True)
class NavigationSummary:
    config: dict
    cells: tuple[Cell, ...]
    paired: tuple[Paired, ...]
    illustration: dict | None

    def cell(self, controller: str, variance: float, rule: str | None = None) -> Cell | None:
        return next((c for c in self.cells if c.controller == controller
                     and c.variance == variance and (c.main if rule is None else
                                                     c.rule == rule)), None)

    def pair(self, first: str, second: str, variance: float) -> Paired | None:
        return next((p for p in self.paired if (p.first, p.second, p.variance)
                     == (first, second, variance)), None)


def summarise(config, plan, store: RunStore, ids: dict) -> NavigationSummary:
    """The summary of a complete run; ``ids`` maps each task to its id."""
    ep = store.table("episodes").assign(goal_radius=config.goal_radius)
    timing = store.table("timing")
    main_ids = {ids[t] for ts in plan.main.values() for t in ts}
    cells = []
    for key, rows in ep.groupby(["controller", "rule", "variance"], sort=False):
        tids = set(rows["task_id"])
        cells.append(Cell.of(key, rows, timing[timing["task_id"].isin(tids)],
                             bool(tids & main_ids)))
    main = ep[ep["task_id"].isin(main_ids)]
    paired = []
    for v in config.variances:
        at = main[main["variance"] == v]
        for x, y in PAIRS:
            rx, ry = at[at["controller"] == x], at[at["controller"] == y]
            if len(rx) and len(ry):
                paired.append(Paired.of(x, y, v, rx[["realisation", "crashed"]],
                                        ry[["realisation", "crashed"]]))
    bas = main[main["controller"] == "bas_mppi"]
    for (label, v), ts in plan.sweep.items():  # every alpha rule against BaS-MPPI
        rows = ep[ep["task_id"].isin({ids[t] for t in ts})]
        ry = bas[bas["variance"] == v]
        if len(ry):
            paired.append(Paired.of(f"{rows['controller'].iloc[0]}[{label}]", "bas_mppi", v,
                                    rows[["realisation", "crashed"]],
                                    ry[["realisation", "crashed"]]))
    illu = store.meta(ids[plan.illustration]) if plan.illustration else None
    return NavigationSummary(config.as_dict(), tuple(cells), tuple(paired), illu)


def summary(finished) -> Summary:
    """summary.json: the cells, paired tests, illustration and the assumed values; one console
    line per cell. Also writes map.json (the map the run used)."""
    from studies.navigation.paper import assumed_values
    from studies.navigation.tasks import Controllers, setup

    config = finished.config
    s = summarise(config, finished.plan, finished.store, finished.ids)
    assumed = assumed_values(config, setup(Controllers.of(config)))
    atomic_write_json(finished.out / "map.json", {
        "start": config.scene.start, "goal": config.scene.goal,
        "circles": config.scene.circle_array().tolist()})
    lines = tuple(f"{NAMES[c.controller]:26s} {c.rule:22s} var {c.variance:6g}  safety "
                  f"{fmt_rate(c.safe, 0):16s} RMSE {c.rmse:.4f}  {c.mean_step_ms:.1f} ms/step"
                  for c in s.cells)
    return Summary({**to_jsonable(s), "assumed": assumed}, s, lines)

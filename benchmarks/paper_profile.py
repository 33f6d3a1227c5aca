"""How long Table I's paper profile takes on W workers: estimated from a smaller run of the
same cells, with its lower bound at the hand-written C floor.

A navigation run with fewer realisations per cell (for example ``workbench run navigation
--profile paper --set realisations=8 --set sweep_realisations=8 --workers 2 --out RUN``) gives,
per cell (controller, alpha rule, variance), the mean number of control steps of an episode
(episodes end at a crash or after ``steps``) and the mean time of a step. The paper profile's
plan gives the number of episodes per cell. Then

* estimate = sum over cells of episodes x mean steps x mean step time, divided by W, plus the
  run's fixed part (calibration, reports: its wall time minus its step time / W);
* lower bound = the same step counts, each robust step (SA-RMPPI, RMPPI) costing only the
  hand-written C floor of its SAIS rollout and each MPPI step (BaS-MPPI, crash-cost MPPI) only
  the floor of the BaS-MPPI rollout, both reading their noise from memory (``make bench``
  records ``floor_sais_rollout_N1024_T100_1thread`` and ``floor_bas_mppi_rollout_...``): no
  noise generation, candidate batch, feedback gains, weights, update, plant or Python; one
  thread per worker, W workers busy all the time.

Usage: ``python -m benchmarks.paper_profile RUN [reports/bench/bench.json] [--workers 2]``.
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path

import pandas as pd

from studies.navigation import STUDY
from studies.navigation.config import ROBUST
from studies.navigation.tasks import Realisation, plan, rule_label
from workbench.study.runner import resolve_config

FLOORS = {"robust": "floor_sais_rollout_N1024_T100_1thread",
          "mppi": "floor_bas_mppi_rollout_N1024_T100_1thread"}


def cell_counts(config) -> Counter:
    """Episodes per (controller, rule label, variance) of a config's plan."""
    return Counter((t.controller, rule_label(t.controller, t.rule), float(t.variance))
                   for t in plan(config).tasks if isinstance(t, Realisation))


def run_cells(run: Path) -> pd.DataFrame:
    """Per cell of a stored run: episodes, mean steps, mean step time (ms)."""
    e = pd.read_csv(run / "episodes.csv")
    t = pd.read_csv(run / "timing.csv")[["task_id", "mean_step_ms"]]
    m = e.merge(t, on="task_id", validate="one_to_one")
    m["step_s"] = m["steps"] * m["mean_step_ms"] / 1e3
    g = m.groupby(["controller", "rule", "variance"]).agg(
        episodes=("steps", "size"), steps=("steps", "mean"), step_s=("step_s", "mean"))
    return g


def estimate(run: Path, floors: dict[str, float], workers: int = 2,
             profile: str = "paper") -> dict:
    """Estimated wall time (s) of ``profile`` and its floor lower bound, from ``run``."""
    cells = run_cells(run)
    target = cell_counts(resolve_config(STUDY, profile))
    missing = [k for k in target if k not in cells.index]
    if missing:
        raise ValueError(f"run {run}: no episodes of the profile's cells {missing[:3]} "
                         f"({len(missing)} missing): run the profile with fewer realisations")
    step_s = floor_s = steps = 0.0
    for (ctrl, rule, var), n in target.items():
        c = cells.loc[(ctrl, rule, var)]
        step_s += n * c["step_s"]
        steps += n * c["steps"]
        kind = "robust" if ctrl in ROBUST else "mppi"
        floor_s += n * c["steps"] * floors[kind] / 1e3
    rec = json.loads((run / "run.json").read_text())
    run_step_s = float((cells["episodes"] * cells["step_s"]).sum())
    whole = rec.get("tasks", {}).get("loaded", 1) == 0  # every task computed in one go
    wall = float(rec.get("wall_time_s", 0.0)) if whole else 0.0
    fixed = max(0.0, wall - run_step_s / workers)  # 0 when the run resumed stored tasks
    return {"episodes": int(sum(target.values())), "steps": steps,
            "estimate_s": step_s / workers + fixed, "fixed_s": fixed,
            "lower_bound_s": floor_s / workers, "workers": workers,
            "run_episodes": int(cells["episodes"].sum()), "run_wall_s": wall,
            "floors_ms": floors}


def floors_from(bench: Path) -> dict[str, float]:
    recs = {r["name"]: r for r in json.loads(bench.read_text())["records"]}
    try:
        return {k: float(recs[name]["value"]) for k, name in FLOORS.items()}
    except KeyError as exc:
        raise ValueError(f"{bench}: no record {exc} (run make bench first)") from None


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("bench", type=Path, nargs="?", default=Path("reports/bench/bench.json"))
    ap.add_argument("--workers", type=int, default=2)
    a = ap.parse_args(argv)
    r = estimate(a.run, floors_from(a.bench), a.workers)
    print(f"paper profile: {r['episodes']} episodes, {r['steps']:.0f} control steps "
          f"(from {r['run_episodes']} episodes in {a.run})")
    print(f"estimated {r['estimate_s'] / 60:.1f} min on {a.workers} workers "
          f"(fixed part {r['fixed_s']:.0f} s); lower bound at the C floor "
          f"{r['lower_bound_s'] / 60:.1f} min (floors {r['floors_ms']})")


if __name__ == "__main__":
    main()

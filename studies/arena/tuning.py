"""The arena's fair tuning: one task per (system, controller), each the same budget of optuna
trials on the same training episodes (maps from the tuning seed range, disjoint from the test
maps), maximising one declared objective.

Every controller meets the same training episodes: episode e of every trial, for every
controller of a system, has the same map, plant disturbances and sampler stream (keyed by the
system and e only). The first trial is the hand-tuned point.

``make tune-arena`` runs this study and writes its result as the shipped defaults
(:mod:`workbench.scenarios.tuned`), read by the arena's ``tuned`` rows.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from studies.arena.config import RESULT_VERSION, ArenaConfig
from studies.arena.episodes import Controls, run_episode
from studies.arena.tasks import hand_settings, system_values, where
from workbench.scenarios.methods import names
from workbench.scenarios.systems import SYSTEMS, system
from workbench.scenarios.tuned import SHIPPED, Tuned, shipped, space
from workbench.study import TaskContext, TaskOutput, to_jsonable
from workbench.study.io import atomic_write_json
from workbench.study.spec import Declaration, Summary
from workbench.study.tasks import seed_sequence
from workbench.study.tuning import tune

OBJECTIVE = ("success rate (goal reached without a crash) minus 0.01 x the mean final distance "
             "to the goal in map units (metres divided by the system's map scale)")


@dataclass(frozen=True)
class TuningTask:
    system: str
    controller: str

    def stream_key(self) -> tuple[int, int]:
        return list(SYSTEMS).index(self.system), names().index(self.controller)


def training(config: ArenaConfig) -> list[tuple[str, int]]:
    """The training maps: (family, seed) for every family and every tuning seed."""
    return [(f.family, s) for s in config.tuning_seeds() for f in config.families]


def objective_of(config: ArenaConfig, task: TuningTask, threads: int = 1):
    base = hand_settings(config, task.system)
    spec = system(task.system)
    dist = config.tuning_disturbance.disturbance(spec.level_scale, spec.disturbed)
    maps = training(config)
    key = list(SYSTEMS).index(task.system)

    def objective(params: dict[str, float], trial: int) -> float:
        c = Controls(task.controller, base.with_values(task.controller, params), config.robust,
                     config.feedback, config.calibration_seed)
        success, error = [], []
        for e in range(config.tuning.episodes):
            fam, seed = maps[e % len(maps)]
            ss = seed_sequence(config.seed, (key, 1_000_003, e))  # not the controller or trial
            rc, rp = (np.random.default_rng(s) for s in ss.spawn(2))
            out = run_episode(where(config, task.system, fam, seed), c, dist, config.steps,
                              config.goal_radius, rc, rp, threads)
            success.append(out.success)
            error.append(out.final_error / spec.scale)
        return float(np.mean(success) - 0.01 * np.mean(error))

    return objective, base.values(task.controller)


def run_task(task: TuningTask, ctx: TaskContext, config: ArenaConfig,
             prepared=None) -> TaskOutput:
    objective, start = objective_of(config, task, ctx.threads)
    res = tune(space(task.controller), objective, config.tuning, start, description=OBJECTIVE)
    t = res.trials
    return TaskOutput(
        tables={"trials": {"trial": np.array([x.number for x in t]),
                           "score": np.array([x.score for x in t]),
                           "params": np.array([json.dumps(x.params) for x in t], dtype=str)},
                "best": {"score": np.array([res.score]), "start_score": np.array([
                    res.start_score]), "params": np.array([json.dumps(res.best)], dtype=str)}})


def plan(config: ArenaConfig) -> tuple[TuningTask, ...]:
    return tuple(TuningTask(s, c) for s in config.systems for c in config.controllers)


def fingerprint(config: ArenaConfig) -> dict:
    d = asdict(config)
    d["system_values"] = system_values(config.systems)
    for k in ("controllers", "systems", "test_maps", "test_seed", "disturbances",
              "realisations", "tunings"):
        d.pop(k)
    return d


def declare(config: ArenaConfig) -> Declaration:
    return Declaration(plan(config), run_task, fingerprint(config), RESULT_VERSION)


def tuned_entries(config: ArenaConfig, store) -> list[Tuned]:
    best = store.table("best")
    maps = ", ".join(f"{f}-{s}" for f, s in training(config))
    train = (f"{config.tuning.episodes} episodes per trial on maps {maps} under "
             f"{config.tuning_disturbance.label}")
    out = []
    for _, r in best.iterrows():
        out.append(Tuned(r["system"], r["controller"], json.loads(r["params"]),
                         float(r["score"]), float(r["start_score"]), config.tuning, OBJECTIVE,
                         train))
    return out


def summary(finished) -> Summary:
    entries = tuned_entries(finished.config, finished.store)
    lines = tuple(f"{t.system:18s} {t.controller:14s} training score {t.start_score:.3f} "
                  f"(hand) -> {t.score:.3f}: " + ", ".join(f"{k} {v:.3g}"
                                                          for k, v in t.params.items())
                  for t in entries)
    return Summary({"tuned": [t.as_dict() for t in entries],
                    "budget": to_jsonable(finished.config.tuning)}, entries, lines)


def report(finished, summ) -> Path:
    from workbench.study import md_table
    from workbench.study.io import atomic_write_text

    rows = [[t.system, t.controller, f"{t.start_score:.3f}", f"{t.score:.3f}",
             ", ".join(f"{k} {v:.3g}" for k, v in t.params.items())] for t in summ.value]
    b = finished.config.tuning
    text = ["# Arena tuning", "", finished.run_line, "",
            f"Budget per controller: {b.trials} trials x {b.episodes} episodes "
            f"(TPE seeded with {b.seed}). Objective: {OBJECTIVE}.", "",
            *md_table(["system", "controller", "hand-tuned score", "tuned score", "tuned"],
                      rows), ""]
    path = Path(finished.out) / "report.md"
    atomic_write_text(path, "\n".join(text))
    return path


def ship(run_dir: Path | str, path: Path | None = None) -> Path:
    """Write a finished tuning run's results as the shipped defaults (entries for other
    (system, controller) pairs are kept)."""
    data = json.loads((Path(run_dir) / "summary.json").read_text(encoding="utf-8"))
    entries = {k: v.as_dict() for k, v in shipped(path).items()}
    for e in data["tuned"]:
        entries[(e["system"], e["controller"])] = e
    target = Path(path or SHIPPED)
    atomic_write_json(target, {"tuned": [entries[k] for k in sorted(entries)]})
    return target


if __name__ == "__main__":
    import sys

    print(ship(sys.argv[1] if len(sys.argv) > 1 else "reports/arena-tuning"))

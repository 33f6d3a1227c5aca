"""Run the study on the framework: declare it, execute (resumably), summarise, report."""

from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path

from studies.navigation.config import RESULT_VERSION, StudyConfig
from studies.navigation.paper import assumed_values
from studies.navigation.report import write_report
from studies.navigation.summary import NavigationSummary, summarise
from studies.navigation.tasks import Plan, plan, run_task, setup
from workbench.sampling.controllers import MPPIConfig, RMPPIConfig
from workbench.sampling.feedback import FeedbackWeights
from workbench.scenarios.navigation import TUNED_LAMBDA, TUNED_Q_BETA, TUNED_SIGMA
from workbench.study import RunResult, RunStore, Study, run_study, tasks_phrase, to_jsonable
from workbench.study.io import atomic_write_json


@dataclass(frozen=True)
class Outcome:
    """A finished run: its summary, the framework's run record and the report's path."""

    summary: NavigationSummary
    run: RunResult
    report: Path


def fingerprint(config: StudyConfig) -> dict:
    """Every input results depend on beyond the task description."""
    return {"scene": asdict(config.scene), "steps": config.steps,
            "goal_radius": config.goal_radius, "velocity_stride": config.velocity_stride,
            "mppi": asdict(MPPIConfig(sigma=TUNED_SIGMA, lam=TUNED_LAMBDA)),
            "q_beta": TUNED_Q_BETA, "robust": asdict(RMPPIConfig()),
            "feedback": asdict(FeedbackWeights())}


def study(config: StudyConfig) -> tuple[Study, Plan]:
    p = plan(config)
    return Study("navigation", p.tasks, partial(run_task, config=config), seed=config.seed,
                 config=config.as_dict(), fingerprint=fingerprint(config),
                 version=RESULT_VERSION), p


def run(config: StudyConfig, out: Path, *, workers: int = 2, scheduler: str | None = None,
        progress: bool = True) -> Outcome:
    """Run (or continue) the study in ``out``; write summary.json, map.json, the figures and
    report.md. Raises RuntimeError listing the tasks that raised."""
    t0, load0 = time.perf_counter(), os.getloadavg()[0]
    out = Path(out)
    decl, p = study(config)
    result = run_study(decl, out, workers=workers, scheduler=scheduler, progress=progress)
    result.raise_for_errors()
    store = RunStore(out)
    ids = dict(zip(decl.tasks, decl.task_ids(), strict=True))
    summary = summarise(config, p, store, ids)
    nav = setup(config.scene)
    assumed = assumed_values(config, nav)
    circles = config.scene.circle_array()
    atomic_write_json(out / "map.json", {"start": config.scene.start, "goal": config.scene.goal,
                                         "circles": circles.tolist()})
    atomic_write_json(out / "summary.json", {"study": decl.name, **to_jsonable(summary),
                                             "assumed": assumed})
    wall = time.perf_counter() - t0
    where = f"scheduler {scheduler}" if scheduler else f"{workers} workers"
    cpu = os.cpu_count()
    load = (load0, os.getloadavg()[0])
    atomic_write_json(out / "run.json", {
        "tasks": {"total": result.n_tasks, "computed": result.computed, "loaded": result.loaded},
        "wall_time_s": wall, "backend": where, "cpu_count": cpu, "load_average_1min": load})
    run_line = (f"Wall time {wall:.0f} s ("
                f"{tasks_phrase(result.computed, result.n_tasks)}; {where}; {cpu} cores, "
                f"1-min load average {load[0]:.1f} at the start and {load[1]:.1f} at the end: "
                "compute times per step are wall-clock and grow with the load).")
    report = write_report(summary, store, p, ids, config.scene, assumed, run_line)
    return Outcome(summary, result, report)

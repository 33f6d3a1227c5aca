"""Run the study on the framework: declare it, execute (resumably), summarise, report.

Tasks and their streams: :mod:`~studies.tracking_comparison.tasks`; the run directory layout:
:mod:`workbench.study.store`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path

from studies.tracking_comparison.config import RESULT_VERSION, StudyConfig
from studies.tracking_comparison.findings import all_claims
from studies.tracking_comparison.methods import Setup
from studies.tracking_comparison.paper import assumed_values
from studies.tracking_comparison.report import write_report
from studies.tracking_comparison.summary import TrackingSummary, summarise
from studies.tracking_comparison.tasks import plan, run_task
from workbench.study import RunResult, RunStore, Study, run_study, tasks_phrase, to_jsonable
from workbench.study.io import atomic_write_json


@dataclass(frozen=True)
class Outcome:
    """A finished run: its summary, the framework's run record and the report's path."""

    summary: TrackingSummary
    run: RunResult
    report: Path


def study(config: StudyConfig, setup: Setup) -> tuple[Study, object]:
    """The study declaration: tasks, task function, seed, and what every result depends on."""
    p = plan(config)
    return Study("tracking_comparison", p.tasks, partial(run_task, setup=setup),
                 seed=config.seed, config=config.as_dict(),
                 fingerprint={"setup": setup.fixed()}, version=RESULT_VERSION), p


def run(config: StudyConfig, out: Path, *, workers: int = 2, scheduler: str | None = None,
        setup: Setup | None = None, progress: bool = True) -> Outcome:
    """Run (or continue) the study in ``out``; write summary.json, the figures and report.md.
    Raises RuntimeError listing the tasks that raised (their tracebacks in errors.json)."""
    t0 = time.perf_counter()
    setup = setup or Setup()
    decl, p = study(config, setup)
    result = run_study(decl, out, workers=workers, scheduler=scheduler, progress=progress)
    result.raise_for_errors()
    store = RunStore(out)
    ids = dict(zip(decl.tasks, decl.task_ids(), strict=True))
    summary = summarise(config, p, store, ids)
    main_ids = {ids[t] for ts in p.main.values() for t in ts}
    table = store.table("rollouts")
    main = table[table["task_id"].isin(main_ids)]
    wall = time.perf_counter() - t0
    where = f"scheduler {scheduler}" if scheduler else f"{workers} workers"
    run_line = (f"Wall time {wall:.1f} s ("
                f"{tasks_phrase(result.computed, result.n_tasks)}; {where}).")
    assumed = assumed_values(config, setup)
    # summary.json depends only on the results (byte-identical across runs); run.json does not
    atomic_write_json(Path(out) / "summary.json",
                      {"study": decl.name, **to_jsonable(summary), "assumed": assumed,
                       "claims": to_jsonable(all_claims(summary))})  # printed iff holds
    atomic_write_json(Path(out) / "run.json",
                      {"tasks": {"total": result.n_tasks, "computed": result.computed,
                                 "loaded": result.loaded}, "wall_time_s": wall, "backend": where})
    report = write_report(summary, store, main, setup.scene, assumed, run_line)
    return Outcome(summary, result, report)

"""Run the study on the framework: shared set-up (once), declare, execute (resumably),
summarise from the tidy tables, report."""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path

from studies.free_energy_bound.config import RESULT_VERSION, StudyConfig
from studies.free_energy_bound.findings import all_claims
from studies.free_energy_bound.paper import assumed_values
from studies.free_energy_bound.report import write_report
from studies.free_energy_bound.shared import Shared, load_or_compute
from studies.free_energy_bound.summary import BoundSummary, summarise
from studies.free_energy_bound.tasks import run_task, tasks
from workbench.study import RunResult, RunStore, Study, run_study, tasks_phrase, to_jsonable
from workbench.study.io import atomic_write_json


@dataclass(frozen=True)
class Outcome:
    summary: BoundSummary
    run: RunResult
    report: Path
    wall_s: float


def study(config: StudyConfig, shared: Shared) -> Study:
    """Tasks, the task function (with the shared set-up bound in) and what results depend on:
    the config's result values and the shared set-up itself (threshold knots, constants)."""
    fp = {"config": config.results_dict(), "shared": {k: v for k, v in asdict(shared).items()
                                                      if k != "setup_s"}}
    return Study("free_energy_bound", tasks(config), partial(run_task, config=config,
                                                             shared=shared),
                 seed=config.seed, config=config.as_dict(), fingerprint=fp,
                 version=RESULT_VERSION)


def run(config: StudyConfig, out: Path, *, workers: int = 2, scheduler: str | None = None,
        progress: bool = True) -> Outcome:
    """Run (or continue) the study in ``out``; write summary.json, the figures and report.md.
    Raises RuntimeError listing the tasks that raised (tracebacks in errors.json)."""
    t0 = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    shared = load_or_compute(config, out)
    decl = study(config, shared)
    result = run_study(decl, out, workers=workers, scheduler=scheduler, progress=progress)
    result.raise_for_errors()
    store = RunStore(out)
    steps, episodes = store.table("steps"), store.table("episodes")
    summary = summarise(config, steps, episodes)
    wall = time.perf_counter() - t0
    where = f"scheduler {scheduler}" if scheduler else f"{workers} workers"
    run_line = (f"Wall time {wall:.1f} s ("
                f"{tasks_phrase(result.computed, result.n_tasks)}; {where}; shared set-up "
                f"{sum(shared.setup_s.values()):.1f} s when first computed).")
    assumed = assumed_values(config, shared)
    nb = shared.no_barrier.L_q
    claims = all_claims(summary, nb)
    atomic_write_json(out / "summary.json", {
        "study": decl.name, **to_jsonable(summary),
        "global_constant": to_jsonable(shared.global_), "no_barrier_constant":
        to_jsonable(shared.no_barrier), "assumed": assumed,
        "claims": {k: [to_jsonable(c) for c in v] for k, v in claims.items()}})
    atomic_write_json(out / "run.json", {
        "tasks": {"total": result.n_tasks, "computed": result.computed, "loaded": result.loaded},
        "wall_time_s": wall, "backend": where, "shared_setup_s": shared.setup_s})
    report = write_report(summary, steps, out, assumed, nb, run_line)
    return Outcome(summary, result, report, wall)

"""A toy study for the framework tests: cells of seeded tasks, optional sleep and failure.

Run as ``main([out, workers, n_tasks, sleep])`` from a subprocess (exit code 130 when stopped).
"""

from __future__ import annotations

import json
import os
import sys
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np

from workbench.study import (
    Rate,
    RunStore,
    Study,
    StudyInterrupted,
    TaskContext,
    TaskOutput,
    run_study,
    to_jsonable,
)

INITIALISED = False


def init_toy() -> None:
    """A worker initialiser: marks the process (a study would set sampler threads here)."""
    global INITIALISED
    INITIALISED = True


@dataclass(frozen=True)
class ToyTask:
    cell: str
    seed_index: int
    n: int = 50


def run_toy(task: ToyTask, ctx: TaskContext, sleep: float = 0.0,
            fail_seed: int | None = None) -> TaskOutput:
    """Gaussian draws from the task's own stream; a swallowed KeyboardInterrupt is flagged."""
    interrupted = False
    t_end = time.monotonic() + sleep
    while time.monotonic() < t_end:
        try:
            time.sleep(0.01)
        except KeyboardInterrupt:  # like a solver that swallows the interrupt
            interrupted = True
    if task.seed_index == fail_seed:
        raise ValueError(f"toy failure in cell {task.cell}")
    x = ctx.rng().standard_normal(task.n)
    return TaskOutput(tables={"draws": {"i": np.arange(task.n), "x": x,
                                        "interrupted": np.full(task.n, interrupted)}},
                      arrays={"path": np.cumsum(x)},
                      meta={"mean": float(x.mean()), "initialised": INITIALISED,
                            "omp": os.environ.get("OMP_NUM_THREADS"), "threads": ctx.threads,
                            "pid": os.getpid()})


def toy_study(n_tasks: int = 8, sleep: float = 0.0, fail_seed: int | None = None,
              cells: tuple[str, ...] = ("a", "b"), init: bool = False) -> Study:
    tasks = [ToyTask(c, s) for s in range(n_tasks // len(cells)) for c in cells]
    return Study("toy", tuple(tasks), partial(run_toy, sleep=sleep, fail_seed=fail_seed),
                 seed=7, config={"n_tasks": n_tasks}, fingerprint={"fail_seed": fail_seed},
                 worker_init=init_toy if init else None)


def summary_json(out: Path) -> str:
    """A typed summary from the tidy table: per cell, the rate of positive draws."""
    df = RunStore(out).table("draws")
    rates = {c: Rate.of(g["x"].to_numpy() > 0) for c, g in df.groupby("cell")}
    return json.dumps(to_jsonable(rates), sort_keys=True)


def main(argv: list[str]) -> None:
    out, workers, n_tasks, sleep = Path(argv[0]), int(argv[1]), int(argv[2]), float(argv[3])
    try:
        run_study(toy_study(n_tasks, sleep), out, workers=workers, progress=False)
    except StudyInterrupted:
        sys.exit(130)
    print(summary_json(out))


if __name__ == "__main__":
    main(sys.argv[1:])


def toy_stages(outputs, per_round: int = 4, rounds: int = 3):
    """A staged toy: round r has ``per_round`` tasks of cell ``r{r}``; the next round runs
    while the mean of every draw so far is above -1 (always, for N(0, 1) draws), but only up
    to round ``rounds - 2``: the last round is never asked for."""
    wanted = [ToyTask(f"r{r}", s) for r in range(1) for s in range(per_round)]
    for r in range(1, rounds - 1):
        outs = [outputs(t) for t in wanted]
        if any(o is None for o in outs):
            return wanted
        if np.mean([o["draws"]["x"].mean() for o in outs]) > -1:
            wanted += [ToyTask(f"r{r}", s) for s in range(per_round)]
    return wanted


def staged_toy(per_round: int = 4, rounds: int = 3) -> Study:
    tasks = [ToyTask(f"r{r}", s) for r in range(rounds) for s in range(per_round)]
    return Study("toy_staged", tuple(tasks), run_toy, seed=7, config={"rounds": rounds},
                 stages=partial(toy_stages, per_round=per_round, rounds=rounds))

"""The study's tasks: Monte Carlo batches (method, variant, seed) and the noise-free nominal
closed loops the figures draw, the pure task function, and the plan of which tasks make up the
main study and each sweep point."""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cache

import numpy as np

from studies.tracking_comparison.config import METHODS, RESULT_VERSION, StudyConfig, Variant
from studies.tracking_comparison.methods import Nominal, Setup, solve_nominal
from studies.tracking_comparison.rollouts import (
    LinearDynamics,
    StepClock,
    control_noise,
    ecbf_rollouts,
    feedback_rollouts,
    lift_function,
    margins_function,
    rollout_metrics,
    stream_key,
)
from workbench.filters.ecbf import ECBFFilter
from workbench.problem.barrier import embed_barrier
from workbench.study import TaskContext, TaskOutput
from workbench.study.latency import step_table
from workbench.study.spec import Declaration


@dataclass(frozen=True)
class Rollouts:
    """n_rollouts closed loops of ``method`` under ``variant`` with noise stream ``seed_index``
    (seed 0 keeps its paths for the figures)."""

    method: str
    variant: Variant
    seed_index: int
    n_rollouts: int

    def stream_key(self) -> tuple[int, int]:
        return stream_key(self.method, self.seed_index)


@dataclass(frozen=True)
class NominalLoop:
    """The noise-free closed loop of a method's nominal solution (paper Figs. 1-3, left)."""

    method: str
    variant: Variant

    def stream_key(self) -> tuple[int, int]:
        return len(METHODS), METHODS.index(self.method)  # draws nothing


def nominal(method: str, variant: Variant, setup: Setup) -> Nominal:
    """A method's nominal solution, solved once per process (a few ms); the noise level and
    placement do not enter the plan."""
    return _nominal(method, replace(variant, ecbf_noise="before", noise_std=0.0), setup)


@cache
def _nominal(method: str, variant: Variant, setup: Setup) -> Nominal:
    return solve_nominal(method, variant, setup)


def closed_loop(method: str, variant: Variant, setup: Setup, nom: Nominal,
                noise: np.ndarray, clock: StepClock | None = None) -> dict[str, np.ndarray]:
    """Run one batch of closed loops under ``noise`` (N, T, nu) and measure each rollout
    (``clock``: times each step's control computation)."""
    model = setup.model()
    dyn = LinearDynamics.from_model(model)
    x0 = np.array(setup.scene.start)
    counts = {name: np.zeros(noise.shape[0], dtype=np.int64)
              for name in ("infeasible_qp_steps", "fallback_steps", "qp_steps")}
    if method == "ecbf":
        r = ecbf_rollouts(dyn, x0, nom.X, nom.U, nom.K, noise,
                          ECBFFilter(model, setup.ecbf_for(variant)),
                          noise_after=variant.ecbf_noise == "after", clock=clock)
        X = r.X
        counts = {"infeasible_qp_steps": r.infeasible_steps, "fallback_steps": r.fallback_steps,
                  "qp_steps": r.qp_steps}
    else:
        lift = lift_function(embed_barrier(model, setup.barrier)) if method == "bas" else None
        X = feedback_rollouts(dyn, x0, nom.X, nom.U, nom.K, noise, model.u_min, model.u_max,
                              lift, clock)
    min_h, final = rollout_metrics(X, margins_function(model), np.array(setup.scene.target[:2]))
    return {"X": X, "min_h": min_h, "final_distance": final, **counts}


def run_task(task: Rollouts | NominalLoop, ctx: TaskContext, setup: Setup) -> TaskOutput:
    """The task function: rows per rollout (and seed-0 paths), or the nominal loop."""
    nom = nominal(task.method, task.variant, setup)
    T = setup.scene.horizon
    if isinstance(task, NominalLoop):
        clock = StepClock()  # one robot's control step, online (the solve above is offline)
        cl = closed_loop(task.method, task.variant, setup, nom, np.zeros((1, T, 2)), clock)
        meta = {**nom.info, "closed_loop_min_h": float(cl["min_h"][0]),
                "closed_loop_final_distance": float(cl["final_distance"][0]),
                "closed_loop_infeasible_qp_steps": int(cl["infeasible_qp_steps"][0])}
        return TaskOutput(tables={"step_times": step_table(clock.wall, clock.cpu)},
                          arrays={"path": cl["X"][0, :, :2]}, meta=meta)
    noise = control_noise(ctx.rng(), task.n_rollouts, T, 2, task.variant.noise_std)
    res = closed_loop(task.method, task.variant, setup, nom, noise)
    rows = {"rollout": np.arange(task.n_rollouts), "min_h": res["min_h"],
            "final_distance": res["final_distance"],
            **{k: res[k] for k in ("infeasible_qp_steps", "fallback_steps", "qp_steps")}}
    arrays = ({"positions": res["X"][:, :, :2].astype(np.float32)} if task.seed_index == 0
              else {})
    return TaskOutput(tables={"rollouts": rows}, arrays=arrays)


@dataclass(frozen=True)
class Plan:
    """The tasks in dispatch order, and which of them make up each part of the study."""

    tasks: tuple[Rollouts | NominalLoop, ...]
    nominal: dict[str, NominalLoop]
    main: dict[str, tuple[Rollouts, ...]]
    sweep: tuple[tuple[str, float | str, dict[str, tuple[Rollouts, ...]]], ...]


def plan(config: StudyConfig) -> Plan:
    """Main tasks at the base variant and, per sweep point and method, its tasks (a point that
    does not change a method shares that method's tasks with the base point)."""
    def batch(m, variant, n_seeds, n):
        v = variant.for_method(m, config.base)
        return tuple(Rollouts(m, v, s, n) for s in range(n_seeds))

    main = {m: batch(m, config.base, config.n_seeds, config.n_rollouts) for m in config.methods}
    sweep = tuple((name, value, {m: batch(m, v, config.sweep_seeds, config.sweep_rollouts)
                                 for m in config.methods})
                  for name, value, v in config.sweep_points())
    nominals = {m: NominalLoop(m, config.base.for_method(m, config.base))
                for m in config.methods}
    rollouts = dict.fromkeys([*(t for ts in main.values() for t in ts),
                              *(t for _, _, per in sweep for ts in per.values() for t in ts)])
    # nominal loops first (fast), then the slow ECBF batches, largest first
    ordered = sorted(rollouts, key=lambda t: (t.method != "ecbf", -t.n_rollouts))
    return Plan((*nominals.values(), *ordered), nominals, main, sweep)


def run(task: Rollouts | NominalLoop, ctx: TaskContext, config: StudyConfig) -> TaskOutput:
    """The framework's task function: every task runs on the fixed set-up."""
    return run_task(task, ctx, Setup())


def declare(config: StudyConfig) -> Declaration:
    """The tasks of a run; results depend on the fixed set-up beyond the task descriptions."""
    p = plan(config)
    return Declaration(p.tasks, run, fingerprint={"setup": Setup().fixed()},
                       version=RESULT_VERSION, plan=p)

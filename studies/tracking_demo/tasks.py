"""One task per barrier weight: BaS-iLQG on the tracking scene, checked against IPOPT."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from studies.tracking_demo.config import DemoConfig
from workbench.ilqg.bas import TrackingWeights, bas_ilqg, tracking_params
from workbench.ilqg.oracle import solve_ipopt
from workbench.problem.models import double_integrator
from workbench.scenarios.scenes import TrackingScene
from workbench.study import TaskContext, TaskOutput
from workbench.study.spec import Declaration

RESULT_VERSION = 1


@dataclass(frozen=True)
class Solve:
    """BaS-iLQG at barrier weight ``q_beta`` and IPOPT on the same embedded problem."""

    q_beta: float


def run(task: Solve, ctx: TaskContext, config: DemoConfig) -> TaskOutput:
    scene = TrackingScene()
    model = double_integrator(obstacles=(scene.obstacle,), u_limit=scene.u_limit)
    ref = scene.reference()
    res, problem = bas_ilqg(model, scene.start, ref, scene.target,
                            weights=TrackingWeights(q_beta=task.q_beta))
    P = tracking_params(problem, ref, scene.target)
    oracle = solve_ipopt(problem, scene.start, np.zeros((scene.horizon, 2)), P)
    row = {"cost": res.cost, "ipopt_cost": oracle.cost,
           "rel_cost_gap": (res.cost - oracle.cost) / abs(oracle.cost),
           "min_h": float(min(model.margins(x[:4]).min() for x in res.X)),
           "final_distance": float(np.linalg.norm(res.X[-1, :2] - np.array(scene.target[:2]))),
           "iterations": res.iterations, "converged": res.converged}
    return TaskOutput(tables={"solves": {k: np.array([v]) for k, v in row.items()}},
                      arrays={"X": res.X},
                      meta={"ilqg_time_s": res.solve_time_s, "ipopt_time_s": oracle.solve_time_s})


def declare(config: DemoConfig) -> Declaration:
    tasks = tuple(Solve(q) for q in config.q_betas)
    return Declaration(tasks, run, fingerprint={"scene": TrackingScene().assumed_values(),
                                                "weights": TrackingWeights().__dict__},
                       version=RESULT_VERSION, plan=tasks)

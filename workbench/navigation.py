"""The navigation study's set-up (SPEC 3.2, 8.2, 10.3) with every assumed value in one place."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workbench.barrier import BarrierOptions, embed_barrier
from workbench.models import Model, double_integrator
from workbench.sampling.controllers import MPPI, MPPIConfig
from workbench.sampling.problem import SamplingProblem, navigation_costs
from workbench.scenes import NavigationScene
from workbench.validation import fail

# [A] SPEC 8.2 starts from sigma = 2, lambda = 1, q_beta = 1 and asks to tune the undisturbed
# BaS-MPPI to reach the goal. With q_beta = 1 the robot stalls in a local minimum of this map at
# (3.8, 2.2); the values below reach the goal (final error ~0.01 m in 20 s); the grid that
# chose them is in NOTES.md ("BaS-MPPI tuning").
TUNED_SIGMA = (5.0, 5.0)
TUNED_LAMBDA = 10.0
TUNED_Q_BETA = 0.01


@dataclass(frozen=True, eq=False)
class NavigationSetup:
    scene: NavigationScene
    plant: Model
    problem: SamplingProblem
    goal: np.ndarray  # physical goal state (4,)
    x0: np.ndarray  # physical start state (4,)
    mppi: MPPIConfig

    def alpha_from_bas_mppi(self, rng: np.random.Generator, calls: int = 5,
                            factor: float = 1.5) -> float:
        """SPEC 10.3 [A]: alpha = factor x the median nominal free energy of undisturbed
        BaS-MPPI calls at the start state."""
        ctrl = MPPI(self.problem, self.goal, self.mppi)
        state, F = ctrl.initial_state(), []
        for _ in range(calls):
            state, _, info = ctrl.step(state, self.x0, rng)
            F.append(info.free_energy)
        return float(factor * np.median(F))


def navigation_setup(scene: NavigationScene | None = None, *,
                     barrier: BarrierOptions | None = None, q_beta: float = TUNED_Q_BETA,
                     mppi: MPPIConfig | None = None) -> NavigationSetup:
    """Plant, barrier-embedded sampling problem and MPPI settings of the navigation study."""
    scene = scene or NavigationScene()
    plant = double_integrator(obstacles=scene.obstacles(), u_limit=scene.u_limit, dt=scene.dt)
    for name in ("start", "goal"):  # also for scenes that bring their own obstacles
        h = plant.margins(np.array([*getattr(scene, name), 0.0, 0.0]))
        if h.size and h.min() <= 0:
            raise fail(f"scene.{name}", getattr(scene, name),
                       f"lies inside obstacle {int(np.argmin(h))}; start and goal must be in "
                       "free space (h > 0)")
    problem = navigation_costs(embed_barrier(plant, barrier or BarrierOptions()), q_beta=q_beta)
    cfg = mppi or MPPIConfig(sigma=TUNED_SIGMA, lam=TUNED_LAMBDA)
    return NavigationSetup(scene, plant, problem, np.array([*scene.goal, 0.0, 0.0]),
                           np.array([*scene.start, 0.0, 0.0]), cfg)

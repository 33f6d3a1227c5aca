"""The navigation study's set-up (SPEC 3.2, 8.2, 10.3) with every assumed value in one place."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from workbench.problem.barrier import BarrierOptions, embed_barrier
from workbench.problem.models import Model, double_integrator
from workbench.sampling.controllers import MPPI, MPPIConfig, RMPPIConfig, RobustMPPI, physical_model
from workbench.sampling.feedback import FeedbackWeights, ILQGFeedback
from workbench.sampling.problem import SamplingProblem, navigation_costs
from workbench.sampling.threshold import AlphaRule, Threshold, make_threshold
from workbench.scenarios.scenes import CircleScene, NavigationScene
from workbench.sim import closed_loop
from workbench.validation import fail, one_of

CONTROLLERS = ("bas_mppi", "sa_rmppi", "rmppi", "mppi_crash")

# [A] SPEC 8.2 starts from sigma = 2, lambda = 1, q_beta = 1 and asks to tune the undisturbed
# BaS-MPPI to reach the goal. With q_beta = 1 the robot stalls in a local minimum of this map at
# (3.8, 2.2); the values below reach the goal (final error ~0.01 m in 20 s); the grid that
# chose them is in NOTES.md ("BaS-MPPI tuning").
TUNED_SIGMA = (5.0, 5.0)
TUNED_LAMBDA = 10.0
TUNED_Q_BETA = 0.01


@dataclass(frozen=True, eq=False)
class NavigationSetup:
    scene: NavigationScene | CircleScene
    plant: Model
    problem: SamplingProblem
    goal: np.ndarray  # physical goal state (4,)
    x0: np.ndarray  # physical start state (4,)
    mppi: MPPIConfig

    _traces: dict = field(default_factory=dict, repr=False)

    def physical_problem(self) -> SamplingProblem:
        """The same costs on the plant without a barrier state (crash cost only)."""
        S = self.problem.weights["S"][: self.plant.nx]
        return navigation_costs(self.plant, S=tuple(S), q_beta=0.0)

    def feedback(self, kind: str, weights: FeedbackWeights = FeedbackWeights()) -> ILQGFeedback:
        """K_safe ("bas_ilqg", on the embedded model) or plain tracking gains ("ilqg")."""
        one_of("feedback", kind, ("bas_ilqg", "ilqg"))
        model = self.problem.model if kind == "bas_ilqg" else physical_model(self.problem.model)
        return ILQGFeedback(model, self.mppi.horizon, self.problem.nx, weights)

    def calibration_trace(self, feedback: str = "bas_ilqg", robust: RMPPIConfig = RMPPIConfig(),
                          steps: int = 600, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Undisturbed run of the robust controller with alpha = inf: visited states (n, 4)
        and the real-state candidate free energies (n,), for threshold calibration."""
        key = (feedback, replace(robust, diagnostics=False), steps, seed)
        if key not in self._traces:
            # diagnostics off: the trace keeps every step's info, and a diagnostic batch is MBs
            ctrl = RobustMPPI(self.problem, self.goal, self.mppi,
                              replace(robust, alpha=np.inf, diagnostics=False),
                              self.feedback(feedback))
            ep = closed_loop(ctrl, self.plant, self.x0, steps, np.random.default_rng(seed),
                             np.random.default_rng(seed + 1))
            F = np.array([i.candidate_free_energy[-1] if i.candidate_free_energy.size
                          else np.nan for i in ep.infos])
            self._traces[key] = (ep.X[: len(F)], F)
        return self._traces[key]

    def threshold(self, rule: AlphaRule = AlphaRule(), feedback: str = "bas_ilqg",
                  robust: RMPPIConfig = RMPPIConfig(), seed: int = 0) -> Threshold:
        """The selection threshold of a rule, calibrated on this map (SPEC 10.3)."""
        if not rule.needs_calibration:
            return make_threshold(rule)
        X, F = self.calibration_trace(feedback, robust, rule.calibration_steps, seed)
        return make_threshold(rule, X, F, self.goal, self.plant.position)

    def controller(self, name: str, rule: AlphaRule = AlphaRule(),
                   robust: RMPPIConfig = RMPPIConfig(),
                   weights: FeedbackWeights = FeedbackWeights(), seed: int = 0):
        """One of :data:`CONTROLLERS`: BaS-MPPI, SA-RMPPI, RMPPI (plain iLQG feedback, the same
        alpha rule calibrated on RMPPI itself) or MPPI with a crash cost only."""
        one_of("controller", name, CONTROLLERS)
        if name == "bas_mppi":
            return MPPI(self.problem, self.goal, self.mppi)
        if name == "mppi_crash":
            return MPPI(self.physical_problem(), self.goal, self.mppi)
        kind = "bas_ilqg" if name == "sa_rmppi" else "ilqg"
        return RobustMPPI(self.problem, self.goal, self.mppi, robust,
                          self.feedback(kind, weights), self.threshold(rule, kind, robust, seed))


def navigation_setup(scene: NavigationScene | CircleScene | None = None, *,
                     barrier: BarrierOptions | None = None, q_beta: float = TUNED_Q_BETA,
                     mppi: MPPIConfig | None = None) -> NavigationSetup:
    """Plant, barrier-embedded sampling problem and MPPI settings of the navigation study.

    ``scene``: the paper's map (default, :class:`NavigationScene`) or your own circles
    (:class:`~workbench.scenarios.scenes.CircleScene`); any object with ``start``, ``goal``, ``dt``,
    ``u_limit`` and ``obstacles()`` works."""
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

"""The navigation set-up: a map of circles, the plant of a :class:`System` (the planar double
integrator by default), the barrier-embedded sampling problem and the sampler settings, and the
controllers built on them."""

from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from workbench.problem.barrier import BarrierOptions, embed_barrier
from workbench.problem.models import Model, margin_violation
from workbench.sampling.calibration import calibrate
from workbench.sampling.feedback import FeedbackWeights, ILQGFeedback
from workbench.sampling.mppi import MPPIConfig
from workbench.sampling.planning import physical_model
from workbench.sampling.problem import SamplingProblem, goal_costs, navigation_costs
from workbench.sampling.robust import RMPPIConfig
from workbench.sampling.threshold import AlphaRule, Threshold
from workbench.scenarios.methods import MethodSettings, build, feedback_law, method
from workbench.scenarios.scenes import CircleScene, NavigationScene, ObstacleScene
from workbench.scenarios.systems import SYSTEMS, System
from workbench.scenarios.systems import TUNED_LAMBDA as TUNED_LAMBDA
from workbench.scenarios.systems import TUNED_Q_BETA as TUNED_Q_BETA
from workbench.scenarios.systems import TUNED_SIGMA as TUNED_SIGMA
from workbench.scenarios.systems import system as system_named
from workbench.validation import fail, one_of


@dataclass(frozen=True, eq=False)
class NavigationSetup:
    """The plant, the barrier-embedded sampling problem and the sampler settings of one map,
    for one :class:`~workbench.scenarios.systems.System`."""

    scene: NavigationScene | CircleScene | ObstacleScene
    plant: Model
    problem: SamplingProblem
    goal: np.ndarray  # physical goal state (n_physical,)
    x0: np.ndarray  # physical start state (n_physical,)
    mppi: MPPIConfig
    system: System = field(default_factory=lambda: SYSTEMS["double_integrator"])

    def physical_problem(self) -> SamplingProblem:
        """The same costs on the plant without a barrier state (crash cost only)."""
        w = self.problem.weights
        if w is None:
            raise fail("NavigationSetup.problem.weights", None, "must be set (by "
                       "navigation_costs or goal_costs) to form the physical problem")
        S = w["S"][: self.plant.nx]
        if self.system.cost_form == "navigation":
            return navigation_costs(self.plant, S=tuple(S), q_beta=0.0)
        return goal_costs(self.plant, Q=w["Q"], S=S, q_beta=0.0,
                          angles=tuple(int(i) for i in w["angles"]))

    def _weights(self, weights: FeedbackWeights | None) -> FeedbackWeights:
        return self.system.feedback_weights if weights is None else weights

    def feedback(self, kind: str, weights: FeedbackWeights | None = None) -> ILQGFeedback:
        """K_safe ("bas_ilqg", on the embedded model) or plain tracking gains ("ilqg");
        ``weights`` default to the system's tracking weights."""
        one_of("feedback", kind, ("bas_ilqg", "ilqg"))
        model = self.problem.model if kind == "bas_ilqg" else physical_model(self.problem.model)
        return ILQGFeedback(model, self.mppi.horizon, self.problem.nx, self._weights(weights))

    def progress(self) -> ca.SX | None:
        """The progress measure of the threshold rules (:meth:`System.progress`): None (the
        distance in the plant's position coordinates (0, 1)) or the system's distance to the
        goal as a CasADi expression in the plant's state."""
        return self.system.progress(self.plant, self.goal)

    def goal_distance(self, X) -> np.ndarray:
        """Distance of the states ``X`` to the goal (:meth:`System.goal_distance`)."""
        return self.system.goal_distance(self.plant, X, self.goal)

    def threshold(self, rule: AlphaRule = AlphaRule(), feedback: str = "bas_ilqg",
                  robust: RMPPIConfig = RMPPIConfig(),
                  weights: FeedbackWeights | None = None, seed: int = 0,
                  settings: MethodSettings | None = None) -> Threshold:
        """The selection threshold of ``rule`` on this map (:func:`calibrate`: one undisturbed
        episode of the robust controller with this feedback, seeded with ``seed``).
        ``feedback``: "bas_ilqg" (K_safe), "ilqg", "al_ilqg" or "ecbf" (see
        :func:`workbench.scenarios.methods.feedback_law`); ``settings``: the methods' options
        (default options when None)."""
        law = feedback_law(self, feedback, settings, weights=self._weights(weights))
        return calibrate(rule, self.problem, self.goal, self.plant, self.x0, self.mppi, law,
                         robust, seed=seed, progress=self.progress())

    def controller(self, name: str, rule: AlphaRule = AlphaRule(),
                   robust: RMPPIConfig = RMPPIConfig(),
                   weights: FeedbackWeights | None = None, seed: int = 0,
                   threshold: Threshold | None = None,
                   settings: MethodSettings | None = None):
        """The registered method ``name`` (:func:`workbench.scenarios.methods.names`) with
        ``settings`` (default options when None; see
        :func:`workbench.scenarios.methods.build`). The robust ones use ``threshold``;
        without one, they calibrate ``rule`` here (:meth:`threshold`, on the controller itself,
        seeded with ``seed``): pass a threshold computed once when you build many
        controllers. ``weights``: tracking weights of the feedback laws (default: the
        system's)."""
        spec = method(name)
        weights = self._weights(weights)
        if spec.robust and threshold is None:
            why = spec.missing(self, weights)
            if why is not None:
                raise fail("controller", name, why)
            threshold = self.threshold(rule, spec.feedback or "", robust, weights, seed,
                                       settings)
        return build(self, name, settings, threshold=threshold, robust=robust,
                              weights=weights)


def navigation_setup(scene: NavigationScene | CircleScene | ObstacleScene | None = None, *,
                     system: str | System = "double_integrator",
                     barrier: BarrierOptions | None = None, q_beta: float | None = None,
                     mppi: MPPIConfig | None = None, scene_capacity: int | None = None,
                     runtime_obstacles: bool = True) -> NavigationSetup:
    """Plant, barrier-embedded sampling problem and MPPI settings of the navigation study.

    ``scene``: the paper's map (default: :class:`NavigationScene`, scaled by the system's
    ``scale``, :meth:`System.scaled`; a system built from your model: its own scene) or your
    own circles
    (:class:`~workbench.scenarios.scenes.CircleScene`, used as given, in the system's units)
    or obstacles of any kind, an occupancy map's signed-distance grid among them
    (:class:`~workbench.scenarios.scenes.ObstacleScene`: the plant is built on its
    :class:`~workbench.problem.scene_layout.SceneLayout`, ``scene_capacity`` stays unset);
    any object with ``start``, ``goal``, ``dt``, ``u_limit`` and ``obstacles()`` works.
    ``system``: a name of :data:`~workbench.scenarios.systems.SYSTEMS` or a :class:`System`
    (default the double integrator, whose set-up is unchanged). Start and goal are the system's
    states at rest (:attr:`System.state_at`), both heading from start towards the goal.
    ``q_beta`` and ``mppi`` default to the system's (sigma, lambda; N = 1024, T = 100).
    The obstacles are run-time inputs with ``scene_capacity`` slots (default: one per circle;
    every map with at most that many circles then shares one compiled set of kernels);
    ``runtime_obstacles=False`` bakes them in."""
    sysm = system if isinstance(system, System) else system_named(system)
    if scene is None:
        scene = sysm.scene if sysm.scene is not None else sysm.scaled(NavigationScene())
    plant = sysm.plant(scene, scene_capacity=scene_capacity, runtime_obstacles=runtime_obstacles)
    start, goal = np.asarray(scene.start, float), np.asarray(scene.goal, float)
    d = goal - start
    heading = float(np.arctan2(d[1], d[0])) if d.size >= 2 and np.any(d[:2] != 0) else 0.0
    states = {"start": sysm.state_at(start, heading), "goal": sysm.state_at(goal, heading)}
    eps = (barrier or BarrierOptions()).eps_h  # the barrier state counts h <= eps_h as a crash
    for name, x in states.items():  # also for scenes that bring their own obstacles
        where = margin_violation(plant, plant.margins(x), eps)
        if where is not None:
            raise fail(f"scene.{name}", getattr(scene, name),
                       f"{where}; start and goal must be in free space (h > {eps:g})")
    qb = sysm.q_beta if q_beta is None else q_beta
    problem = sysm.costs(embed_barrier(plant, barrier or BarrierOptions()), q_beta=qb)
    cfg = mppi or MPPIConfig(sigma=sysm.sigma, lam=sysm.lam, horizon=sysm.horizon)
    return NavigationSetup(scene, plant, problem, states["goal"], states["start"], cfg, sysm)

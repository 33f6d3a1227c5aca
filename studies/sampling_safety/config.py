"""Configuration of the sampling-safety study: frozen, validated at construction (errors name
the field)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from studies.navigation.config import checked_variances, variance_key
from studies.navigation.scene import MapSpec
from workbench.sampling.feedback import FeedbackWeights
from workbench.sampling.mppi import MPPIConfig
from workbench.sampling.robust import RMPPIConfig
from workbench.sampling.threshold import AlphaRule
from workbench.scenarios.methods import MethodSettings, names
from workbench.scenarios.navigation import TUNED_LAMBDA, TUNED_Q_BETA, TUNED_SIGMA
from workbench.validation import MAX_STEPS, MAX_TASKS, at_most, fail, integer, real

RESULT_VERSION = 1  # bump when the meaning of stored task results changes

__all__ = ["RESULT_VERSION", "StudyConfig", "variance_key"]


@dataclass(frozen=True)
class StudyConfig:
    """Every controller of ``controllers`` on the navigation map at every variance of
    ``variances`` (velocity disturbance, as in the navigation study), ``realisations`` episodes
    each; realisation j at a variance uses the same controller and plant streams for every
    controller (common random numbers), so results are paired by realisation.

    ``sampler``, ``q_beta``, ``robust``, ``feedback`` and ``rule`` are the navigation study's
    settings (every method shares the sampler: the same N, T, sigma and lambda); ``methods``
    holds each method's own options. The robust controllers calibrate ``rule`` once per run
    on an undisturbed episode seeded with ``calibration_seed``.

    Size limits (checked here): at most 10^7 tasks per run, 10^7 steps per episode."""

    controllers: tuple[str, ...] = field(default_factory=names)  # every registered method
    variances: tuple[float, ...] = (10.0, 50.0, 100.0)
    realisations: int = 30
    steps: int = 1000
    seed: int = 2024
    goal_radius: float = 1.0
    scene: MapSpec = field(default_factory=MapSpec)
    sampler: MPPIConfig = MPPIConfig(sigma=TUNED_SIGMA, lam=TUNED_LAMBDA)
    q_beta: float = TUNED_Q_BETA
    robust: RMPPIConfig = RMPPIConfig()
    feedback: FeedbackWeights = FeedbackWeights()
    rule: AlphaRule = AlphaRule(kappa=0.1)
    methods: MethodSettings = field(default_factory=MethodSettings)
    calibration_seed: int = 0

    def __post_init__(self) -> None:
        ctrls, known = self.controllers, names()
        if isinstance(ctrls, str) or not hasattr(ctrls, "__iter__") or len(ctrls) == 0:
            raise fail("controllers", ctrls, f"must be a non-empty subset of {known}")
        for c in ctrls:
            if c not in known:
                raise fail("controllers", c, f"unknown controller; allowed values are {known}")
        if len(set(ctrls)) != len(ctrls):
            raise fail("controllers", ctrls, "must not repeat a controller")
        object.__setattr__(self, "controllers", tuple(c for c in known if c in ctrls))
        object.__setattr__(self, "variances", checked_variances("variances", self.variances))
        for name, lo, hi in (("realisations", 1, MAX_TASKS), ("steps", 1, MAX_STEPS),
                             ("seed", 0, None), ("calibration_seed", 0, None)):
            object.__setattr__(self, name, integer(name, getattr(self, name), lo, hi))
        at_most("realisations", self.realisations,
                len(self.controllers) * len(self.variances) * self.realisations, MAX_TASKS,
                "controllers x variances x realisations (tasks of a run)")
        object.__setattr__(self, "goal_radius",
                           real("goal_radius", self.goal_radius, 0.0, strict=True))
        if not isinstance(self.scene, MapSpec):
            raise fail("scene", self.scene, "must be a MapSpec")
        self.scene.check()
        for name, kind in (("sampler", MPPIConfig), ("robust", RMPPIConfig),
                           ("feedback", FeedbackWeights), ("rule", AlphaRule),
                           ("methods", MethodSettings)):
            if not isinstance(getattr(self, name), kind):
                raise fail(name, getattr(self, name), f"must be a {kind.__name__}")
        object.__setattr__(self, "q_beta", real("q_beta", self.q_beta, 0.0))

    def as_dict(self) -> dict:
        return asdict(self)

"""Study configuration: frozen, validated at construction (errors name the field)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from studies.navigation.scene import MapSpec
from workbench.sampling.feedback import FeedbackWeights
from workbench.sampling.mppi import MPPIConfig
from workbench.sampling.robust import RMPPIConfig
from workbench.sampling.threshold import AlphaRule
from workbench.scenarios.methods import method
from workbench.scenarios.navigation import TUNED_LAMBDA, TUNED_Q_BETA, TUNED_SIGMA
from workbench.validation import (
    MAX_STEPS,
    MAX_TASKS,
    at_most,
    fail,
    flag,
    integer,
    one_of,
    real,
)

# Table I's controllers and their two ablations, in the report's order
CONTROLLERS = ("bas_mppi", "sa_rmppi", "rmppi", "mppi_crash")
ROBUST = tuple(c for c in CONTROLLERS if method(c).robust)  # controllers that use an alpha rule
RESULT_VERSION = 2  # bump when the meaning of stored task results changes
DEFAULT_RULE = AlphaRule(kappa=0.1)  # [A] chosen by an activation sweep; see sweep_rules




def checked_variances(name: str, values, allow_empty: bool = False) -> tuple[float, ...]:
    """``values`` as a tuple of distinct variances >= 0 (empty only with ``allow_empty``), or an
    error naming the field ``name``."""
    if isinstance(values, str) or not hasattr(values, "__iter__") or (
            len(values) == 0 and not allow_empty):
        raise fail(name, values, "must be a non-empty sequence of variances >= 0")
    out = tuple(real(f"{name}[{i}]", v, 0.0, strict=False) for i, v in enumerate(values))
    if len(set(out)) != len(out):
        raise fail(name, values, "must not repeat a variance")
    if len({variance_key(v) for v in out}) != len(out):
        raise fail(name, values, "variances must differ by at least 0.001")
    return out


def variance_key(variance: float) -> int:
    """The variance as an integer stream word (milli-units)."""
    return round(variance * 1000)


def _rules(name: str, rules) -> tuple[AlphaRule, ...]:
    if isinstance(rules, AlphaRule) or not hasattr(rules, "__iter__"):
        raise fail(name, rules, "must be a sequence of AlphaRule")
    for i, r in enumerate(rules):
        if not isinstance(r, AlphaRule):
            raise fail(f"{name}[{i}]", r, "must be an AlphaRule")
    return tuple(rules)


@dataclass(frozen=True)
class StudyConfig:
    """Everything a run depends on (assumptions §12.2). Main cells: every controller at every
    variance, robust controllers with ``rule``; alpha sweep: ``sweep_controller`` with each of
    ``sweep_rules`` at each of ``sweep_variances``. ``steps``: episode length (20 s = 1000
    steps of 0.02 s [A]); ``goal_radius``: "reached" radius [P, 1 m]; ``velocity_stride``: steps
    between rows of the velocity table; ``illustration``: run the Fig. 4 task (limits +-50,
    velocity variance 5000).

    The controllers: ``sampler`` (sigma, lambda, N, T, ... of every sampling controller),
    ``q_beta`` (the barrier-state weight of the sampling cost), ``robust`` (the RMPPI selection
    and its candidates), ``feedback`` (the weights of K_safe and of the plain iLQG gains).
    ``calibration_seed``: the seed of the undisturbed episode that calibrates each alpha rule
    once per run (``rule.calibration_steps`` steps; the episodes' streams come from ``seed``).

    Size limits (checked here): at most 10^7 tasks per run, 10^7 steps per episode."""

    controllers: tuple[str, ...] = CONTROLLERS
    variances: tuple[float, ...] = (0.0, 5.0, 10.0, 50.0, 100.0)
    realisations: int = 100
    steps: int = 1000
    seed: int = 2023
    rule: AlphaRule = DEFAULT_RULE
    sweep_controller: str = "sa_rmppi"
    sweep_variances: tuple[float, ...] = (10.0, 100.0)
    sweep_rules: tuple[AlphaRule, ...] = (
        AlphaRule(kappa=0.0), AlphaRule(kappa=0.25), AlphaRule(kind="quantile", quantile=0.9),
        AlphaRule(kind="start", factor=1.5))
    sweep_realisations: int = 100
    goal_radius: float = 1.0
    velocity_stride: int = 10
    illustration: bool = True
    illustration_steps: int = 60
    scene: MapSpec = field(default_factory=MapSpec)
    sampler: MPPIConfig = MPPIConfig(sigma=TUNED_SIGMA, lam=TUNED_LAMBDA)
    q_beta: float = TUNED_Q_BETA
    robust: RMPPIConfig = RMPPIConfig()
    feedback: FeedbackWeights = FeedbackWeights()
    calibration_seed: int = 0

    def __post_init__(self) -> None:
        ctrls = self.controllers
        if isinstance(ctrls, str) or not hasattr(ctrls, "__iter__") or len(ctrls) == 0:
            raise fail("controllers", ctrls, f"must be a non-empty subset of {CONTROLLERS}")
        for c in ctrls:
            if c not in CONTROLLERS:
                raise fail("controllers", c, f"unknown controller; allowed values are "
                           f"{CONTROLLERS}")
        if len(set(ctrls)) != len(ctrls):
            raise fail("controllers", ctrls, "must not repeat a controller")
        object.__setattr__(self, "controllers", tuple(c for c in CONTROLLERS if c in ctrls))
        object.__setattr__(self, "variances", checked_variances("variances", self.variances))
        for name, lo, hi in (("realisations", 1, MAX_TASKS), ("steps", 1, MAX_STEPS),
                             ("seed", 0, None), ("sweep_realisations", 1, MAX_TASKS),
                             ("velocity_stride", 1, MAX_STEPS),
                             ("illustration_steps", 2, MAX_STEPS)):
            object.__setattr__(self, name, integer(name, getattr(self, name), lo, hi))
        if not isinstance(self.rule, AlphaRule):
            raise fail("rule", self.rule, "must be an AlphaRule")
        one_of("sweep_controller", self.sweep_controller, ROBUST)
        object.__setattr__(self, "sweep_variances",
                           checked_variances("sweep_variances", self.sweep_variances, True))
        object.__setattr__(self, "sweep_rules", _rules("sweep_rules", self.sweep_rules))
        main = len(self.controllers) * len(self.variances) * self.realisations
        sweep = len(self.sweep_variances) * (1 + len(self.sweep_rules)) * self.sweep_realisations
        big = "realisations" if main >= sweep else "sweep_realisations"
        at_most(big, getattr(self, big), main + sweep + 1, MAX_TASKS,
                "controllers x variances x realisations + sweep_variances x (1 + sweep_rules) "
                "x sweep_realisations + 1 (tasks of a run, at most)")
        object.__setattr__(self, "goal_radius",
                           real("goal_radius", self.goal_radius, 0.0, strict=True))
        object.__setattr__(self, "illustration", flag("illustration", self.illustration))
        default_steps = type(self).__dataclass_fields__["illustration_steps"].default
        if not self.illustration and self.illustration_steps != default_steps:
            raise fail("illustration_steps", self.illustration_steps, "is read only by the "
                       "illustration task, and illustration = false; leave it out (default "
                       f"{default_steps}) or set illustration = true")
        if not isinstance(self.scene, MapSpec):
            raise fail("scene", self.scene, "must be a MapSpec")
        self.scene.check()  # start / goal inside an obstacle -> names scene.start / scene.goal
        for name, kind in (("sampler", MPPIConfig), ("robust", RMPPIConfig),
                           ("feedback", FeedbackWeights)):
            if not isinstance(getattr(self, name), kind):
                raise fail(name, getattr(self, name), f"must be a {kind.__name__}")
        object.__setattr__(self, "q_beta", real("q_beta", self.q_beta, 0.0))
        object.__setattr__(self, "calibration_seed",
                           integer("calibration_seed", self.calibration_seed, 0))

    def as_dict(self) -> dict:
        return asdict(self)

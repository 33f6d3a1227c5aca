"""Configuration of the sampling-safety study: frozen, validated at construction (errors name
the field)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from typing import Literal

from studies.navigation.config import checked_variances, variance_key
from studies.navigation.scene import MapSpec
from workbench.sampling.feedback import FeedbackWeights
from workbench.sampling.mppi import MPPIConfig
from workbench.sampling.robust import RMPPIConfig
from workbench.sampling.sampler import Backend, Precision
from workbench.sampling.threshold import AlphaRule
from workbench.scenarios.maps import MapFamily, generate
from workbench.scenarios.methods import MethodSettings, names
from workbench.scenarios.model_system import resolve_system
from workbench.validation import MAX_STEPS, MAX_TASKS, at_most, fail, integer, real

RESULT_VERSION = 2  # bump when the meaning of stored task results changes

__all__ = ["RESULT_VERSION", "Resolved", "SamplerSettings", "StudyConfig", "variance_key"]


@dataclass(frozen=True)
class SamplerSettings:
    """The sampler's settings over the system's own sampler (its sigma, lambda and horizon,
    MPPIConfig's defaults for the rest): each key given replaces that value, each key left
    out (None) keeps it."""

    n_samples: int | None = None
    horizon: int | None = None
    lam: float | None = None
    sigma: tuple[float, ...] | None = None
    nu_mix: float | None = None
    iterations: int | None = None
    crash_cost: float | None = None
    tail: Literal["hold", "zero"] | None = None
    smoothing: tuple[int, int] | None = None
    backend: Backend | None = None
    precision: Precision | None = None

    def over(self, base: MPPIConfig) -> MPPIConfig:
        """``base`` with the keys given here (validated by MPPIConfig)."""
        return replace(base, **{k: v for k, v in asdict(self).items() if v is not None})


@dataclass(frozen=True)
class StudyConfig:
    """Every controller of ``controllers`` on the navigation map at every variance of
    ``variances`` (velocity disturbance, as in the navigation study), ``realisations`` episodes
    each; realisation j at a variance uses the same controller and plant streams for every
    controller (common random numbers), so results are paired by realisation.

    ``system``: a registered system (``workbench list``) or your own, as ``"module:function"``
    or ``"path/file.py:function"`` returning a System
    (:func:`~workbench.scenarios.model_system.system_from_model`). ``scene``: the map of a map
    system (None: the default map, scaled to the system); a system built from a model runs on
    its own start, goal and constraints, and a scene is refused. ``family`` and ``map_seed``:
    instead of ``scene``, the map of seed ``map_seed`` (default 0) of a generated map family
    (:class:`~workbench.scenarios.maps.MapFamily`, static; e.g. ``occupancy_grid``, whose map
    is a signed-distance grid), scaled to the system. ``sampler``, ``q_beta``,
    ``feedback`` and ``goal_radius``: None takes the system's own (sigma, lambda and horizon
    with 1024 samples); a ``[sampler]`` table (:class:`SamplerSettings`) changes the keys it
    gives and keeps the system's for the others; an MPPIConfig (from Python) is used whole.
    Every method shares the sampler; ``methods`` holds each method's own options. A level of
    ``variances`` is in the double integrator's units, scaled by the system's
    ``level_scale`` on its ``disturbed`` states. The robust controllers calibrate
    ``rule`` once per run on an undisturbed episode seeded with ``calibration_seed``.
    ``cost_rounds`` (>= 2) and ``cost_steps``: the cost pass, measured once per run after the
    episodes with none running, replays every method on the first ``cost_steps`` steps (at
    most ``steps``) of realisation 0 at the largest variance, kernels on one thread, methods in
    lock step, ``cost_rounds`` rounds (:mod:`workbench.study.cost_pass`); the order by cost
    comes from it.

    Size limits (checked here): at most 10^7 tasks per run, 10^7 steps per episode."""

    controllers: tuple[str, ...] = field(default_factory=names)  # every registered method
    variances: tuple[float, ...] = (10.0, 50.0, 100.0)
    realisations: int = 30
    steps: int = 1000
    seed: int = 2024
    goal_radius: float | None = None
    system: str = "double_integrator"
    scene: MapSpec | None = None
    family: MapFamily | None = None
    map_seed: int | None = None
    sampler: SamplerSettings | MPPIConfig | None = None
    q_beta: float | None = None
    robust: RMPPIConfig = RMPPIConfig()
    feedback: FeedbackWeights | None = None
    rule: AlphaRule = AlphaRule(kappa=0.1)
    methods: MethodSettings = field(default_factory=MethodSettings)
    calibration_seed: int = 0
    cost_rounds: int = 10
    cost_steps: int = 100

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
                             ("seed", 0, None), ("calibration_seed", 0, None),
                             ("cost_rounds", 2, 10_000), ("cost_steps", 1, MAX_STEPS)):
            object.__setattr__(self, name, integer(name, getattr(self, name), lo, hi))
        at_most("realisations", self.realisations,
                len(self.controllers) * len(self.variances) * self.realisations, MAX_TASKS,
                "controllers x variances x realisations (tasks of a run)")
        if self.goal_radius is not None:
            object.__setattr__(self, "goal_radius",
                               real("goal_radius", self.goal_radius, 0.0, strict=True))
        sysm = resolve_system(self.system)
        if self.scene is not None:
            if not isinstance(self.scene, MapSpec):
                raise fail("scene", self.scene, "must be a MapSpec or None")
            if sysm.scene is not None:
                raise fail("scene", self.scene, f"the system {sysm.name!r} runs on its own "
                           "start, goal and constraints; leave scene out")
            self.scene.check()
        if self.map_seed is not None:
            object.__setattr__(self, "map_seed", integer("map_seed", self.map_seed, 0))
        if self.family is not None:
            if not isinstance(self.family, MapFamily):
                raise fail("family", self.family, "must be a MapFamily or None")
            if self.scene is not None:
                raise fail("family", self.family.family, "give a scene or a map family, not "
                           "both")
            if sysm.scene is not None:
                raise fail("family", self.family.family, f"the system {sysm.name!r} runs on "
                           "its own start, goal and constraints; leave family out")
            if self.family.moving:
                raise fail("family", self.family.family, "this study runs on a static map: "
                           "use moving = 0 (moving obstacles run in the arena)")
            generate(self.family, self.map_seed or 0)  # a start or goal inside an obstacle
        elif self.map_seed is not None:
            raise fail("map_seed", self.map_seed, "selects a map of family; set family or "
                       "leave map_seed out")
        if not isinstance(self.sampler, SamplerSettings | MPPIConfig | None):
            raise fail("sampler", self.sampler, "must be a table of sampler settings, an "
                       "MPPIConfig or None")
        for name, kind in (("robust", RMPPIConfig), ("feedback", FeedbackWeights),
                           ("rule", AlphaRule), ("methods", MethodSettings)):
            v = getattr(self, name)
            if not isinstance(v, kind) and not (v is None and name == "feedback"):
                raise fail(name, v, f"must be a {kind.__name__}")
        self.resolved()  # the sampler over the system's: checked here, by MPPIConfig
        if self.q_beta is not None:
            object.__setattr__(self, "q_beta", real("q_beta", self.q_beta, 0.0))

    def as_dict(self) -> dict:
        return asdict(self)

    def resolved(self) -> Resolved:
        """The settings that run: every None replaced by the system's own value."""
        sysm = resolve_system(self.system)
        base = MPPIConfig(sigma=sysm.sigma, lam=sysm.lam, horizon=sysm.horizon)
        sampler = (base if self.sampler is None else self.sampler
                   if isinstance(self.sampler, MPPIConfig) else self.sampler.over(base))
        return Resolved(
            system=sysm.name, entry=self.system,
            scene=self.scene or (MapSpec() if sysm.scene is None and self.family is None
                                 else None),
            family=self.family, map_seed=self.map_seed or 0,
            sampler=sampler, q_beta=sysm.q_beta if self.q_beta is None else self.q_beta,
            robust=self.robust,
            feedback=sysm.feedback_weights if self.feedback is None else self.feedback,
            rule=self.rule, methods=self.methods,
            goal_radius=sysm.goal_radius if self.goal_radius is None else self.goal_radius)


@dataclass(frozen=True)
class Resolved:
    """A config's controller settings with the system's defaults filled in (hashable: the
    key of the per-process caches)."""

    system: str
    entry: str
    scene: MapSpec | None
    family: MapFamily | None
    map_seed: int
    sampler: MPPIConfig
    q_beta: float
    robust: RMPPIConfig
    feedback: FeedbackWeights
    rule: AlphaRule
    methods: MethodSettings
    goal_radius: float

"""Configuration of the arena: frozen, validated at construction (errors name the field)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from studies.arena.episodes import arena_system
from workbench.sampling.feedback import FeedbackWeights
from workbench.sampling.mppi import MPPIConfig
from workbench.sampling.robust import RMPPIConfig
from workbench.sampling.threshold import AlphaRule
from workbench.scenarios.maps import MapFamily, generate
from workbench.scenarios.methods import MethodSettings, names
from workbench.scenarios.systems import SYSTEMS, System
from workbench.sim import DISTURBANCE_MODELS, Disturbance
from workbench.study.tuning import TuningBudget
from workbench.validation import MAX_STEPS, MAX_TASKS, at_most, fail, integer, real

RESULT_VERSION = 2  # bump when the meaning of stored task results changes
TUNINGS = ("hand", "tuned")


def _names(field_name: str, values, allowed: tuple[str, ...], what: str) -> tuple[str, ...]:
    if isinstance(values, str) or not hasattr(values, "__iter__") or len(values) == 0:
        raise fail(field_name, values, f"must be a non-empty list of {what} from {allowed}")
    for v in values:
        if v not in allowed:
            raise fail(field_name, v, f"unknown {what}; allowed values are {allowed}")
    if len(set(values)) != len(values):
        raise fail(field_name, values, f"must not repeat a {what}")
    return tuple(a for a in allowed if a in values)


def _systems(values) -> tuple[str, ...]:
    """``systems``: registered names (in the registry's order) and entries (in the order
    given), each loaded here once (an entry's system is then registered in this process)."""
    what = (f"registered system names {tuple(SYSTEMS)} or entries 'module:function' / "
            "'path/file.py:function' returning a System (system_from_model)")
    if isinstance(values, str) or not hasattr(values, "__iter__") or len(values) == 0:
        raise fail("systems", values, f"must be a non-empty list of {what}")
    seen: dict[str, str] = {}
    for v in values:
        if not isinstance(v, str):
            raise fail("systems", v, f"must be one of the {what}")
        try:
            sysm: System = arena_system(v)
        except ValueError as exc:  # the loader's reason, without its own field name
            reason = str(exc).split(" is invalid: ", 1)[-1]
            if ":" not in v:
                reason = f"unknown system; allowed values are {what}"
            raise fail("systems", v, reason) from None
        except Exception as exc:  # an entry's own code failed while loading
            raise fail("systems", v, f"loading it raised {type(exc).__name__}: {exc}") from exc
        if sysm.name in seen:
            raise fail("systems", v, f"must not repeat a system: it is {sysm.name!r}, as "
                       f"{seen[sysm.name]!r} is")
        seen[sysm.name] = v
    return (tuple(a for a in SYSTEMS if a in values)
            + tuple(v for v in values if ":" in v))


@dataclass(frozen=True)
class DisturbanceSpec:
    """One disturbance of the arena: a :class:`~workbench.sim.Disturbance` ``model`` at
    ``level`` on ``states`` (empty: the system's default disturbed states). ``level`` is in the
    double integrator's units; each system scales it by its own ``level_scale`` (see
    :class:`~workbench.scenarios.systems.System`). The time-dependent types take
    ``start_step`` (impulse, step), ``duration`` (impulse) and ``frequency`` (periodic); a type
    that does not read one of these refuses a value for it. For them (and "uniform") ``level``
    is an acceleration on the disturbed states [m/s^2 on the double integrator's velocities].
    ``states`` (names or indices) must exist on every system of the run (checked by
    :class:`ArenaConfig`)."""

    model: str = "velocity_variance"
    level: float = 50.0
    states: tuple[str | int, ...] = ()
    start_step: int = 100
    duration: int = 20
    frequency: float = 0.5

    def __post_init__(self) -> None:
        if self.model not in DISTURBANCE_MODELS:
            raise fail("disturbances.model", self.model,
                       f"unknown disturbance type; allowed values are {DISTURBANCE_MODELS}")
        real("disturbances.level", self.level, 0.0)
        st = (self.states,) if isinstance(self.states, str | int) else self.states
        allowed = ("must be a list of distinct state names or indices >= 0 (empty: each "
                   "system's own disturbed states)")
        if not isinstance(st, tuple | list) or len(set(st)) != len(st):
            raise fail("disturbances.states", self.states, allowed)
        for x in st:
            if not (isinstance(x, str) and x) and not (
                    isinstance(x, int) and not isinstance(x, bool) and x >= 0):
                raise fail("disturbances.states", self.states, allowed)
        object.__setattr__(self, "states", tuple(st))
        integer("disturbances.start_step", self.start_step, 0, MAX_STEPS)
        integer("disturbances.duration", self.duration, 1, MAX_STEPS)
        real("disturbances.frequency", self.frequency, 0.0, strict=True)
        defaults = type(self).__dataclass_fields__
        for name, readers in _READ_BY.items():  # a value no row would use is refused
            if self.model not in readers and getattr(self, name) != defaults[name].default:
                raise fail(f"disturbances.{name}", getattr(self, name),
                           f"is not read by the disturbance type {self.model!r} (only by "
                           f"{' and '.join(readers)}); leave it out")

    @property
    def label(self) -> str:
        return self.disturbance(1.0, self.states or None).label

    def disturbance(self, scale: float, states: tuple[str, ...] | None) -> Disturbance:
        kw = {name: getattr(self, name) for name, readers in _READ_BY.items()
              if self.model in readers}
        return Disturbance(self.level * scale, self.model, states=self.states or states, **kw)

    def check_states(self, field_name: str, system: System) -> None:
        """Refuse states that ``system`` does not have, naming ``field_name`` and its states."""
        names = system.state_names
        for x in self.states:
            if (x not in names) if isinstance(x, str) else x >= len(names):
                raise fail(f"{field_name}.states", self.states,
                           f"the system {system.name!r} has no state {x!r}; its states are "
                           + ", ".join(f"{i}: {n!r}" for i, n in enumerate(names))
                           + " (a disturbance runs on every system of the run: name states "
                           "each has, or leave states out for each system's own)")


# the fields of a DisturbanceSpec beside model, level and states, and the types that read them
_READ_BY: dict[str, tuple[str, ...]] = {"start_step": ("impulse", "step"),
                                        "duration": ("impulse",), "frequency": ("periodic",)}


METRICS = ("safety", "success")  # paired binary outcomes a comparison may decide on


@dataclass(frozen=True)
class Comparison:
    """A declared comparison: ``first`` against ``second`` on ``metric`` ("safety": no crash;
    "success": the goal reached without a crash), in every (system, disturbance, tuning) of
    the run, or in those listed (``systems``, ``disturbances`` by label, ``tunings``). Each
    combination is one comparison of the family over which the error rates are kept."""

    first: str
    second: str
    metric: str = "safety"
    systems: tuple[str, ...] = ()
    disturbances: tuple[str, ...] = ()
    tunings: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        for name in ("first", "second"):
            if getattr(self, name) not in names():
                raise fail(f"comparisons.{name}", getattr(self, name),
                           f"unknown controller; allowed values are {names()}")
        if self.first == self.second:
            raise fail("comparisons.second", self.second, "must differ from first")
        if self.metric not in METRICS:
            raise fail("comparisons.metric", self.metric, f"must be one of {METRICS}")
        for name in ("systems", "disturbances", "tunings"):
            v = getattr(self, name)
            if isinstance(v, str):
                v = (v,)
            if not isinstance(v, tuple | list) or not all(isinstance(x, str) for x in v):
                raise fail(f"comparisons.{name}", v, "must be a list of names")
            object.__setattr__(self, name, tuple(v))


@dataclass(frozen=True)
class DecisionSettings:
    """How the declared comparisons are decided (group-sequential, see
    :mod:`studies.arena.decisions`): ``margin`` is the smallest difference that matters (and
    the equivalence margin), ``alpha`` the family-wise error rate over every declared
    comparison, ``power`` the power planned at ``margin`` given the assumed share of
    discordant pairs ``discordance``; ``rounds`` is the number of looks: each round adds
    ``test_maps`` new maps of every family with ``realisations`` each, for the comparisons
    still undecided."""

    margin: float = 0.10
    alpha: float = 0.05
    power: float = 0.80
    discordance: float = 0.35
    rounds: int = 1

    def __post_init__(self) -> None:
        for name, lo, hi in (("margin", 0.0, 1.0), ("alpha", 0.0, 0.5), ("power", 0.5, 1.0),
                             ("discordance", 0.0, 1.0)):
            v = real(f"decision.{name}", getattr(self, name), lo, strict=True)
            if v >= hi:
                raise fail(f"decision.{name}", v, f"must lie in ({lo:g}, {hi:g})")
            object.__setattr__(self, name, v)
        object.__setattr__(self, "rounds", integer("decision.rounds", self.rounds, 1, 50))


@dataclass(frozen=True)
class ArenaConfig:
    """Cells: every controller x system x test map x disturbance, ``realisations`` episodes
    each, with the hand-tuned settings and/or the shipped tuned ones (``tunings``).

    ``systems``: registered names (``workbench list``) and your own systems as entries
    ``"path/file.py:function"`` or ``"module:function"`` returning a System
    (:func:`~workbench.scenarios.model_system.system_from_model`); each worker process loads an
    entry itself.

    Maps: ``test_maps`` maps of each family in ``families`` with seeds from ``test_seed``
    on (the tuning runs use ``tuning_maps`` maps from ``tuning_seed`` on: the ranges must not
    overlap). Common random numbers: realisation j of a (system, map, disturbance) gives every
    controller and tuning the same plant and sampler streams. An episode ends at a crash, at
    the goal (within ``goal_radius``, scaled by the system) or after ``steps`` steps.

    A system built from a model runs on its own scene (start, goal, constraints), never on a
    generated map; its map seeds only select the random streams, so each round still draws new
    disturbances (assumptions §12.4). A run with such a system takes one static map family
    (the built-in systems' maps; when every system has its own scene, only the default one),
    and such a system uses its own goal radius (``System.goal_radius``, in its own distance to
    the goal), not ``goal_radius`` (map units); tuned values do not exist for it."""

    controllers: tuple[str, ...] = ("bas_mppi", "sa_rmppi")
    systems: tuple[str, ...] = ("double_integrator", "unicycle")
    families: tuple[MapFamily, ...] = (MapFamily("spec"),)
    test_maps: int = 3
    test_seed: int = 1000
    disturbances: tuple[DisturbanceSpec, ...] = (DisturbanceSpec(),)
    realisations: int = 4
    tunings: tuple[str, ...] = ("hand",)
    steps: int = 1000
    goal_radius: float = 0.5
    seed: int = 2026
    sampler: MPPIConfig = MPPIConfig()
    robust: RMPPIConfig = RMPPIConfig()
    feedback: FeedbackWeights | None = None  # None: each system's own weights
    rule: AlphaRule = AlphaRule(kappa=0.1)
    methods: MethodSettings = field(default_factory=MethodSettings)
    calibration_seed: int = 0
    tuning: TuningBudget = field(default_factory=TuningBudget)
    tuning_maps: int = 4
    tuning_seed: int = 0
    validation_maps: int = 4  # the tuning runs' held-out maps, seeds from validation_seed on;
    validation_seed: int = 500  # no two of the test, tuning and validation ranges may overlap
    tuning_disturbance: DisturbanceSpec = field(default_factory=DisturbanceSpec)
    comparisons: tuple[Comparison, ...] = ()  # empty: claim (i), when both ran
    decision: DecisionSettings = field(default_factory=DecisionSettings)

    def __post_init__(self) -> None:
        object.__setattr__(self, "controllers",
                           _names("controllers", self.controllers, names(), "controller"))
        object.__setattr__(self, "systems", _systems(self.systems))
        object.__setattr__(self, "tunings", _names("tunings", self.tunings, TUNINGS, "tuning"))
        for name, kind in (("families", MapFamily), ("disturbances", DisturbanceSpec)):
            v = getattr(self, name)
            if isinstance(v, kind) or not hasattr(v, "__iter__") or not v:
                raise fail(name, v, f"must be a non-empty list of {kind.__name__}")
            for i, x in enumerate(v):
                if not isinstance(x, kind):
                    raise fail(f"{name}[{i}]", x, f"must be a {kind.__name__}")
            object.__setattr__(self, name, tuple(v))
        if len({f.family for f in self.families}) != len(self.families):
            raise fail("families", [f.family for f in self.families],
                       "one entry per map family")
        labels = [d.label for d in self.disturbances]
        if len(set(labels)) != len(labels):
            raise fail("disturbances", labels, "must not repeat a disturbance")
        for name, lo in (("test_maps", 1), ("test_seed", 0), ("realisations", 1), ("steps", 1),
                         ("seed", 0), ("calibration_seed", 0), ("tuning_maps", 1),
                         ("tuning_seed", 0), ("validation_maps", 1), ("validation_seed", 0)):
            object.__setattr__(self, name, integer(name, getattr(self, name), lo))
        for name in ("test_maps", "realisations", "tuning_maps", "validation_maps", "steps"):
            at_most(name, getattr(self, name), getattr(self, name), MAX_STEPS, name)
        at_most("realisations", self.realisations, len(self.controllers) * len(self.systems)
                * len(self.families) * self.test_maps * len(self.disturbances)
                * len(self.tunings) * self.realisations, MAX_TASKS, "the number of episodes")
        if not isinstance(self.decision, DecisionSettings):
            raise fail("decision", self.decision, "must be a DecisionSettings")
        self._check_comparisons()
        seeds = {"test": self.map_seeds(), "tuning": self.tuning_seeds(),
                 "validation": self.validation_seeds()}
        for name, a, b in (("test_seed", "test", "tuning"),
                           ("validation_seed", "validation", "tuning"),
                           ("validation_seed", "validation", "test")):
            if set(seeds[a]) & set(seeds[b]):
                raise fail(name, getattr(self, name),
                           f"{a} maps {min(seeds[a])}..{max(seeds[a])} overlap the {b} maps "
                           f"{min(seeds[b])}..{max(seeds[b])}; the seed ranges must be disjoint")
        if self.feedback is not None and not isinstance(self.feedback, FeedbackWeights):
            raise fail("feedback", self.feedback, "must be a FeedbackWeights or None")
        real("goal_radius", self.goal_radius, 0.0, strict=True)
        self._check_own_scenes()
        for f in self.families:  # a start or goal inside a generated obstacle fails here
            generate(f, self.test_seed)
        for name, kind in (("sampler", MPPIConfig), ("robust", RMPPIConfig),
                           ("rule", AlphaRule),
                           ("methods", MethodSettings), ("tuning", TuningBudget),
                           ("tuning_disturbance", DisturbanceSpec)):
            if not isinstance(getattr(self, name), kind):
                raise fail(name, getattr(self, name), f"must be a {kind.__name__}")
        for sname in self.systems:  # every disturbance's states exist on every system
            sysm = arena_system(sname)
            for i, d in enumerate(self.disturbances):
                d.check_states(f"disturbances[{i}]", sysm)
            self.tuning_disturbance.check_states("tuning_disturbance", sysm)
        default = MPPIConfig()
        for name in ("sigma", "lam"):  # each system's own (hand) or its tuned value runs
            if getattr(self.sampler, name) != getattr(default, name):
                raise fail(f"sampler.{name}", getattr(self.sampler, name),
                           "is set per system in the arena: the hand-tuned rows use each "
                           "system's own value and the tuned rows the shipped tuned one; "
                           "leave it out (or compare your values with the sampling-safety "
                           "study, whose [sampler] table applies them)")

    def _check_own_scenes(self) -> None:
        """The rules for systems with a scene of their own (assumptions §12.4): no tuned
        values, one static map family, and no family or goal radius that nothing would use."""
        own = [s for s in self.systems if arena_system(s).scene is not None]
        user = [s for s in self.systems if ":" in s or s in own]
        if "tuned" in self.tunings and user:
            raise fail("tunings", "tuned", f"no tuned values exist for the system {user[0]!r} "
                       "(tuned values are shipped for the built-in systems only); use "
                       "tunings = [\"hand\"]")
        if not own:
            return
        fams = [f.family for f in self.families]
        why = (f"the system {own[0]!r} runs on its own scene, not on generated maps (its map "
               "seeds only select the random streams)")
        if len(self.families) != 1 or self.families[0].moving:
            raise fail("families", fams, f"{why}: a run with it takes one static map family "
                       "(for the built-in systems of the run); run other families or moving "
                       "obstacles in a run without it")
        if len(own) == len(self.systems):
            if self.families[0] != MapFamily():
                raise fail("families", self.families[0], f"{why}, and so does every system "
                           "of this run: no system would use this map family; leave "
                           "families out")
            default = type(self).__dataclass_fields__["goal_radius"].default
            if self.goal_radius != default:
                raise fail("goal_radius", self.goal_radius, f"{why}, and so does every system "
                           "of this run: each uses its own goal radius (System.goal_radius, "
                           "system_from_model(goal_radius=...)), so this map-unit radius "
                           f"would be used by none; leave it out (default {default:g})")

    def _check_comparisons(self) -> None:
        v = self.comparisons
        if isinstance(v, Comparison) or not isinstance(v, tuple | list):
            raise fail("comparisons", v, "must be a list of Comparison")
        object.__setattr__(self, "comparisons", tuple(v))
        labels = [d.label for d in self.disturbances]
        for i, c in enumerate(self.comparisons):
            if not isinstance(c, Comparison):
                raise fail(f"comparisons[{i}]", c, "must be a Comparison")
            for name in ("first", "second"):
                if getattr(c, name) not in self.controllers:
                    raise fail(f"comparisons[{i}].{name}", getattr(c, name),
                               f"is not among the run's controllers {self.controllers}")
            for name, allowed in (("systems", self.systems), ("disturbances", labels),
                                  ("tunings", self.tunings)):
                for x in getattr(c, name):
                    if x not in allowed:
                        raise fail(f"comparisons[{i}].{name}", x,
                                   f"is not in the run; allowed values are {tuple(allowed)}")

    def map_seeds(self) -> tuple[int, ...]:
        """The test maps' seeds of every round (round r: ``test_maps`` seeds from
        ``test_seed + r * test_maps``)."""
        return tuple(range(self.test_seed,
                           self.test_seed + self.test_maps * self.decision.rounds))

    def round_seeds(self, r: int) -> tuple[int, ...]:
        start = self.test_seed + r * self.test_maps
        return tuple(range(start, start + self.test_maps))

    def round_of(self, seed: int) -> int:
        return (seed - self.test_seed) // self.test_maps

    def tuning_seeds(self) -> tuple[int, ...]:
        return tuple(range(self.tuning_seed, self.tuning_seed + self.tuning_maps))

    def validation_seeds(self) -> tuple[int, ...]:
        return tuple(range(self.validation_seed, self.validation_seed + self.validation_maps))

    def as_dict(self) -> dict:
        return asdict(self)

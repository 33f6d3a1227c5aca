"""What a safe-sampling method is to the workbench, declared once: :class:`MethodSpec`, and the
registry every list of methods is read from (the command line's ``workbench list``, the
studies' configs, task order and plot markers, the tuner's search spaces, the tests).

A method is added by writing its module (the controller and one :class:`MethodSpec`) and one
registry line (:func:`register`, or an entry of the built-in catalogue). Names are kept in
registration order; that order is the order of every table and figure.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from workbench.filters.ecbf import unreached_margins
from workbench.registry import Registry
from workbench.sim import Controller
from workbench.study.tuning import Param
from workbench.validation import fail

if TYPE_CHECKING:
    from workbench.scenarios.navigation import NavigationSetup

# What a method may require of a system, each with the question asked of a navigation set-up
# (None: satisfied, else why not).
REQUIREMENTS: dict[str, str] = {
    "margins": "constraint margins h(x) (a barrier state or a crash rule is built from them)",
    "tracking": "tracking weights sized for the model (System.feedback_weights)",
    "relative_degree": "every margin reached by the controls within two steps (relative "
                       "degree 1 or 2, the ECBF rows' orders)",
}


@dataclass(frozen=True)
class MethodSpec:
    """One safe-sampling method.

    ``name``: its key (lower case, digits and ``_``); ``label``: its name in reports;
    ``mechanism``: what makes it safe, in a few words; ``build(setup, settings, **robust)``:
    the controller on a :class:`~workbench.scenarios.navigation.NavigationSetup` (robust
    methods also receive ``threshold``, ``robust`` and ``weights``); ``marker``: its matplotlib
    marker; ``feedback``: the feedback law of a robust method (``"bas_ilqg"``, ``"ilqg"``,
    ``"al_ilqg"``, ``"ecbf"``; None for the others; a robust method calibrates a selection
    threshold with it); ``options``: its options dataclass (None: none) and
    ``options_key``: where :class:`~workbench.scenarios.methods.settings.MethodSettings` keeps
    them (a field of it for the built-in methods, else the method's name); ``tunable``: its
    own tuned parameters, named ``"<options_key>.<field>"`` (the sampler's sigma scale and
    lambda, and kappa for robust methods, are tuned for every method); ``activity``: the key of
    :attr:`~workbench.sampling.step_stats.StepStats.activity` that says its mechanism acted
    (None: a method without a separate mechanism); ``requires``: keys of :data:`REQUIREMENTS`;
    ``cost_rank``: the order in which studies dispatch its tasks, slowest first (rank 0 first;
    measured per step on the navigation map, N = 1024, T = 100, one thread); ``wraps``: the
    registered method it adds its mechanism to (the same sampler without the mechanism: the
    controller it must not be less safe than), None for a baseline.
    """

    name: str
    label: str
    mechanism: str
    build: Callable[..., Controller]
    marker: str
    feedback: str | None = None
    options: type | None = None
    options_key: str | None = None
    tunable: tuple[Param, ...] = ()
    activity: str | None = None
    requires: tuple[str, ...] = ("margins",)
    cost_rank: int = 0
    wraps: str | None = None

    def __post_init__(self) -> None:
        n = self.name
        if not (isinstance(n, str) and n and n[0].isalpha()
                and all(c.islower() or c.isdigit() or c == "_" for c in n)):
            raise fail("MethodSpec.name", n, "must be lower case letters, digits and _, "
                       "starting with a letter")
        for f in ("label", "mechanism", "marker"):
            if not isinstance(getattr(self, f), str) or not getattr(self, f):
                raise fail(f"MethodSpec({n}).{f}", getattr(self, f), "must be a non-empty string")
        if not callable(self.build):
            raise fail(f"MethodSpec({n}).build", self.build, "must be callable")
        if self.feedback is not None and self.feedback not in FEEDBACK_LAWS:
            raise fail(f"MethodSpec({n}).feedback", self.feedback,
                       f"must be None or one of {FEEDBACK_LAWS}")
        if self.options is not None and not isinstance(self.options, type):
            raise fail(f"MethodSpec({n}).options", self.options, "must be a dataclass type")
        if self.options_key is not None and self.options is None:
            raise fail(f"MethodSpec({n}).options_key", self.options_key,
                       "needs options (the dataclass it names)")
        key = self.key
        for p in self.tunable:
            if not isinstance(p, Param):
                raise fail(f"MethodSpec({n}).tunable", p, "must be Param entries")
            group, _, field_name = p.name.partition(".")
            if self.options is None or group != key or not hasattr(self.options(), field_name):
                raise fail(f"MethodSpec({n}).tunable", p.name,
                           f"must name a field of its options as '{key}.<field>'")
        for r in self.requires:
            if r not in REQUIREMENTS:
                raise fail(f"MethodSpec({n}).requires", r, f"must be one of {tuple(REQUIREMENTS)}")
        if not isinstance(self.cost_rank, int) or isinstance(self.cost_rank, bool):
            raise fail(f"MethodSpec({n}).cost_rank", self.cost_rank, "must be an integer")
        if self.wraps is not None and (not isinstance(self.wraps, str) or self.wraps == n):
            raise fail(f"MethodSpec({n}).wraps", self.wraps,
                       "must be None or the name of another method")

    @property
    def robust(self) -> bool:
        """Robust MPPI with a feedback law: it needs a calibrated selection threshold."""
        return self.feedback is not None

    @property
    def key(self) -> str:
        """Where the method's options live in MethodSettings."""
        return self.options_key or self.name

    def missing(self, setup: NavigationSetup, weights=None) -> str | None:
        """Why this method cannot run on ``setup`` with tracking ``weights`` (default: the
        system's); None when it can."""
        sysm, plant = setup.system, setup.plant
        if "margins" in self.requires and plant.nh == 0:
            return f"{self.name} needs {REQUIREMENTS['margins']}; {plant.name} has none"
        if "tracking" in self.requires:
            w = sysm.feedback_weights if weights is None else weights
            nx, nu = len(w.Q), len(w.R)
            if (nx, nu) != (plant.nx, plant.nu):
                return (f"{self.name} needs {REQUIREMENTS['tracking']}: the weights are "
                        f"sized for {nx} states and {nu} controls, the plant "
                        f"{plant.name!r} has {plant.nx} and {plant.nu}")
        if "relative_degree" in self.requires and plant.nh:
            far = unreached_margins(plant)
            if far:
                return (f"{self.name} needs {REQUIREMENTS['relative_degree']}; the controls "
                        f"of {plant.name!r} do not reach margins {list(far)} within two steps "
                        "(use a method whose discrete CBF has higher order, e.g. "
                        "cbf_projection or shield_mppi, or write h so that u reaches it)")
        return None


FEEDBACK_LAWS = ("bas_ilqg", "ilqg", "al_ilqg", "ecbf")

_REGISTRY: Registry[MethodSpec] = Registry("method", MethodSpec, lookup_field="controller",
                                           arg_field="spec", name_field="spec.name")


def register(spec: MethodSpec) -> MethodSpec:
    """Add ``spec`` to the registry (its name must be new, and the method it ``wraps``
    registered before it); returns it."""
    if spec.wraps is not None and spec.wraps not in _REGISTRY:
        raise fail(f"MethodSpec({spec.name}).wraps", spec.wraps,
                   f"must name a registered method; registered: {tuple(_REGISTRY)}")
    return _REGISTRY.register(spec)


def unregister(name: str) -> MethodSpec:
    """Remove the method ``name`` (e.g. a test's own); returns its spec."""
    return _REGISTRY.unregister(name)


def method(name: str) -> MethodSpec:
    """The registered method ``name``; an unknown name is a ValueError naming the known ones."""
    return _REGISTRY.named(name)


def methods() -> tuple[MethodSpec, ...]:
    """Every registered method, in registration order."""
    return tuple(_REGISTRY.values())


def names() -> tuple[str, ...]:
    """The registered method names, in registration order."""
    return tuple(_REGISTRY)


def robust_names() -> tuple[str, ...]:
    """The robust methods (those with a feedback law), in registration order."""
    return tuple(s.name for s in _REGISTRY.values() if s.robust)


def slowest_first() -> tuple[str, ...]:
    """The method names by cost rank (slowest first), ties in registration order (a stable
    sort of the registration order)."""
    return tuple(sorted(_REGISTRY, key=lambda n: _REGISTRY[n].cost_rank))


def labels() -> dict[str, str]:
    """Report label by method name."""
    return {s.name: s.label for s in _REGISTRY.values()}


def markers() -> dict[str, str]:
    """Plot marker by method name."""
    return {s.name: s.marker for s in _REGISTRY.values()}

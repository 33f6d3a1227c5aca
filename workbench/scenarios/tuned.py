"""What automatic tuning may change per controller, how tuned values enter a controller's
settings, and the tuned defaults shipped for each (controller, system) pair.

Every controller tunes the sampler's exploration and temperature (``sigma_scale`` multiplies
the system's per-control sigma; ``lam``); the robust ones also the alpha rule's ``kappa``; a
method with a gain of its own tunes that gain too. The barrier-state weight ``q_beta`` is not
tuned: it is compiled into the sampling kernels, so each value would cost a compile.

The shipped defaults (``tuned.json`` beside this module) are written by the arena's tuning run
(``make tune-arena``) with the budget and objective they were tuned under;
:func:`shipped` reads them.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from functools import cache
from pathlib import Path

from workbench.sampling.mppi import MPPIConfig
from workbench.sampling.threshold import AlphaRule
from workbench.scenarios.methods import MethodSettings, method
from workbench.study.tuning import Param, TuningBudget
from workbench.validation import fail

SHIPPED = Path(__file__).with_name("tuned.json")

COMMON = (Param("sigma_scale", 0.25, 4.0), Param("lam", 0.3, 100.0))
KAPPA = Param("kappa", 0.01, 1.0)


def space(controller: str) -> tuple[Param, ...]:
    """The parameters tuning may change for ``controller``: :data:`COMMON`, :data:`KAPPA` for
    a robust method, and the method's own (:attr:`MethodSpec.tunable`)."""
    spec = method(controller)
    return COMMON + ((KAPPA,) if spec.robust else ()) + spec.tunable


@dataclass(frozen=True)
class ControllerSettings:
    """A controller's settings on one system: the sampler, the barrier-state weight, the
    alpha rule (robust controllers) and each method's own options."""

    sampler: MPPIConfig
    q_beta: float
    rule: AlphaRule
    methods: MethodSettings

    def values(self, controller: str) -> dict[str, float]:
        """The current values of ``space(controller)`` (sigma_scale relative to ``base``
        sigma is 1 by definition: the hand-tuned point)."""
        spec = method(controller)
        out = {"sigma_scale": 1.0, "lam": float(self.sampler.lam)}
        if spec.robust:
            out["kappa"] = float(self.rule.kappa)
        for p in spec.tunable:
            out[p.name] = float(getattr(self.methods.options(spec), p.name.split(".")[1]))
        return out

    def with_values(self, controller: str, params: dict[str, float]) -> ControllerSettings:
        """These settings with tuned ``params`` (names of ``space(controller)``) applied."""
        allowed = {p.name: p for p in space(controller)}
        for k, v in params.items():
            if k not in allowed:
                raise fail("params", k, f"is not tuned for {controller}; allowed {list(allowed)}")
            if not allowed[k].contains(float(v)):
                raise fail(f"params.{k}", v, f"must lie in [{allowed[k].low:g}, "
                           f"{allowed[k].high:g}]")
        s = self.sampler
        sampler = dataclasses.replace(
            s, sigma=tuple(params.get("sigma_scale", 1.0) * v for v in s.sigma),
            lam=float(params.get("lam", s.lam)))
        rule = (dataclasses.replace(self.rule, kappa=float(params["kappa"]))
                if "kappa" in params else self.rule)
        methods, spec = self.methods, method(controller)
        for k, v in params.items():
            if "." in k:
                name = k.split(".")[1]
                sub = methods.options(spec)  # the method's own options
                value = round(v) if isinstance(getattr(sub, name), int) else float(v)
                methods = methods.with_options(spec, dataclasses.replace(sub, **{name: value}))
        return ControllerSettings(sampler, self.q_beta, rule, methods)


@dataclass(frozen=True)
class Tuned:
    """Tuned parameters of one (system, controller) pair: the values, the training score and
    the hand-tuned start's score under the same objective, the budget, the objective and the
    training maps."""

    system: str
    controller: str
    params: dict[str, float]
    score: float
    start_score: float
    budget: TuningBudget
    objective: str
    training: str

    def as_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["budget"] = dataclasses.asdict(self.budget)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> Tuned:
        def num(v) -> float:  # strict JSON writes a non-finite score as null
            return float("nan") if v is None else float(v)

        return cls(d["system"], d["controller"], {k: float(v) for k, v in d["params"].items()},
                   num(d["score"]), num(d["start_score"]), TuningBudget(**d["budget"]),
                   d["objective"], d["training"])


@cache
def _read(path: Path) -> dict[tuple[str, str], Tuned]:
    if not path.exists():
        return {}
    entries = json.loads(path.read_text(encoding="utf-8"))["tuned"]
    return {(e["system"], e["controller"]): Tuned.from_dict(e) for e in entries}


def shipped(path: Path | None = None) -> dict[tuple[str, str], Tuned]:
    """The shipped tuned defaults by (system, controller) ({} when none are shipped)."""
    return dict(_read(Path(path or SHIPPED)))


def tuned(system: str, controller: str, path: Path | None = None) -> Tuned | None:
    """The shipped tuned parameters of (``system``, ``controller``), or None."""
    return _read(Path(path or SHIPPED)).get((system, controller))

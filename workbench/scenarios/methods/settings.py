"""Each method's own options as one frozen config (the sampler settings are the set-up's)."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from workbench.filters.ecbf import ECBFOptions
from workbench.sampling.feedback.al import ALFeedbackOptions
from workbench.sampling.methods.cbf_projection import CBFProjectionConfig
from workbench.sampling.methods.gatekeeper import GatekeeperConfig
from workbench.sampling.methods.shield import ShieldConfig
from workbench.sampling.methods.tube import TubeConfig
from workbench.scenarios.methods.spec import MethodSpec, method, methods
from workbench.study.config_io import load
from workbench.validation import fail


def _options_type(f: dataclasses.Field[Any]) -> type | None:
    """The type of a method-options field: that of its default_factory's value (None: the
    field has no default_factory, so it holds no method's options)."""
    factory = f.default_factory
    return type(factory()) if callable(factory) else None


@dataclass(frozen=True)
class MethodSettings:
    """Each method's own options: one field per built-in method's options (config files set
    them as ``methods.<field>.<option>``), ``braking_gain`` of the gatekeeper's backup, and
    ``extra``: the options of methods registered at run time, as (method name, options) pairs
    (a table of options per name in a config file, read into the method's options type)."""

    tube: TubeConfig = field(default_factory=TubeConfig)
    cbf_projection: CBFProjectionConfig = field(default_factory=CBFProjectionConfig)
    shield: ShieldConfig = field(default_factory=ShieldConfig)
    gatekeeper: GatekeeperConfig = field(default_factory=GatekeeperConfig)
    # [A] the backup's u = -gain v (clipped); None: 1/dt, which stops each axis within 50
    # steps from 5 m/s, inside the gatekeeper's 60-step horizon. Other systems: the gain of
    # their own backup law (System.backup; the bicycle brakes a = -gain v, the quadrotor's
    # hover law uses it as its velocity gain, the unicycle's stop ignores it)
    braking_gain: float | None = None
    al: ALFeedbackOptions = field(default_factory=ALFeedbackOptions)
    ecbf: ECBFOptions = field(default_factory=ECBFOptions)
    extra: tuple[tuple[str, Any], ...] | None = None

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            if f.name in ("braking_gain", "extra"):
                continue
            kind = _options_type(f)
            if kind is None:
                raise TypeError(f"MethodSettings.{f.name} has no default_factory: a method's "
                                "options field is built by its options type")
            if not isinstance(getattr(self, f.name), kind):
                raise fail(f"methods.{f.name}", getattr(self, f.name),
                           f"must be a {kind.__name__}")
        g = self.braking_gain
        if g is not None and not (isinstance(g, int | float) and not isinstance(g, bool)
                                  and np.isfinite(g) and g > 0):
            raise fail("methods.braking_gain", g, "must be a finite number > 0 (or left out: "
                       "1/dt)")
        if self.extra is not None:
            object.__setattr__(self, "extra", self._read_extra(self.extra))

    @staticmethod
    def _read_extra(extra) -> tuple[tuple[str, Any], ...]:
        if not isinstance(extra, tuple | list):
            raise fail("methods.extra", extra, "must be a list of (method name, options) pairs")
        out: dict[str, Any] = {}
        for i, item in enumerate(extra):
            if not (isinstance(item, tuple | list) and len(item) == 2):
                raise fail(f"methods.extra[{i}]", item, "must be a (method name, options) pair")
            name, opts = item
            spec = method(name)
            if spec.options is None or spec.options_key is not None:
                raise fail(f"methods.extra[{i}]", name, "is not a method registered at run time "
                           "with options (built-in methods have their own field)")
            if name in out:
                raise fail(f"methods.extra[{i}]", name, "appears twice")
            if isinstance(opts, Mapping):
                opts = load(spec.options, opts, path=f"methods.extra.{name}.")
            if not isinstance(opts, spec.options):
                raise fail(f"methods.extra.{name}", opts, f"must be a {spec.options.__name__}")
            out[name] = opts
        return tuple(out.items())

    def options(self, spec: MethodSpec | str) -> Any:
        """The options of method ``spec`` (its own defaults when none were set; None for a
        method without options)."""
        spec = method(spec) if isinstance(spec, str) else spec
        if spec.options is None:
            return None
        if spec.options_key is not None:
            return getattr(self, spec.options_key)
        return dict(self.extra or ()).get(spec.name, spec.options())

    def with_options(self, spec: MethodSpec | str, options: Any) -> MethodSettings:
        """These settings with method ``spec``'s options replaced by ``options``."""
        spec = method(spec) if isinstance(spec, str) else spec
        if spec.options is None or not isinstance(options, spec.options):
            raise fail(f"methods.{spec.key}", options,
                       f"must be a {getattr(spec.options, '__name__', 'None')}")
        if spec.options_key is not None:
            changes: dict[str, Any] = {spec.options_key: options}
            return dataclasses.replace(self, **changes)
        extra = dict(self.extra or ())
        extra[spec.name] = options
        return dataclasses.replace(self, extra=tuple(extra.items()))


def _unset_extra_left_out(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    if [k for k, _ in pairs] == _FIELDS and dict(pairs)["extra"] is None:
        pairs = [(k, v) for k, v in pairs if k != "extra"]
    return dict(pairs)


_FIELDS = [f.name for f in dataclasses.fields(MethodSettings)]


def fingerprint(value: Any) -> dict[str, Any]:
    """``dataclasses.asdict(value)`` with every MethodSettings' ``extra`` left out while it is
    unset: a study's fingerprint, and so its task ids, are those of a workbench without
    run-time methods until one has options."""
    return dataclasses.asdict(value, dict_factory=_unset_extra_left_out)


def check_fields() -> None:
    """Every built-in method's ``options_key`` names a field of MethodSettings of its type."""
    fields = {f.name: f for f in dataclasses.fields(MethodSettings)}
    for s in methods():
        if s.options_key is not None:
            f = fields.get(s.options_key)
            if f is None or _options_type(f) is not s.options:
                raise fail(f"MethodSpec({s.name}).options_key", s.options_key,
                           "must name a field of MethodSettings holding its options type")

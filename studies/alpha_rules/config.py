"""Configuration of the alpha-rule study: frozen, validated (errors name the field)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workbench.validation import fail


@dataclass(frozen=True)
class AlphaRulesConfig:
    """episodes per (controller, rule, variance) cell; steps per episode (dt = 0.02 s); root
    seed; plant velocity-disturbance variances (SPEC 2.3)."""

    profile: str = "quick"
    episodes: int = 20
    steps: int = 1000
    seed: int = 2026
    variances: tuple[float, ...] = (10.0, 100.0)

    def __post_init__(self) -> None:
        if not isinstance(self.profile, str) or not self.profile:
            raise fail("profile", self.profile, "must be a non-empty string")
        for name, low in (("episodes", 1), ("steps", 1), ("seed", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < low:
                raise fail(name, v, f"must be an integer >= {low}")
        v = self.variances
        if isinstance(v, str) or not hasattr(v, "__iter__") or len(v) == 0:
            raise fail("variances", v, "must be a non-empty list of numbers >= 0")
        for i, x in enumerate(v):
            if isinstance(x, bool) or not isinstance(x, int | float) or not np.isfinite(x) \
                    or x < 0:
                raise fail(f"variances[{i}]", x, "must be a finite number >= 0")
        object.__setattr__(self, "variances", tuple(float(x) for x in v))

"""Configuration of the BaS-iLQG tracking demo: frozen, validated (errors name the field)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workbench.validation import fail


@dataclass(frozen=True)
class DemoConfig:
    """profile: a label for the report; q_betas: the barrier-state weights solved, one BaS-iLQG
    run (checked against IPOPT) each."""

    profile: str = "quick"
    q_betas: tuple[float, ...] = (1e-2,)

    def __post_init__(self) -> None:
        if not isinstance(self.profile, str) or not self.profile:
            raise fail("profile", self.profile, "must be a non-empty string")
        q = self.q_betas
        if isinstance(q, str) or not hasattr(q, "__iter__") or len(q) == 0:
            raise fail("q_betas", q, "must be a non-empty list of numbers >= 0")
        for i, v in enumerate(q):
            if isinstance(v, bool) or not isinstance(v, int | float) or not np.isfinite(v) \
                    or v < 0:
                raise fail(f"q_betas[{i}]", v, "must be a finite number >= 0")
        object.__setattr__(self, "q_betas", tuple(float(v) for v in q))

"""Configuration of the BaS-iLQG tracking demo: frozen, validated (errors name the field)."""

from __future__ import annotations

from dataclasses import dataclass

from workbench.validation import fail, integer, real


@dataclass(frozen=True)
class DemoConfig:
    """q_betas: the barrier-state weights solved, one BaS-iLQG run (checked against IPOPT) each;
    seed: the root seed of the framework (the solves draw nothing)."""

    q_betas: tuple[float, ...] = (1e-2,)
    seed: int = 0

    def __post_init__(self) -> None:
        q = self.q_betas
        if isinstance(q, str) or not hasattr(q, "__iter__") or len(q) == 0:
            raise fail("q_betas", q, "must be a non-empty list of numbers >= 0")
        values = tuple(real(f"q_betas[{i}]", v, 0.0) for i, v in enumerate(q))
        if len(set(values)) != len(values):
            raise fail("q_betas", q, "must not repeat a value")
        object.__setattr__(self, "q_betas", values)
        object.__setattr__(self, "seed", integer("seed", self.seed, 0))

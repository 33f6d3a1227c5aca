"""What a sampling controller's step did with its samples, the same for every method.

Every controller's step info exposes ``stats`` (a :class:`StepStats`): how many samples the
update was weighted over, how many of them were collision-free, the effective sample size of
those weights, and ``activity`` — how often each safety mechanism of the method acted in this
step (a projection, a shield repair, a backup control, a nominal reset, ...), as numbers in
[0, 1] (a fraction of samples or sample-steps, or 0/1 for a per-step event). A mechanism that
never acts shows up as an activity of 0, which is how a method that runs but does nothing is
caught (:mod:`workbench.scenarios.mechanism_health`).

The samples themselves are the info's ``samples``: None unless the controller records them
(``ctrl.record_samples(k)``, :mod:`workbench.sampling.samples`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

from workbench.validation import fail


@dataclass(frozen=True)
class StepStats:
    """Sample statistics of one control step (see module docstring)."""

    n_samples: int
    n_collision_free: int
    ess: float
    activity: Mapping[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not 0 <= self.n_collision_free <= self.n_samples:
            raise fail("StepStats.n_collision_free", self.n_collision_free,
                       f"must lie in [0, n_samples = {self.n_samples}]")
        object.__setattr__(self, "activity", MappingProxyType(dict(self.activity)))

    @property
    def collision_free_fraction(self) -> float:
        return self.n_collision_free / self.n_samples if self.n_samples else float("nan")

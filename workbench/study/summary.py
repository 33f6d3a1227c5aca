"""Typed summary building blocks: a binomial rate with its Wilson interval, a spread of values,
and JSON conversion of summary dataclasses. A study defines each metric once (a function of its
tidy table) and builds its own frozen summary dataclasses from these."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from numbers import Integral
from typing import Any

import numpy as np

from workbench.study.stats import wilson_interval
from workbench.validation import fail


@dataclass(frozen=True)
class Rate:
    """k events in n trials: the rate and its 95% Wilson interval (n = 0: nan in [0, 1]; a
    JSON file such as summary.json holds ``null`` for the nan)."""

    k: int
    n: int
    value: float = field(init=False)
    low: float = field(init=False)
    high: float = field(init=False)

    def __post_init__(self) -> None:
        for name in ("k", "n"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, Integral) or v < 0:
                raise fail(name, v, "must be an integer >= 0")
            object.__setattr__(self, name, int(v))
        if self.k > self.n:
            raise fail("k", self.k, f"must be <= n = {self.n}")
        lo, hi = wilson_interval(self.k, self.n) if self.n else (0.0, 1.0)
        object.__setattr__(self, "value", self.k / self.n if self.n else math.nan)
        object.__setattr__(self, "low", lo)
        object.__setattr__(self, "high", hi)

    @classmethod
    def of(cls, flags) -> Rate:
        """The rate of True in a boolean array."""
        f = np.asarray(flags, dtype=bool)
        return cls(int(f.sum()), int(f.size))

    def below(self, other: Rate) -> bool:
        """Lower than ``other`` with disjoint 95% intervals."""
        return self.high < other.low

    def above(self, other: Rate) -> bool:
        return other.below(self)

    def contains(self, p: float) -> bool:
        """``p`` lies inside the 95% interval."""
        return self.low <= p <= self.high


@dataclass(frozen=True)
class Spread:
    """Mean, standard deviation (ddof 0), min, median and max of a sample (an empty sample:
    n = 0 and nan, written as ``null`` in a JSON file)."""

    n: int
    mean: float
    std: float
    min: float
    median: float
    max: float

    @classmethod
    def of(cls, values) -> Spread:
        v = np.asarray(values, dtype=float).ravel()
        if v.size == 0:
            return cls(0, *(math.nan,) * 5)
        return cls(int(v.size), float(v.mean()), float(v.std()), float(v.min()),
                   float(np.median(v)), float(v.max()))


def to_jsonable(obj: Any) -> Any:
    """Dataclasses (nested, in tuples, lists and dicts) as plain JSON-able data. Non-finite
    floats stay as they are; the writers (:func:`workbench.study.io.atomic_write_json`) turn
    them into ``null``."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj

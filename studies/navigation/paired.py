"""Paired comparison of two controllers' safety on the same realisations (common random
numbers): discordant counts, exact McNemar test, Newcombe's interval of the difference."""

from __future__ import annotations

from dataclasses import dataclass

import pandas as pd

from workbench.study.stats import mcnemar_exact, paired_counts, paired_difference_interval


@dataclass(frozen=True)
class Paired:
    """Safety of ``first`` minus ``second`` on the same realisations at one variance:
    counts a (both safe), b (only first), c (only second), d (neither); exact McNemar p and
    Newcombe's 95% interval of the difference."""

    first: str
    second: str
    variance: float
    n: int
    a: int
    b: int
    c: int
    d: int
    difference: float
    low: float
    high: float
    p_value: float

    @classmethod
    def of(cls, first: str, second: str, variance: float, x: pd.DataFrame,
           y: pd.DataFrame) -> Paired:
        m = x.merge(y, on="realisation", suffixes=("_1", "_2"))
        a, b, c, d = paired_counts(~m["crashed_1"].to_numpy(bool),
                                   ~m["crashed_2"].to_numpy(bool))
        diff, lo, hi = paired_difference_interval(a, b, c, d)
        return cls(first, second, variance, a + b + c + d, a, b, c, d, diff, lo, hi,
                   mcnemar_exact(b, c))

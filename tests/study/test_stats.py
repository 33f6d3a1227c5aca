"""Paired-comparison statistics against independent oracles (scipy, simulation)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from workbench.study.stats import mcnemar_exact, paired_difference_interval, wilson_interval


def test_mcnemar_exact_matches_the_binomial_sum():
    for b, c in ((0, 0), (3, 0), (10, 4), (7, 7), (1, 12)):
        n, k = b + c, min(b, c)
        expect = 1.0 if n == 0 else min(1.0, 2 * sum(math.comb(n, i) for i in range(k + 1))
                                        / 2 ** n)
        assert mcnemar_exact(b, c) == pytest.approx(expect, rel=1e-12)


def test_paired_interval_reduces_to_exact_cases_and_covers():
    theta, lo, hi = paired_difference_interval(20, 2, 2, 16)
    assert theta == 0 and lo < 0 < hi
    theta, lo, hi = paired_difference_interval(0, 10, 0, 0)  # only the first ever succeeds
    assert theta == 1.0 and hi == 1.0 and lo > 0.6
    # coverage by simulation: correlated pairs with a known difference of 0.15
    rng = np.random.default_rng(0)
    p = np.array([0.45, 0.25, 0.10, 0.20])  # a, b, c, d -> p1 - p2 = 0.25 - 0.10
    hits, reps = 0, 2000
    for _ in range(reps):
        a, b, c, d = rng.multinomial(100, p)
        _, lo, hi = paired_difference_interval(int(a), int(b), int(c), int(d))
        hits += lo <= 0.15 <= hi
    assert 0.93 <= hits / reps <= 0.975


def test_bad_counts_name_the_field():
    with pytest.raises(ValueError, match="b"):
        mcnemar_exact(-1, 2)
    with pytest.raises(ValueError, match="c"):
        paired_difference_interval(1, 1, 1.5, 1)
    with pytest.raises(ValueError, match=r"a \+ b \+ c \+ d"):
        paired_difference_interval(0, 0, 0, 0)
    with pytest.raises(ValueError, match="successes"):
        wilson_interval(5, 4)

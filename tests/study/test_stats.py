"""Paired-comparison statistics against independent oracles (scipy, simulation)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from workbench.study.stats import (
    PooledPaired,
    mcnemar_exact,
    paired_difference_interval,
    pooled_paired,
    wilson_interval,
)


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


# ---------------------------------------------------------------------------------------------
# stratified paired comparison (one stratum per map): oracles in plain Python/NumPy and scipy

EXAMPLE = [(5, 4, 1, 2), (3, 6, 2, 1), (10, 2, 2, 0)]  # (a, b, c, d): both, only A, only B, none


def _binom_p(b: int, c: int) -> float:
    n, k = b + c, min(b, c)
    return 1.0 if n == 0 else min(1.0, 2 * sum(math.comb(n, i) for i in range(k + 1)) / 2**n)


def _cmh_oracle(strata) -> float:
    """CMH chi-square (no correction) in plain NumPy, each stratum the table
    [[a + b, c + d], [a + c, b + d]] (rows A, B; columns safe, unsafe)."""
    num = var = 0.0
    for a, b, c, d in strata:
        t = np.array([[a + b, c + d], [a + c, b + d]], dtype=float)
        N, r, col = t.sum(), t.sum(axis=1), t.sum(axis=0)
        if col.min() == 0:
            continue
        num += t[0, 0] - r[0] * col[0] / N
        var += r[0] * r[1] * col[0] * col[1] / (N**2 * (N - 1))
    if var == 0:
        return 1.0
    return math.erfc(math.sqrt(num**2 / var / 2))  # chi-square(1) survival


def _homogeneity_oracle(strata):
    from scipy.stats import chi2_contingency

    t = np.array([[b, c] for _, b, c, _ in strata if b + c > 0])
    if len(t) < 2:
        return None
    if t[:, 0].sum() == 0 or t[:, 1].sum() == 0:
        return 1.0
    return float(chi2_contingency(t, correction=False).pvalue)


def _agrees(r: PooledPaired, strata) -> bool:
    """Every field of ``r`` against the oracles for ``strata``."""
    a, b, c, d = (sum(s[i] for s in strata) for i in range(4))
    n = a + b + c + d
    _, lo, hi = paired_difference_interval(a, b, c, d)
    h, h_ref = r.homogeneity_p, _homogeneity_oracle(strata)
    return (r.b == b and r.c == c and r.n == n and r.n_strata == len(strata)
            and math.isclose(r.difference, (b - c) / n, rel_tol=1e-12, abs_tol=1e-15)
            and (r.low, r.high) == (lo, hi)
            and math.isclose(r.p_value, _binom_p(b, c), rel_tol=1e-12)
            and math.isclose(r.cmh_p, _cmh_oracle(strata), rel_tol=1e-9)
            and (h is None if h_ref is None else h is not None
                 and math.isclose(h, h_ref, rel_tol=1e-9)))


def test_pooled_paired_against_hand_values():
    r = pooled_paired(EXAMPLE)
    assert (r.b, r.c, r.n, r.n_strata) == (12, 5, 38, 3)
    assert r.difference == pytest.approx(7 / 38, rel=1e-12)
    assert r.p_value == pytest.approx(2 * sum(math.comb(17, i) for i in range(6)) / 2**17,
                                      rel=1e-12)
    # CMH by hand: numerator sum (b_i - c_i) / 2 = 1.5 + 2 + 0 = 3.5; variances
    # c1 c2 / (4 (2 n_i - 1)) = 15*9/92 + 14*10/92 + 24*4/108
    var = 15 * 9 / 92 + 14 * 10 / 92 + 24 * 4 / 108
    assert r.cmh_p == pytest.approx(math.erfc(math.sqrt(3.5**2 / var / 2)), rel=1e-9)
    assert r.cmh_p == pytest.approx(_cmh_oracle(EXAMPLE), rel=1e-9)
    assert r.low < r.difference < r.high
    assert _agrees(r, EXAMPLE)


def test_the_cmh_statistic_is_statsmodels_and_scipy_agree_on_homogeneity():
    from statsmodels.stats.contingency_tables import StratifiedTable

    tables = np.stack([np.array([[a + b, c + d], [a + c, b + d]]) for a, b, c, d in EXAMPLE],
                      axis=2)
    ref = StratifiedTable(tables.astype(float)).test_null_odds(correction=False).pvalue
    assert pooled_paired(EXAMPLE).cmh_p == pytest.approx(ref, rel=1e-9)
    assert pooled_paired(EXAMPLE).homogeneity_p == pytest.approx(_homogeneity_oracle(EXAMPLE))


def test_homogeneous_and_heterogeneous_strata():
    same = [(10, 8, 2, 5), (12, 15, 5, 3), (7, 12, 3, 4)]  # b_i / m_i: 0.80, 0.75, 0.80
    r = pooled_paired(same)
    assert _agrees(r, same)
    assert r.homogeneity_p > 0.5 and r.p_value < 1e-3 and r.cmh_p < 1e-3 and r.low > 0
    # A far safer on one map, far less safe on the other: the pooled effect cancels
    opposite = [(10, 18, 2, 5), (12, 2, 18, 3)]
    r = pooled_paired(opposite)
    assert _agrees(r, opposite)
    assert r.homogeneity_p < 1e-5 and r.difference == 0.0 and r.p_value == 1.0
    assert r.low < 0 < r.high


def test_degenerate_strata():
    r = pooled_paired([(5, 0, 0, 5), (3, 0, 0, 1)])  # no discordant pairs
    assert (r.p_value, r.cmh_p, r.difference, r.homogeneity_p) == (1.0, 1.0, 0.0, None)
    r = pooled_paired([(4, 0, 0, 0), (0, 0, 0, 3), (0, 0, 0, 0)])  # every table has a zero margin
    assert (r.p_value, r.cmh_p, r.homogeneity_p, r.n, r.n_strata) == (1.0, 1.0, None, 7, 3)
    r = pooled_paired([(5, 4, 1, 2), (6, 0, 0, 0)])  # one informative stratum
    assert r.homogeneity_p is None and r.cmh_p == pytest.approx(_cmh_oracle([(5, 4, 1, 2)]))
    r = pooled_paired([(4, 3, 0, 1), (2, 5, 0, 0)])  # all discordant pairs favour A
    assert r.homogeneity_p == 1.0 and r.p_value == pytest.approx(2 / 2**8)
    assert pooled_paired(np.array(EXAMPLE)) == pooled_paired(EXAMPLE)


def _swapped(strata):  # b and c exchanged: B's advantage read as A's
    return pooled_paired([(a, c, b, d) for a, b, c, d in strata])


def _first_only(strata):
    r = pooled_paired(strata[:1])
    return PooledPaired(**{**r.__dict__, "n_strata": len(strata)})


def _collapsed(strata):  # one summed stratum: right pooled counts, wrong stratified tests
    r = pooled_paired([tuple(int(sum(s[i] for s in strata)) for i in range(4))])
    return PooledPaired(**{**r.__dict__, "n_strata": len(strata)})


@pytest.mark.parametrize("wrong", [_swapped, _first_only, _collapsed])
def test_wrong_copies_fail_the_oracle_check(wrong):
    for strata in (EXAMPLE, [(10, 8, 2, 5), (12, 15, 5, 3), (7, 12, 3, 4)]):
        assert _agrees(pooled_paired(strata), strata)
    assert not _agrees(wrong(EXAMPLE), EXAMPLE)


@pytest.mark.parametrize(("strata", "message"), [
    ([(1, 2, -1, 0)], r"^strata\[0\]\.c = -1 is invalid: must be an integer >= 0"),
    ([(1, 2, 3, 4), (1, 2.5, 0, 0)], r"^strata\[1\]\.b = 2\.5 is invalid"),
    ([(1, 2, 3, 4), (1, 2, 3)], r"^strata\[1\] = \[1 2 3\] is invalid: must be 4 counts"),
    ([(1, 2, 3, 4, 5)], r"^strata\[0\] = .* is invalid: must be 4 counts"),
    ([], r"^strata = .* is invalid: must be a non-empty sequence"),
    ("abcd", r"^strata = 'abcd' is invalid"),
    ([(0, 0, 0, 0)], r"^strata = .* is invalid: need at least one pair"),
    ([(True, 0, 0, 1)], r"^strata\[0\]\.a = True is invalid"),
])
def test_bad_strata_name_the_field(strata, message):
    with pytest.raises(ValueError, match=message):
        pooled_paired(strata)

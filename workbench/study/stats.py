"""Small statistics helpers for study reports."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache

import numpy as np
from scipy import stats

from workbench.validation import fail, integer, real

Z_95 = 1.959963984540054  # standard normal quantile 0.975


@cache
def _t975(df: int) -> float:
    return float(stats.t.ppf(0.975, df))


def t_interval(values: np.ndarray) -> tuple[float, float, float]:
    """Mean of ``values`` and the 95 % t-interval of the mean (a single value: the value and
    a nan interval)."""
    v = np.asarray(values, dtype=float)
    m = float(v.mean())
    if v.size < 2:
        return m, math.nan, math.nan
    half = _t975(v.size - 1) * float(v.std(ddof=1)) / math.sqrt(v.size)
    return m, m - half, m + half


def wilson_interval(successes: int, n: int, z: float = Z_95) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion (95% by default), clipped to [0, 1].
    Counts are integers (never ``bool``); ``z`` > 0."""
    n = integer("n", n, 1)
    successes = integer("successes", successes, 0, n)
    z = real("z", z, 0.0, strict=True)
    p = successes / n
    z2 = z * z
    denom = 1.0 + z2 / n
    center = (p + z2 / (2 * n)) / denom
    half = z / denom * math.sqrt(p * (1.0 - p) / n + z2 / (4 * n * n))
    low = 0.0 if successes == 0 else max(0.0, center - half)
    high = 1.0 if successes == n else min(1.0, center + half)
    return low, high


def paired_counts(first, second) -> tuple[int, int, int, int]:
    """Counts of paired binary outcomes (True = success): (a, b, c, d) = both, only the
    first, only the second, neither."""
    s1, s2 = np.asarray(first, dtype=bool), np.asarray(second, dtype=bool)
    return (int(np.sum(s1 & s2)), int(np.sum(s1 & ~s2)), int(np.sum(~s1 & s2)),
            int(np.sum(~s1 & ~s2)))


def mcnemar_exact(b: int, c: int) -> float:
    """Two-sided exact McNemar p-value from the discordant counts b (only the first method
    succeeded) and c (only the second): a binomial test of b in b + c trials at p = 1/2."""
    b, c = integer("b", b, 0), integer("c", c, 0)
    if b + c == 0:
        return 1.0
    from scipy.stats import binomtest

    return float(binomtest(int(b), int(b + c), 0.5).pvalue)


def paired_difference_interval(a: int, b: int, c: int, d: int,
                               z: float = Z_95) -> tuple[float, float, float]:
    """Difference p1 - p2 of paired proportions and its 95% interval (Newcombe 1998, method
    10: Wilson limits of each margin combined with the phi correlation).

    Counts: a both succeed, b only the first, c only the second, d neither.
    """
    a, b, c, d = (integer(name, v, 0) for name, v in (("a", a), ("b", b), ("c", c), ("d", d)))
    z = real("z", z, 0.0, strict=True)
    n = a + b + c + d
    if n < 1:
        raise fail("a + b + c + d", n, "need at least one pair")
    p1, p2 = (a + b) / n, (a + c) / n
    l1, u1 = wilson_interval(a + b, n, z)
    l2, u2 = wilson_interval(a + c, n, z)
    den = (a + b) * (c + d) * (a + c) * (b + d)
    phi = (a * d - b * c) / math.sqrt(den) if den > 0 else 0.0
    dl = math.sqrt(max((p1 - l1) ** 2 - 2 * phi * (p1 - l1) * (u2 - p2) + (u2 - p2) ** 2, 0.0))
    du = math.sqrt(max((u1 - p1) ** 2 - 2 * phi * (u1 - p1) * (p2 - l2) + (p2 - l2) ** 2, 0.0))
    theta = p1 - p2
    return theta, max(-1.0, theta - dl), min(1.0, theta + du)


@dataclass(frozen=True)
class PooledPaired:
    """Two controllers A and B compared on paired binary outcomes (1 = safe) over strata
    (maps); see :func:`pooled_paired`."""

    b: int  # pairs where only A was safe, summed over the strata
    c: int  # pairs where only B was safe, summed
    n: int  # pairs
    n_strata: int  # strata given (uninformative ones included)
    difference: float  # safety rate of A minus that of B: (b - c) / n
    low: float  # 95% interval of the difference
    high: float
    p_value: float  # exact McNemar on the summed b, c
    cmh_p: float  # Cochran-Mantel-Haenszel: common odds ratio (controller x outcome) is 1
    homogeneity_p: float | None  # same paired odds ratio b_i / c_i in every stratum


_COUNTS = ("a", "b", "c", "d")


def pooled_paired(strata: Sequence[tuple[int, int, int, int]]) -> PooledPaired:
    """Stratified paired comparison of controllers A and B (e.g. one stratum per map).

    Each stratum is (a, b, c, d), counts of pairs (A's episode and B's episode on the same
    map, seed and start): a both safe, b only A safe, c only B safe, d neither; the order of
    :func:`paired_difference_interval`. Safety rates are (a + b) / n for A and (a + c) / n for
    B, so A - B = (b - c) / n over all n pairs (weights n_i / n per stratum).

    - ``low``, ``high``: Newcombe's interval (:func:`paired_difference_interval`) on the summed
      table. It treats the pairs as one sample and ignores the strata, so when the strata
      differ it is at least as wide as a stratified interval (conservative).
    - ``p_value``: exact McNemar on the summed discordant counts (:func:`mcnemar_exact`).
    - ``cmh_p``: Cochran-Mantel-Haenszel test (no continuity correction, chi-square with 1
      degree of freedom, statsmodels ``StratifiedTable.test_null_odds``) that the common odds
      ratio of the per-stratum 2x2 tables controller x outcome, [[a + b, c + d], [a + c,
      b + d]], is 1. Strata with a zero column margin (every episode safe, or every one
      unsafe: no information, and 0/0 when empty) are left out; with none left it is 1.0.
      These tables count the two controllers' episodes as independent samples: with the
      usual positive correlation of paired episodes (same map and seed) the test is
      conservative; the paired test is ``p_value``.
    - ``homogeneity_p``: whether the paired effect is the same in every stratum. Given the
      m_i = b_i + c_i discordant pairs of stratum i, b_i ~ Binomial(m_i, psi_i / (1 + psi_i))
      with psi_i the stratum's paired (conditional) odds ratio, the argument behind
      McNemar's test; equal psi_i is equal proportions b_i / m_i, tested by Pearson's
      chi-square on the k x 2 table [b_i, c_i] of the k strata with m_i > 0 (k - 1 degrees of
      freedom; asymptotic, so rough with few discordant pairs per stratum). Breslow-Day on the
      controller x outcome tables is not used: it tests the marginal odds ratios and assumes
      independent rows, which paired episodes are not. None when fewer than 2 strata have
      discordant pairs; 1.0 when all discordant pairs go one way (every proportion 0 or 1).
    """
    if (isinstance(strata, str | bytes) or not isinstance(strata, Sequence | np.ndarray)
            or len(strata) == 0):
        raise fail("strata", strata, "must be a non-empty sequence of (a, b, c, d) counts")
    rows = []
    for i, s in enumerate(strata):
        if not isinstance(s, tuple | list | np.ndarray) or len(s) != 4:
            raise fail(f"strata[{i}]", s, "must be 4 counts (a, b, c, d): pairs both safe, "
                       "only A safe, only B safe, neither")
        rows.append([integer(f"strata[{i}].{name}", v, 0) for name, v in zip(_COUNTS, s,
                                                                               strict=True)])
    t = np.array(rows, dtype=np.int64)
    a, b, c, d = (int(v) for v in t.sum(axis=0))
    n = a + b + c + d
    if n < 1:
        raise fail("strata", strata, "need at least one pair")
    diff, low, high = paired_difference_interval(a, b, c, d)
    return PooledPaired(b=b, c=c, n=n, n_strata=len(rows), difference=diff, low=low, high=high,
                        p_value=mcnemar_exact(b, c), cmh_p=_cmh_p(t),
                        homogeneity_p=_homogeneity_p(t[:, 1], t[:, 2]))


def _cmh_p(t: np.ndarray) -> float:
    """CMH p-value over the strata rows (a, b, c, d) of ``t`` with both outcomes present."""
    a, b, c, d = t.T
    safe, unsafe = 2 * a + b + c, b + c + 2 * d  # column margins of [[a+b, c+d], [a+c, b+d]]
    keep = (safe > 0) & (unsafe > 0)
    if not keep.any():
        return 1.0
    from scipy.stats import chi2
    from statsmodels.stats.contingency_tables import StratifiedTable

    tables = np.stack([np.stack([a + b, c + d]), np.stack([a + c, b + d])])[:, :, keep]
    stat = float(StratifiedTable(tables.astype(float)).test_null_odds(correction=False).statistic)
    return float(chi2.sf(stat, 1))  # sf: accurate for small p (statsmodels takes 1 - cdf)


def _homogeneity_p(b: np.ndarray, c: np.ndarray) -> float | None:
    """Pearson chi-square p-value for equal b_i / (b_i + c_i) over the strata with b_i + c_i
    > 0; None with fewer than 2 of them."""
    m = b + c
    keep = m > 0
    if keep.sum() < 2:
        return None
    b, m = b[keep].astype(float), m[keep].astype(float)
    p = b.sum() / m.sum()
    if p in (0.0, 1.0):
        return 1.0
    stat = float(np.sum((b - m * p) ** 2 / (m * p * (1.0 - p))))
    from scipy.stats import chi2

    return float(chi2.sf(stat, int(keep.sum()) - 1))

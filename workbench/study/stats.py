"""Small statistics helpers for study reports."""

from __future__ import annotations

import math
from numbers import Integral

from workbench.validation import fail

Z_95 = 1.959963984540054  # standard normal quantile 0.975


def wilson_interval(successes: int, n: int, z: float = Z_95) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion (95% by default), clipped to [0, 1]."""
    if not isinstance(n, Integral) or n < 1:
        raise fail("n", n, "must be an integer >= 1")
    if not isinstance(successes, Integral) or not 0 <= successes <= n:
        raise fail("successes", successes, f"must be an integer in [0, {n}]")
    successes, n = int(successes), int(n)
    p = successes / n
    z2 = z * z
    denom = 1.0 + z2 / n
    center = (p + z2 / (2 * n)) / denom
    half = z / denom * math.sqrt(p * (1.0 - p) / n + z2 / (4 * n * n))
    low = 0.0 if successes == 0 else max(0.0, center - half)
    high = 1.0 if successes == n else min(1.0, center + half)
    return low, high


def mcnemar_exact(b: int, c: int) -> float:
    """Two-sided exact McNemar p-value from the discordant counts b (only the first method
    succeeded) and c (only the second): a binomial test of b in b + c trials at p = 1/2."""
    for name, v in (("b", b), ("c", c)):
        if not isinstance(v, Integral) or v < 0:
            raise fail(name, v, "must be an integer >= 0")
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
    for name, v in (("a", a), ("b", b), ("c", c), ("d", d)):
        if not isinstance(v, Integral) or v < 0:
            raise fail(name, v, "must be an integer >= 0")
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

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

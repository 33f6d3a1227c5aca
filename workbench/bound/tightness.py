"""How tight a check is: the ratio of its right-hand side to the observed left-hand side.

Over the *informative steps* (tube radius R > 0: the nominal and the real samples differ, so
the Lipschitz term is not zero), per check: the ratio RHS / LHS on the steps with LHS > 0
(steps with LHS <= 0 are counted apart, never divided by), its quantiles, and the share of
informative steps on which the bound is *informative at c*: LHS > 0 and LHS <= RHS <= c LHS.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import binom, norm

from workbench.study.sequential import score_rci
from workbench.study.stats import wilson_interval
from workbench.validation import fail, real

THRESHOLDS: tuple[float, ...] = (2.0, 10.0, 100.0)
QUANTILES: tuple[float, ...] = (0.05, 0.25, 0.5, 0.75, 0.95)


def _vectors(lhs, rhs, R) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    out = []
    for name, v in (("lhs", lhs), ("rhs", rhs), ("R", R)):
        a = np.asarray(v, dtype=float).ravel()
        out.append(a)
        if a.shape != out[0].shape:
            raise fail(name, a.shape, f"must have the shape of lhs {out[0].shape}")
    if np.any(out[2] < 0) or not np.all(np.isfinite(out[2])):
        raise fail("R", out[2][~(out[2] >= 0)][:3], "tube radii must be finite and >= 0")
    return out[0], out[1], out[2]


def ratios(lhs, rhs) -> np.ndarray:
    """RHS / LHS per step where LHS > 0 (and both are finite), nan elsewhere."""
    lhs, rhs, _ = _vectors(lhs, rhs, np.zeros(np.size(lhs)))
    ok = (lhs > 0) & np.isfinite(lhs) & np.isfinite(rhs)
    out = np.full(lhs.shape, np.nan)
    out[ok] = rhs[ok] / lhs[ok]
    return out


def informative(lhs, rhs, c: float) -> np.ndarray:
    """Per step: LHS > 0 and LHS <= RHS <= c LHS (the bound holds within a factor c)."""
    c = real("c", c, 1.0)
    r = ratios(lhs, rhs)
    return np.isfinite(r) & (r >= 1.0) & (r <= c)


@dataclass(frozen=True)
class Tightness:
    """One check over the informative steps (R > 0) where it was evaluated (finite LHS and
    RHS): ``n`` steps, ``n_lhs_nonpositive`` of them with LHS <= 0 (no ratio), ``n_holding``
    with LHS <= RHS; quantiles ``QUANTILES`` of RHS / LHS over the steps with LHS > 0 (nan
    when there are none); per threshold c of ``THRESHOLDS``, the steps informative at c
    and the Wilson 95 % interval of their share of the ``n`` steps."""

    n: int
    n_lhs_nonpositive: int
    n_holding: int
    ratio_quantiles: tuple[float, ...]
    n_informative: tuple[int, ...]
    informative_interval: tuple[tuple[float, float], ...]

    @property
    def ratio_median(self) -> float:
        return self.ratio_quantiles[QUANTILES.index(0.5)]

    def share(self, c: float) -> float:
        """Share of the n steps informative at threshold c (a value of THRESHOLDS)."""
        if c not in THRESHOLDS:
            raise fail("c", c, f"thresholds are {THRESHOLDS}")
        return self.n_informative[THRESHOLDS.index(c)] / self.n if self.n else float("nan")

    @classmethod
    def of(cls, lhs, rhs, R) -> Tightness:
        lhs, rhs, R = _vectors(lhs, rhs, R)
        use = (R > 0) & np.isfinite(lhs) & np.isfinite(rhs)
        lhs, rhs = lhs[use], rhs[use]
        r = ratios(lhs, rhs)
        pos = r[np.isfinite(r)]
        q = tuple(float(np.quantile(pos, x)) for x in QUANTILES) if pos.size else (
            (float("nan"),) * len(QUANTILES))
        k = tuple(int(informative(lhs, rhs, c).sum()) for c in THRESHOLDS)
        n = int(use.sum())
        return cls(n=n, n_lhs_nonpositive=int(np.sum(lhs <= 0)), n_holding=int(np.sum(lhs <= rhs)),
                   ratio_quantiles=q, n_informative=k,
                   informative_interval=tuple(wilson_interval(x, n) if n else
                                              (float("nan"), float("nan")) for x in k))


def median_interval(x, alpha: float = 0.05) -> tuple[float, float, float]:
    """(median, low, high): the distribution-free interval of the median from order statistics
    (the sign test's): [x_(k+1), x_(n−k)] with k the largest count such that
    P(Binomial(n, ½) <= k) <= alpha/2, covering with probability >= 1 − alpha for independent
    draws; (−inf, inf) when n is too small for any k (n <= 5 at 0.05)."""
    a = np.sort(np.asarray(x, dtype=float).ravel())
    if a.size == 0 or not np.all(np.isfinite(a)):
        raise fail("x", a[:3], "need at least one value, all finite")
    if not 0.0 < real("alpha", alpha) < 1.0:
        raise fail("alpha", alpha, "must lie in (0, 1)")
    n = a.size
    k = int(binom.ppf(alpha / 2, n, 0.5))
    while k >= 0 and binom.cdf(k, n, 0.5) > alpha / 2:
        k -= 1
    med = float(np.median(a))
    if k < 0:
        return med, -np.inf, np.inf
    return med, float(a[k]), float(a[n - 1 - k])


VERDICTS = ("better", "worse", "equivalent", "undecided")


@dataclass(frozen=True)
class Comparison:
    """The bound with constants A against B on the same informative steps (paired by step):
    the share informative at ``threshold`` with A minus that with B, its score interval
    (Tango) at the given z, and the verdict: ``better`` (interval above 0), ``worse`` (below
    0), ``equivalent`` (inside ±margin), else ``undecided``; and the median ratio
    RHS_B / RHS_A over the steps with RHS_A > 0 with its sign-test interval at the same
    level."""

    threshold: float
    n: int
    only_a: int  # steps informative with A only
    only_b: int
    share_a: float
    share_b: float
    difference: float
    low: float
    high: float
    margin: float
    verdict: str
    rhs_ratio: float  # median RHS_B / RHS_A
    rhs_ratio_low: float
    rhs_ratio_high: float
    n_ratio: int  # steps with RHS_A > 0

    @classmethod
    def of(cls, lhs, rhs_a, rhs_b, R, threshold: float = 10.0, z: float = 1.959963984540054,
           margin: float = 0.05) -> Comparison:
        lhs, rhs_a, R = _vectors(lhs, rhs_a, R)
        rhs_b = _vectors(lhs, rhs_b, R)[1]
        z = real("z", z, 0.0, strict=True)
        if not 0.0 < real("margin", margin) < 1.0:
            raise fail("margin", margin, "must lie in (0, 1)")
        use = (R > 0) & np.isfinite(lhs) & np.isfinite(rhs_a) & np.isfinite(rhs_b)
        if not use.any():
            raise fail("R", "no step with R > 0 and finite sides", "need an informative step")
        lhs, rhs_a, rhs_b = lhs[use], rhs_a[use], rhs_b[use]
        ia, ib = informative(lhs, rhs_a, threshold), informative(lhs, rhs_b, threshold)
        n, b, c = int(use.sum()), int(np.sum(ia & ~ib)), int(np.sum(~ia & ib))
        d, low, high = score_rci(b, c, n, z)
        verdict = ("better" if low > 0 else "worse" if high < 0 else
                   "equivalent" if -margin < low and high < margin else "undecided")
        pos = rhs_a > 0
        alpha = 2.0 * float(norm.sf(z))
        m, ml, mh = (median_interval(rhs_b[pos] / rhs_a[pos], alpha) if pos.any()
                     else (float("nan"),) * 3)
        return cls(threshold=float(threshold), n=n, only_a=b, only_b=c,
                   share_a=float(ia.mean()), share_b=float(ib.mean()), difference=float(d),
                   low=float(low), high=float(high), margin=float(margin), verdict=verdict,
                   rhs_ratio=m, rhs_ratio_low=ml, rhs_ratio_high=mh, n_ratio=int(pos.sum()))

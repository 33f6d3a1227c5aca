"""Group-sequential comparison of two controllers A and B on paired binary outcomes.

Each pair (A and B on the same map and random streams) is concordant (both safe or both not)
or discordant: ``b`` pairs where only A was safe, ``c`` where only B was. The difference of
the safety rates is d = p_A - p_B = (b - c) / n over n pairs. Pairs are added in K rounds
(looks) and a comparison stops at the first look that decides it.

Boundaries. Lan-DeMets alpha spending with the O'Brien-Fleming-type function, alpha / 2 per
side and each side spent by 2 - 2 Phi(z_{1-alpha/4} / sqrt(t)) (the convention of the usual
tables: K = 5 equal looks at 0.05 give 4.877, 3.357, 2.680, 2.290, 2.031), at information
fractions t_k (k/K for equal looks, or any increasing fractions ending at 1). The critical
value c_k solves
P(|Z_1| < c_1, ..., |Z_{k-1}| < c_{k-1}, |Z_k| >= c_k) = alpha(t_k) - alpha(t_{k-1}) with
Z_k = W(t_k) / sqrt(t_k), W a standard Brownian motion (the canonical joint distribution).
The probabilities are computed by recursive numerical integration: the sub-density of the
score W(t_k) on the continuation region is carried from look to look through the Gaussian
increments (Simpson's rule on a grid of 24 points per standard deviation of the increment) and
each c_k is a root found by Brent's method. c_1 = z_{1-alpha(t_1)/2} exactly; with one look
c_1 = z_{1-alpha/2}. Results are cached by (fractions, alpha).

Intervals. At look k the repeated confidence interval (RCI) at level 1 - alpha is the set of
differences d0 whose statistic lies in (-c_k, c_k); it holds the true difference at every look
at once with probability at least 1 - alpha (Jennison and Turnbull), to the normal
approximation. Two statistics (:class:`SequentialDesign` ``interval``):

- ``score`` (the default): Tango's (1998) score statistic for paired proportions,
  (b - c - n d0) / sqrt(n (2 p~_c + d0 (1 - d0))), p~_c the maximum-likelihood probability of
  a B-only pair under d = d0. Its variance is taken under d0, so a look where every pair agrees
  gives the interval +-c_k^2 / (n + c_k^2), not a point.
- ``agresti-min``: Agresti and Min's (2005) adjusted Wald interval d~ +- c_k se, with 0.5 added
  to each of the four cells: b' = b + 0.5, c' = c + 0.5, n' = n + 2, d~ = (b' - c') / n',
  se = sqrt(((b' + c') / n' - d~^2) / n') (never 0). Its variance is estimated at the data, and
  when most discordant pairs go one way a small count shrinks both the estimate and se, so the
  one-sided errors of the equivalence tests exceed alpha / m near the margin (about 0.07
  instead of 0.05 at discordance 0.1 and d = margin = 0.1); the score statistic keeps them.

Decisions, for m declared comparisons (Bonferroni: alpha / m each), at look k:

- ``superior`` when the RCI at level 1 - alpha/m lies above 0, ``inferior`` when below 0 (a
  wrong directional claim has probability at most alpha/m over all looks);
- else ``equivalent`` when the RCI at level 1 - 2 alpha/m lies inside (-margin, +margin)
  (two one-sided tests, each at alpha/m);
- else ``continue``, which becomes ``undecided`` at the last look.

A difference inside the margin but away from 0 can be both superior (or inferior) and
equivalent; the directional decision is reported, with both intervals in the :class:`Look`.

Planning. :func:`plan_pairs` gives the smallest number of pairs (a multiple of the looks) with
P(superior | d = margin) >= power and P(equivalent | d = 0) >= power at an assumed discordance
psi = P(a pair is discordant): a normal approximation first, then a seeded simulation
(:func:`simulate`) moves it to the smallest size whose simulated powers have Wilson 95% lower
limits at or above ``power``. :func:`detectable` is the smallest difference with the power at
a given number of pairs (normal approximation).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np
from scipy.optimize import brentq
from scipy.stats import norm

from workbench.study.summary import Rate
from workbench.validation import fail, integer, real

DECISIONS = ("continue", "superior", "inferior", "equivalent", "undecided")
_CONTINUE, _SUPERIOR, _INFERIOR, _EQUIVALENT, _UNDECIDED = range(5)

MAX_LOOKS = 100
MAX_PAIRS_PER_LOOK = 10**8
MAX_REPS = 10**7
PLAN_SEED = 20_250_617  # the planning simulation's seed: plan_pairs is deterministic
PLAN_REPS = 20_000  # replications per truth in the planning simulation

_POINTS_PER_SD = 24  # Simpson grid: points per standard deviation of the score increment
_MAX_GRID = 4001  # grid points per look at most (accuracy drops for tiny increments)
_MAX_BOUND = 40.0  # a critical value whose spent alpha underflows to 0
_CHUNK = 1 << 16  # replications simulated at once


# ---------------------------------------------------------------------------------------------
# validation shared by the design and the planning functions

def _open(field: str, value: object, low: float, high: float) -> float:
    """A finite number strictly between ``low`` and ``high``."""
    try:
        x: float | None = real(field, value, low, strict=True)
    except ValueError:
        x = None
    if x is None or not x < high:
        raise fail(field, value, f"must be a finite number > {low:g} and < {high:g}")
    return x


def _looks(value: object) -> int:
    return integer("looks", value, 1, MAX_LOOKS)


def _alpha(value: object) -> float:
    return _open("alpha", value, 0.0, 0.5)


def _power(value: object) -> float:
    return _open("power", value, 0.5, 1.0)


def _margin(value: object) -> float:
    return _open("margin", value, 0.0, 1.0)


def _comparisons(value: object) -> int:
    return integer("comparisons", value, 1)


# ---------------------------------------------------------------------------------------------
# boundaries

def _fractions(fractions: object) -> tuple[float, ...]:
    """Information fractions: 1-D, strictly increasing, in (0, 1], the last one 1."""
    try:
        t = np.array(fractions, dtype=float)
    except (TypeError, ValueError) as exc:
        raise fail("fractions", fractions, "expected a sequence of numbers") from exc
    allowed = "must be strictly increasing numbers in (0, 1] ending at 1"
    if (t.ndim != 1 or t.size < 1 or t.size > MAX_LOOKS or not np.all(np.isfinite(t))
            or t[0] <= 0 or np.any(np.diff(t) <= 0) or abs(t[-1] - 1.0) > 1e-12):
        raise fail("fractions", fractions, f"{allowed} (at most {MAX_LOOKS} of them)")
    t[-1] = 1.0
    return tuple(float(x) for x in t)


def obrien_fleming_spending(t: np.ndarray | float, alpha: float) -> np.ndarray:
    """Two-sided alpha spent by information fraction t: alpha / 2 per side, each side spent
    by 2 - 2 Phi(z_{1-alpha/4} / sqrt(t)) (the convention of the usual tables)."""
    return 4.0 * norm.sf(norm.isf(alpha / 4.0) / np.sqrt(np.asarray(t, dtype=float)))


def _simpson(half: float, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Simpson's rule on [-half, half] with spacing at most ``step`` (odd point count,
    between 51 and the grid cap)."""
    m = min(max(math.ceil(2.0 * half / step) + 1, 51), _MAX_GRID)
    m += 1 - m % 2
    x, h = np.linspace(-half, half, m, retstep=True)
    w = np.full(m, 2.0)
    w[1::2] = 4.0
    w[0] = w[-1] = 1.0
    return x, w * (h / 3.0)


def _grid_step(t: Sequence[float], k: int) -> float:
    """Grid spacing for the score at look k (0-based): fine against the increments on both
    sides of it (the density's smoothness and the next look's Gaussian kernel)."""
    prev = t[k] - (t[k - 1] if k > 0 else 0.0)
    nxt = t[k + 1] - t[k]
    return math.sqrt(min(prev, nxt)) / _POINTS_PER_SD


def spending_bounds(fractions: object, spent: object) -> np.ndarray:
    """Two-sided critical values c_k for a cumulative two-sided spending ``spent[k]`` at
    information fractions ``fractions[k]``: P(no crossing before look k, |Z_k| >= c_k) =
    spent[k] - spent[k-1] under the canonical joint distribution (recursive integration).
    A look whose increment is 0 gets the bound 40 (nothing is spent there)."""
    t = _fractions(fractions)
    a = np.asarray(spent, dtype=float)
    inc = np.diff(np.concatenate([[0.0], a])) if a.ndim == 1 else np.empty(0)
    if (a.shape != (len(t),) or not np.all(np.isfinite(a)) or np.any(inc < 0)
            or not 0.0 < a[-1] < 1.0):
        raise fail("spent", spent, f"must be {len(t)} non-decreasing cumulative probabilities "
                   "(one per fraction), the last one in (0, 1)")
    return _spending_bounds(t, tuple(float(x) for x in a)).copy()


def _crossing(ck: float, f: np.ndarray, x: np.ndarray, sd: float, root: float) -> float:
    """P(continuing to the previous look, then |W(t_k)| >= ck sqrt(t_k)): the weighted
    sub-density ``f`` at the scores ``x`` times the increment's (sd ``sd``) two tails."""
    return float(f @ (norm.sf((ck * root - x) / sd) + norm.cdf((-ck * root - x) / sd)))


def _spending_bounds(t: tuple[float, ...], spent: tuple[float, ...]) -> np.ndarray:
    inc = np.diff(np.concatenate([[0.0], spent]))
    c = np.empty(len(t))
    c[0] = min(float(norm.isf(inc[0] / 2.0)), _MAX_BOUND) if inc[0] > 0 else _MAX_BOUND
    if len(t) == 1:
        return c
    x, w = _simpson(c[0] * math.sqrt(t[0]), _grid_step(t, 0))
    f = norm.pdf(x, scale=math.sqrt(t[0])) * w  # weighted sub-density of W(t_1), continuing
    for k in range(1, len(t)):
        sd, root = math.sqrt(t[k] - t[k - 1]), math.sqrt(t[k])
        args = (f, x, sd, root)
        c[k] = (brentq(lambda ck, *a, target=inc[k]: _crossing(ck, *a) - target, 0.0,
                       _MAX_BOUND, args=args, xtol=1e-12, rtol=1e-12)
                if inc[k] > 0 else _MAX_BOUND)
        if k + 1 < len(t):  # carry the sub-density over the continuation region of look k
            xn, wn = _simpson(c[k] * root, _grid_step(t, k))
            f = (norm.pdf((xn[:, None] - x[None, :]) / sd) / sd) @ f * wn
            x = xn
    return c


@lru_cache(maxsize=256)
def _obf_cached(t: tuple[float, ...], alpha: float) -> np.ndarray:
    out = _spending_bounds(t, tuple(float(a) for a in obrien_fleming_spending(np.array(t),
                                                                               alpha)))
    out.setflags(write=False)
    return out


def obrien_fleming_bounds(fractions: object, alpha: float) -> np.ndarray:
    """Two-sided critical values c_k of Lan-DeMets O'Brien-Fleming-type spending at the
    information fractions (strictly increasing, ending at 1) and two-sided level ``alpha``
    in (0, 1). Cached by (fractions, alpha); a fresh array is returned."""
    alpha = _open("alpha", alpha, 0.0, 1.0)
    return _obf_cached(_fractions(fractions), alpha).copy()


def equal_fractions(looks: int) -> tuple[float, ...]:
    """Information fractions k / K of K equal looks."""
    looks = _looks(looks)
    return tuple(k / looks for k in range(1, looks + 1))


# ---------------------------------------------------------------------------------------------
# intervals and decisions

INTERVALS = ("score", "agresti-min")


def _am(b, c, n, z):
    """Agresti-Min adjusted difference, lower and upper limits with multiplier z (arrays),
    clipped to [-1, 1]."""
    bp, cp, npr = b + 0.5, c + 0.5, n + 2.0
    d = (bp - cp) / npr
    se = np.sqrt(np.maximum((bp + cp) / npr - d * d, 0.0) / npr)
    return d, np.clip(d - z * se, -1.0, 1.0), np.clip(d + z * se, -1.0, 1.0)


def _score(b, c, n, d0):
    """Score statistic of H0: d = d0 (arrays): (b - c - n d0) / sqrt(n (2 p~_c + d0 (1 - d0)))
    with p~_c the maximum-likelihood P(only B safe) under d0 (the root of
    2n p^2 + (-(b + c) + (2n - b + c) d0) p - c d0 (1 - d0) = 0 in [max(0, -d0), 1]).
    0/0 is 0; x/0 is +-inf."""
    b, c, n, d0 = (np.asarray(v, dtype=float) for v in (b, c, n, d0))
    big_b = -(b + c) + (2.0 * n - b + c) * d0
    small_c = -c * d0 * (1.0 - d0)
    root = np.sqrt(np.maximum(big_b * big_b - 8.0 * n * small_c, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):  # the unused branch may divide by 0
        p_c = np.where(big_b > 0, -2.0 * small_c / (big_b + root), (root - big_b) / (4.0 * n))
        var = n * np.maximum(2.0 * p_c + d0 * (1.0 - d0), 0.0)
        num = b - c - n * d0
        return np.where(var > 0, num / np.sqrt(var),
                        np.where(num == 0, 0.0, np.sign(num) * np.inf))


def _counts(b: object, c: object, n: object, names: tuple[str, str, str] = ("b", "c", "n"),
            ) -> tuple[int, int, int]:
    n = integer(names[2], n, 1)
    b = integer(names[0], b, 0, n)
    c = integer(names[1], c, 0, n - b)
    return b, c, n


def paired_rci(b: int, c: int, n: int, z: float) -> tuple[float, float, float]:
    """Agresti-Min adjusted Wald interval for the paired difference (b - c) / n:
    (d~, d~ - z se, d~ + z se), the limits clipped to [-1, 1]. ``b`` pairs only A safe, ``c``
    only B safe, of ``n`` >= 1 pairs (b + c <= n); ``z`` > 0 (at look k of a design: its
    bound c_k)."""
    b, c, n = _counts(b, c, n)
    z = real("z", z, 0.0, strict=True)
    d, low, high = _am(float(b), float(c), float(n), z)
    return float(d), float(low), float(high)


def score_rci(b: int, c: int, n: int, z: float) -> tuple[float, float, float]:
    """Score interval for the paired difference (Tango 1998): ((b - c) / n, low, high), the
    differences d0 whose score statistic (b - c - n d0) / sqrt(n (2 p~_c + d0 (1 - d0))) lies in
    (-z, z), p~_c the maximum-likelihood P(only B safe) under d = d0. Counts as
    :func:`paired_rci`; ``z`` > 0."""
    b, c, n = _counts(b, c, n)
    z = real("z", z, 0.0, strict=True)
    d = (b - c) / n

    def stat(d0: float) -> float:
        return float(_score(b, c, n, d0))

    low = -1.0 if not stat(-1.0) >= z else brentq(lambda x: stat(x) - z, -1.0, d,
                                                   xtol=1e-12, rtol=1e-12)
    high = 1.0 if not stat(1.0) <= -z else brentq(lambda x: stat(x) + z, d, 1.0,
                                                  xtol=1e-12, rtol=1e-12)
    return d, float(low), float(high)


def _codes(interval: str, b, c, n, z, zeq, margin: float, last) -> np.ndarray:
    """Decision codes (indices into DECISIONS) of looks with cumulative counts b, c of n pairs
    and bounds z (superiority) and zeq (equivalence), elementwise. The score intervals are
    read through the statistic at 0 and +-margin (it decreases in d0)."""
    if interval == "score":
        z0 = _score(b, c, n, 0.0)
        sup, inf = z0 >= z, z0 <= -z
        eq = (_score(b, c, n, margin) <= -zeq) & (_score(b, c, n, -margin) >= zeq)
    else:
        _, low, high = _am(b, c, n, z)
        _, eq_low, eq_high = _am(b, c, n, zeq)
        sup, inf = low > 0, high < 0
        eq = (eq_low > -margin) & (eq_high < margin)
    code = np.where(sup, _SUPERIOR, np.where(inf, _INFERIOR, np.where(eq, _EQUIVALENT,
                                                                      _CONTINUE)))
    return np.where((code == _CONTINUE) & last, _UNDECIDED, code)


@dataclass(frozen=True)
class SequentialDesign:
    """A group-sequential paired comparison: ``looks`` equal rounds of ``pairs_per_look``
    pairs, decided on ``margin`` (the smallest difference that matters and the equivalence
    margin) at family-wise level ``alpha`` over ``comparisons`` declared comparisons
    (Bonferroni). ``power`` is the power aimed at when planning. ``interval``: the repeated
    confidence intervals, ``score`` (Tango's score intervals, the default: they keep the
    error rates) or ``agresti-min`` (Agresti-Min adjusted Wald intervals: their one-sided
    errors exceed alpha / m near the margin when most discordant pairs go one way)."""

    looks: int
    pairs_per_look: int
    margin: float = 0.10
    alpha: float = 0.05
    comparisons: int = 1
    power: float = 0.8
    interval: str = "score"

    def __post_init__(self) -> None:
        for name, value in (("looks", _looks(self.looks)),
                            ("pairs_per_look", integer("pairs_per_look", self.pairs_per_look,
                                                       1, MAX_PAIRS_PER_LOOK)),
                            ("margin", _margin(self.margin)), ("alpha", _alpha(self.alpha)),
                            ("comparisons", _comparisons(self.comparisons)),
                            ("power", _power(self.power))):
            object.__setattr__(self, name, value)
        if not isinstance(self.interval, str) or self.interval not in INTERVALS:
            raise fail("interval", self.interval,
                       f"allowed values are {', '.join(map(repr, INTERVALS))}")

    @property
    def max_pairs(self) -> int:
        """Pairs after the last look."""
        return self.looks * self.pairs_per_look

    @property
    def fractions(self) -> tuple[float, ...]:
        """Information fractions k / K of the looks."""
        return equal_fractions(self.looks)

    def bounds(self) -> np.ndarray:
        """c_k of the superiority/inferiority RCIs: two-sided level alpha / m."""
        return obrien_fleming_bounds(self.fractions, self.alpha / self.comparisons)

    def equivalence_bounds(self) -> np.ndarray:
        """c_k of the equivalence RCIs: two-sided level 2 alpha / m (each side alpha / m)."""
        return obrien_fleming_bounds(self.fractions, 2.0 * self.alpha / self.comparisons)


@dataclass(frozen=True)
class Look:
    """One look of a comparison: cumulative counts, both RCIs and the decision."""

    look: int  # 1-based
    n: int  # pairs so far
    b: int  # pairs where only A was safe
    c: int  # pairs where only B was safe
    difference: float  # (b - c) / n, raw
    low: float  # RCI at 1 - alpha/m (superiority / inferiority)
    high: float
    eq_low: float  # RCI at 1 - 2 alpha/m (equivalence)
    eq_high: float
    bound: float  # c_k of the superiority / inferiority RCI
    decision: str  # superior, inferior, equivalent, continue or undecided (last look)
    eq_bound: float  # c_k of the equivalence RCI


def decide(design: SequentialDesign, look: int, b: int, c: int, n: int) -> Look:
    """The decision at ``look`` (1-based) from the cumulative counts: ``b`` pairs only A safe,
    ``c`` only B safe, of ``n`` pairs. The bounds are those of the look's planned information
    fraction look / K, whatever ``n`` is."""
    if not isinstance(design, SequentialDesign):
        raise fail("design", design, "must be a SequentialDesign")
    look = integer("look", look, 1, design.looks)
    b, c, n = _counts(b, c, n)
    z, zeq = float(design.bounds()[look - 1]), float(design.equivalence_bounds()[look - 1])
    rci = score_rci if design.interval == "score" else paired_rci
    _, low, high = rci(b, c, n, z)
    _, eq_low, eq_high = rci(b, c, n, zeq)
    code = int(_codes(design.interval, b, c, n, z, zeq, design.margin, look == design.looks))
    return Look(look=look, n=n, b=b, c=c, difference=(b - c) / n, low=float(low),
                high=float(high), eq_low=float(eq_low), eq_high=float(eq_high),
                bound=float(z), decision=DECISIONS[code], eq_bound=float(zeq))


def run_looks(design: SequentialDesign, b_per_look: Sequence[int], c_per_look: Sequence[int],
              n_per_look: Sequence[int]) -> tuple[Look, ...]:
    """The looks of one comparison from the counts added at each look (not cumulative): the
    counts are summed look by look and the looks end at the first decision (or with the
    last look given, when none decides). At most ``design.looks`` looks."""
    lengths = {len(b_per_look), len(c_per_look), len(n_per_look)}
    if len(lengths) != 1 or not 1 <= len(b_per_look) <= design.looks:
        raise fail("b_per_look, c_per_look, n_per_look", (len(b_per_look), len(c_per_look),
                   len(n_per_look)), f"must have one common length in [1, {design.looks}]")
    out: list[Look] = []
    b = c = n = 0
    for k, (db, dc, dn) in enumerate(zip(b_per_look, c_per_look, n_per_look, strict=True)):
        db, dc, dn = _counts(db, dc, dn, (f"b_per_look[{k}]", f"c_per_look[{k}]",
                                          f"n_per_look[{k}]"))
        b, c, n = b + db, c + dc, n + dn
        out.append(decide(design, k + 1, b, c, n))
        if out[-1].decision != "continue":
            break
    return tuple(out)


# ---------------------------------------------------------------------------------------------
# simulation of the operating characteristics

@dataclass(frozen=True)
class Operating:
    """Simulated operating characteristics of a design at the truth (p_b, p_c): the rate of
    each final decision (with its Wilson 95% interval) over ``reps`` comparisons, and the pairs
    they used."""

    truth: tuple[float, float]  # (p_b, p_c): P(only A safe), P(only B safe) per pair
    reps: int
    superior: Rate
    inferior: Rate
    equivalent: Rate
    undecided: Rate
    mean_pairs: float
    pairs_quantiles: tuple[float, float, float]  # 10%, 50% and 90% quantiles of pairs used
    stopped: tuple[int, ...]  # comparisons ending at each look
    max_pairs: int

    @property
    def difference(self) -> float:
        """True difference d = p_b - p_c."""
        return self.truth[0] - self.truth[1]


def _truth(p_b: object, p_c: object) -> tuple[float, float]:
    pb = real("p_b", p_b, 0.0, maximum=1.0)
    pc = real("p_c", p_c, 0.0, maximum=1.0 - pb)
    return pb, pc


def _simulate_codes(design: SequentialDesign, p_b: float, p_c: float, reps: int,
                    rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Final decision codes and stopping looks (0-based) of ``reps`` simulated comparisons:
    per look the counts (b, c, concordant) are one multinomial draw per replication."""
    K, m = design.looks, design.pairs_per_look
    z, zeq = design.bounds(), design.equivalence_bounds()
    n = m * np.arange(1, K + 1, dtype=float)
    last = np.arange(K) == K - 1
    draws = rng.multinomial(m, [p_b, p_c, max(0.0, 1.0 - p_b - p_c)], size=(reps, K))
    cum = np.cumsum(draws[:, :, :2], axis=1, dtype=np.int64).astype(float)
    b, c = cum[:, :, 0], cum[:, :, 1]
    codes = _codes(design.interval, b, c, n, z, zeq, design.margin, last)
    stop = np.argmax(codes != _CONTINUE, axis=1)  # the last look always decides
    return codes[np.arange(reps), stop], stop


def simulate(design: SequentialDesign, p_b: float, p_c: float, reps: int,
             rng: np.random.Generator) -> Operating:
    """Operating characteristics of ``design`` over ``reps`` simulated comparisons whose pairs
    are discordant for A with probability ``p_b`` and for B with ``p_c`` (d = p_b - p_c).
    Every draw comes from ``rng``; the same generator state gives the same result."""
    if not isinstance(design, SequentialDesign):
        raise fail("design", design, "must be a SequentialDesign")
    p_b, p_c = _truth(p_b, p_c)
    reps = integer("reps", reps, 1, MAX_REPS)
    if not isinstance(rng, np.random.Generator):
        raise fail("rng", rng, "must be a numpy.random.Generator")
    codes, stops = [], []
    for start in range(0, reps, _CHUNK):
        cd, st = _simulate_codes(design, p_b, p_c, min(_CHUNK, reps - start), rng)
        codes.append(cd)
        stops.append(st)
    code, stop = np.concatenate(codes), np.concatenate(stops)
    pairs = (stop + 1) * design.pairs_per_look
    count = np.bincount(code, minlength=len(DECISIONS))
    q = np.quantile(pairs, [0.1, 0.5, 0.9])
    return Operating(
        truth=(p_b, p_c), reps=reps, superior=Rate(int(count[_SUPERIOR]), reps),
        inferior=Rate(int(count[_INFERIOR]), reps),
        equivalent=Rate(int(count[_EQUIVALENT]), reps),
        undecided=Rate(int(count[_UNDECIDED]), reps), mean_pairs=float(pairs.mean()),
        pairs_quantiles=(float(q[0]), float(q[1]), float(q[2])),
        stopped=tuple(int(v) for v in np.bincount(stop, minlength=design.looks)),
        max_pairs=design.max_pairs)


def expected_pairs(design: SequentialDesign, p_b: float, p_c: float, reps: int,
                   rng: np.random.Generator) -> float:
    """Mean number of pairs a comparison uses at the truth (p_b, p_c), by simulation."""
    return simulate(design, p_b, p_c, reps, rng).mean_pairs


# ---------------------------------------------------------------------------------------------
# planning

def _discordance(value: object, margin: float) -> float:
    psi = real("discordance", value, 0.0, strict=True, maximum=1.0)
    if psi < margin:
        raise fail("discordance", value, f"must be >= margin = {margin:g} (a difference d "
                   "needs at least |d| discordant pairs per pair) and <= 1")
    return psi


def _normal_pairs(design: SequentialDesign, psi: float) -> float:
    """Normal-approximation pairs for both powers: superiority at d = margin (variance
    psi - margin^2 per pair) and equivalence at d = 0 (variance psi)."""
    delta, pw = design.margin, design.power
    sup = (design.bounds()[-1] + norm.ppf(pw)) ** 2 * (psi - delta**2) / delta**2
    eq = (design.equivalence_bounds()[-1] + norm.ppf((1 + pw) / 2)) ** 2 * psi / delta**2
    return max(sup, eq)


def _powered(design: SequentialDesign, psi: float) -> bool:
    """Whether the simulated powers' Wilson lower limits reach ``design.power``: superior at
    d = +margin, equivalent at d = 0 (seeded: deterministic)."""
    rng = np.random.default_rng(PLAN_SEED)
    delta = design.margin
    sup = simulate(design, (psi + delta) / 2, max(0.0, (psi - delta) / 2), PLAN_REPS, rng)
    if sup.superior.low < design.power:
        return False
    return simulate(design, psi / 2, psi / 2, PLAN_REPS, rng).equivalent.low >= design.power


def plan_pairs(margin: float, discordance: float, alpha: float = 0.05, power: float = 0.8,
               looks: int = 4, comparisons: int = 1) -> int:
    """The smallest maximum number of pairs (a multiple of ``looks``) with
    P(superior | d = margin) >= power and P(equivalent | d = 0) >= power, at the discordance
    rate ``discordance`` = P(a pair is discordant) in [margin, 1].

    The normal approximation n = (c_K + z_power)^2 (psi - margin^2) / margin^2 (superiority)
    and (c'_K + z_{(1+power)/2})^2 psi / margin^2 (equivalence; c'_K the equivalence bound)
    is the start; a bisection over the pairs per look then finds the smallest size whose
    simulated powers (:data:`PLAN_REPS` replications per truth, seed :data:`PLAN_SEED`) have
    Wilson 95% lower limits at or above ``power``."""
    design = SequentialDesign(looks, 1, margin, alpha, comparisons, power)
    psi = _discordance(discordance, design.margin)
    start = max(1, math.ceil(_normal_pairs(design, psi) / design.looks))

    def ok(per_look: int) -> bool:
        return _powered(replace(design, pairs_per_look=per_look), psi)

    if ok(start):  # bracket: hi powered, lo not (or 0)
        hi, lo = start, start // 2
        while lo > 0 and ok(lo):
            hi, lo = lo, lo // 2
    else:
        lo, hi = start, 2 * start
        while not ok(hi):
            if hi >= MAX_PAIRS_PER_LOOK:
                raise fail("margin", margin, "needs more than "
                           f"{MAX_PAIRS_PER_LOOK} pairs per look; widen it")
            lo, hi = hi, min(2 * hi, MAX_PAIRS_PER_LOOK)
    while hi - lo > 1:
        mid = (lo + hi) // 2
        lo, hi = (lo, mid) if ok(mid) else (mid, hi)
    return hi * design.looks


def detectable(n: int, discordance: float, alpha: float = 0.05, power: float = 0.8,
               looks: int = 4, comparisons: int = 1) -> float:
    """The smallest difference d that a design of ``n`` pairs in ``looks`` equal looks calls
    superior with probability ``power`` (normal approximation at the last look's bound c_K:
    n = (c_K + z_power)^2 (psi - d^2) / d^2, so d = (c_K + z_power) sqrt(psi / (n +
    (c_K + z_power)^2))), at discordance rate psi = ``discordance`` in (0, 1]. A value above
    ``discordance`` means no possible difference reaches the power (|d| <= psi)."""
    n = integer("n", n, 1)
    psi = real("discordance", discordance, 0.0, strict=True, maximum=1.0)
    alpha, power = _alpha(alpha), _power(power)
    looks, comparisons = _looks(looks), _comparisons(comparisons)
    q = obrien_fleming_bounds(equal_fractions(looks), alpha / comparisons)[-1] + norm.ppf(power)
    return float(q * math.sqrt(psi / (n + q * q)))

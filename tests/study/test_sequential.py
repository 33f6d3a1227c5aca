"""Group-sequential paired comparisons: boundaries against published values and a
multivariate-normal oracle, the intervals against hand computations, every decision, and the
promised error rates and powers by seeded simulation (with a broken boundary that must fail)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import pytest
from scipy.optimize import minimize_scalar
from scipy.stats import multivariate_normal, norm

from workbench.study.sequential import (
    PLAN_REPS,
    PLAN_SEED,
    Look,
    SequentialDesign,
    decide,
    detectable,
    equal_fractions,
    expected_pairs,
    obrien_fleming_bounds,
    obrien_fleming_spending,
    paired_rci,
    plan_pairs,
    run_looks,
    score_rci,
    simulate,
    spending_bounds,
)
from workbench.study.summary import Rate

Z975 = norm.isf(0.025)


def close(actual, expected, rel: float) -> None:
    """Per-element relative tolerance (no absolute floor)."""
    np.testing.assert_allclose(actual, expected, rtol=rel, atol=0.0)


# ---------------------------------------------------------------------------------------------
# boundaries

# Lan-DeMets O'Brien-Fleming-type spending, K = 5 equal looks, two-sided 0.05, as tabulated by
# the usual software (ldbounds, gsDesign: alpha / 2 = 0.025 per side, each side spent by
# 2 - 2 Phi(z_{1 - 0.025/2} / sqrt(t))). Recomputed here by root-finding on Genz's
# multivariate-normal probabilities (4.876885, 3.357012, 2.680280, 2.289817, 2.031032), and the
# crossing probabilities of these values by the Simpson-grid routines h1/hupdate of the PyPI
# package gsdesign 0.1.5 give the cumulative spending to 1e-6 relative.
PUBLISHED_PER_SIDE = [4.8769, 3.3569, 2.6803, 2.2898, 2.0310]
# The other convention, alpha(t) = 2 - 2 Phi(z_{0.975} / sqrt(t)) spent on |Z| (not the
# module's): by root-finding on Genz's probabilities (scipy multivariate_normal.cdf), and
# confirmed with gsdesign's h1/hupdate (cumulative crossing probabilities equal alpha(t_k) to
# 1e-5 relative).
TWO_SIDED = [4.382613, 3.099727, 2.553355, 2.253848, 2.063501]


def test_bounds_match_published_values_of_both_spending_conventions():
    t = np.array(equal_fractions(5))
    close(obrien_fleming_bounds(t, 0.05), PUBLISHED_PER_SIDE, 2e-3)
    close(obrien_fleming_bounds(t, 0.05), [4.876885, 3.357012, 2.680280, 2.289817, 2.031032],
          2e-6)
    on_abs = 2.0 * norm.sf(Z975 / np.sqrt(t))
    close(spending_bounds(t, on_abs), TWO_SIDED, 2e-6)
    # the first bound is analytic: P(|Z_1| >= c_1) = alpha(t_1)
    spent = 4.0 * norm.sf(norm.isf(0.0125) / math.sqrt(0.2))
    close(obrien_fleming_bounds(t, 0.05)[0], norm.isf(spent / 2.0), 1e-12)


def test_one_look_is_the_fixed_sample_test():
    close(obrien_fleming_bounds([1.0], 0.05), [Z975], 1e-12)
    close(SequentialDesign(1, 10).bounds(), [Z975], 1e-12)
    close(SequentialDesign(1, 10, comparisons=4).equivalence_bounds(), [norm.isf(0.0125)],
          1e-12)


def _crossings(t: np.ndarray, c: np.ndarray) -> np.ndarray:
    """P(|Z_j| < c_j for j < k, |Z_k| >= c_k) by Genz's algorithm, corr(Z_i, Z_j) =
    sqrt(t_i / t_j) (i <= j): twice the upper crossing, by symmetry."""
    corr = np.sqrt(np.minimum.outer(t, t) / np.maximum.outer(t, t))
    out = []
    for k in range(len(t)):
        mvn = multivariate_normal(np.zeros(k + 1), corr[:k + 1, :k + 1], abseps=1e-12,
                                  releps=1e-7, maxpts=10**6, seed=1)
        out.append(2 * mvn.cdf(np.append(c[:k], np.inf), lower_limit=np.append(-c[:k], c[k])))
    return np.array(out)


@pytest.mark.parametrize("fractions, alpha", [(equal_fractions(5), 0.05),
                                              ((0.25, 0.6, 1.0), 0.0125)])
def test_crossing_probabilities_equal_the_spending_increments(fractions, alpha):
    t = np.array(fractions)
    c = obrien_fleming_bounds(t, alpha)
    spent = np.diff(np.concatenate([[0.0], obrien_fleming_spending(t, alpha)]))
    close(_crossings(t, c), spent, 1e-5)
    assert np.all(np.diff(c) < 0)  # O'Brien-Fleming: strict early, near z at the end


def test_design_bounds_split_alpha_over_the_comparisons():
    d = SequentialDesign(4, 30, alpha=0.05, comparisons=4)
    t = equal_fractions(4)
    close(d.bounds(), obrien_fleming_bounds(t, 0.0125), 1e-12)
    close(d.equivalence_bounds(), obrien_fleming_bounds(t, 0.025), 1e-12)
    assert d.max_pairs == 120 and d.fractions == (0.25, 0.5, 0.75, 1.0)
    d.bounds()[:] = 0.0  # a cached array is never handed out
    close(d.bounds(), obrien_fleming_bounds(t, 0.0125), 1e-12)


def test_bad_fractions_and_spending_are_refused():
    for bad in ([0.5, 0.9], [0.5, 0.5, 1.0], [0.0, 1.0], [[1.0]], [], ["a"]):
        with pytest.raises(ValueError, match=r"^fractions = "):
            obrien_fleming_bounds(bad, 0.05)
    with pytest.raises(ValueError, match=r"^alpha = "):
        obrien_fleming_bounds([1.0], 1.0)
    with pytest.raises(ValueError, match=r"^spent = "):
        spending_bounds([0.5, 1.0], [0.02, 0.01])


# ---------------------------------------------------------------------------------------------
# intervals

def test_agresti_min_interval_by_hand():
    # b = 10, c = 3, n = 50: b' = 10.5, c' = 3.5, n' = 52, d~ = 7/52,
    # se^2 = (14/52 - (7/52)^2) / 52 = 679 / 52^3
    d, low, high = paired_rci(10, 3, 50, 1.96)
    se = math.sqrt(679 / 52**3)
    close([d, low, high], [7 / 52, 7 / 52 - 1.96 * se, 7 / 52 + 1.96 * se], 1e-12)
    # no discordant pair: d~ = 0, se = sqrt((1/52) / 52) = 1/52, never a zero-width interval
    close(paired_rci(0, 0, 50, 2.0)[1:], [-2 / 52, 2 / 52], 1e-12)
    # clipped at 1: b = n = 5, d~ = 5/7, se^2 = (6/7 - 25/49) / 7 = 17/343
    d, low, high = paired_rci(5, 0, 5, 3.0)
    close([d, low], [5 / 7, 5 / 7 - 3 * math.sqrt(17 / 343)], 1e-12)
    assert high == 1.0 and 5 / 7 + 3 * math.sqrt(17 / 343) > 1
    assert paired_rci(0, 5, 5, 3.0)[1] == -1.0


def _score_by_likelihood(b: int, c: int, n: int, d0: float) -> float:
    """The score statistic from its definition: the constrained MLE of p_c under d = d0 by
    numerical maximisation, the variance n (p_b + p_c - d0^2) at it."""
    r = n - b - c

    def nll(p: float) -> float:
        return -sum(k * math.log(q) for k, q in ((b, p + d0), (c, p), (r, 1 - 2 * p - d0)) if k)

    lo, hi = max(0.0, -d0), (1.0 - d0) / 2.0
    p = minimize_scalar(nll, bounds=(lo + 1e-13, hi - 1e-13), method="bounded",
                        options={"xatol": 1e-13}).x
    return (b - c - n * d0) / math.sqrt(n * (2 * p + d0 - d0 * d0))


@pytest.mark.parametrize("b, c, n, z", [(10, 3, 50, 1.96), (1, 12, 40, 2.5), (7, 0, 30, 3.0),
                                        (40, 35, 300, 2.04)])
def test_score_interval_inverts_the_score_test(b, c, n, z):
    d, low, high = score_rci(b, c, n, z)
    assert d == (b - c) / n and -1 < low < d < high < 1
    close([_score_by_likelihood(b, c, n, low), _score_by_likelihood(b, c, n, high)], [z, -z],
          1e-6)


def test_score_interval_special_tables():
    # at d0 = 0 the score statistic is McNemar's (b - c) / sqrt(b + c): 0 is inside iff
    # |b - c| / sqrt(b + c) < z
    assert score_rci(20, 8, 100, 2.0)[1] > 0 and 12 / math.sqrt(28) > 2.0
    assert score_rci(18, 8, 100, 2.0)[1] < 0 and 10 / math.sqrt(26) < 2.0
    # every pair concordant: Z(d0) = -sqrt(n d0 / (1 - d0)), so +-z^2 / (n + z^2)
    close(score_rci(0, 0, 50, 2.0)[1:], [-4 / 54, 4 / 54], 1e-9)
    # every pair only A safe: the upper limit is 1, the lower one by hand from
    # Z(d0) = sqrt(n (1 - d0) / (1 + d0)) = z: d0 = (n - z^2) / (n + z^2)
    d, low, high = score_rci(50, 0, 50, 1.96)
    assert d == 1.0 and high == 1.0
    close(low, (50 - 1.96**2) / (50 + 1.96**2), 1e-9)
    assert score_rci(0, 50, 50, 1.96)[2] == pytest.approx(-low, rel=1e-9)


def test_bad_counts_are_refused_with_their_names():
    with pytest.raises(ValueError, match=r"^n = "):
        paired_rci(0, 0, 0, 1.0)
    with pytest.raises(ValueError, match=r"^b = "):
        score_rci(11, 0, 10, 1.0)
    with pytest.raises(ValueError, match=r"^c = "):
        paired_rci(6, 5, 10, 1.0)
    with pytest.raises(ValueError, match=r"^z = "):
        score_rci(1, 1, 10, 0.0)


# ---------------------------------------------------------------------------------------------
# decisions

DESIGN = SequentialDesign(looks=4, pairs_per_look=50)  # bounds 3.92 2.77 2.30 2.04


@pytest.mark.parametrize("interval", ["score", "agresti-min"])
@pytest.mark.parametrize("look, b, c, n, expect", [
    (2, 30, 5, 100, "superior"),     # d = 0.25, the interval above 0
    (2, 5, 30, 100, "inferior"),
    (3, 14, 14, 150, "equivalent"),  # d = 0, the TOST interval inside (-0.1, 0.1)
    (1, 5, 5, 50, "continue"),       # the first look's wide interval
    (4, 30, 20, 200, "undecided"),   # d = 0.05 at the last look: neither
])
def test_every_decision_is_reached(interval, look, b, c, n, expect):
    design = replace(DESIGN, interval=interval)
    got = decide(design, look, b, c, n)
    assert got.decision == expect
    rci = score_rci if interval == "score" else paired_rci
    assert (got.low, got.high) == rci(b, c, n, design.bounds()[look - 1])[1:]
    assert (got.eq_low, got.eq_high) == rci(b, c, n, design.equivalence_bounds()[look - 1])[1:]
    assert got.difference == (b - c) / n and got.bound == design.bounds()[look - 1]


def test_a_superior_look_inside_the_margin_reports_superior():
    look = decide(SequentialDesign(2, 1000), 2, 150, 50, 2000)  # d = 0.05
    assert look.decision == "superior" and look.low > 0
    assert -0.1 < look.eq_low and look.eq_high < 0.1  # equivalent too: the interval shows it


@pytest.mark.parametrize("interval", ["score", "agresti-min"])
def test_decisions_read_off_the_intervals(interval):
    rng = np.random.default_rng(3)
    design = replace(DESIGN, interval=interval)
    for _ in range(400):
        look = int(rng.integers(1, 5))
        n = 50 * look
        b = int(rng.integers(0, 40))
        c = int(rng.integers(0, min(40, n - b) + 1))
        got = decide(design, look, b, c, n)
        expect = ("superior" if got.low > 0 else "inferior" if got.high < 0 else "equivalent"
                  if -0.1 < got.eq_low and got.eq_high < 0.1 else
                  "undecided" if look == 4 else "continue")
        assert got.decision == expect, got


def test_run_looks_accumulates_and_stops_at_the_first_decision():
    looks = run_looks(DESIGN, [5, 25, 10, 10], [4, 1, 10, 10], [50, 50, 50, 50])
    assert [lk.decision for lk in looks] == ["continue", "superior"]
    assert (looks[1].b, looks[1].c, looks[1].n) == (30, 5, 100)
    assert looks[1] == decide(DESIGN, 2, 30, 5, 100)
    assert isinstance(looks[0], Look)
    so_far = run_looks(DESIGN, [5], [5], [50])  # fewer looks than planned: ends undecided-free
    assert [lk.decision for lk in so_far] == ["continue"]
    with pytest.raises(ValueError, match="common length"):
        run_looks(DESIGN, [1] * 5, [1] * 5, [50] * 5)
    with pytest.raises(ValueError, match=r"^c_per_look\[1\] = "):
        run_looks(DESIGN, [1, 1], [1, 60], [50, 50])
    with pytest.raises(ValueError, match=r"^look = "):
        decide(DESIGN, 5, 0, 0, 10)


# ---------------------------------------------------------------------------------------------
# the promises, by simulation

REPS = 100_000  # Wilson half-width about 0.0014 at a rate of 0.05


def _truths(psi: float, margin: float) -> dict[str, tuple[float, float]]:
    return {"null": (psi / 2, psi / 2), "plus": ((psi + margin) / 2, (psi - margin) / 2),
            "minus": ((psi - margin) / 2, (psi + margin) / 2), "clear": (psi, 0.0)}


@pytest.mark.parametrize("psi, m", [(0.3, 1), (0.3, 4), (0.1, 1), (0.1, 4)])
def test_planned_design_keeps_its_promises(psi, m):
    n = plan_pairs(0.10, discordance=psi, comparisons=m)
    design = SequentialDesign(looks=4, pairs_per_look=n // 4, comparisons=m)
    assert n % 4 == 0 and design.max_pairs == n
    level = 0.05 / m
    rng = np.random.default_rng(2024 + m)
    op = {k: simulate(design, pb, pc, REPS, rng) for k, (pb, pc) in _truths(psi, 0.1).items()}
    type1 = Rate(op["null"].superior.k + op["null"].inferior.k, REPS)
    print(f"\npsi {psi} m {m}: max pairs {n}, type I {type1.value:.4f} [{type1.low:.4f}, "
          f"{type1.high:.4f}], power {op['plus'].superior.value:.4f}, equivalence power "
          f"{op['null'].equivalent.value:.4f}, wrong equivalence "
          f"{op['plus'].equivalent.value:.4f} / {op['minus'].equivalent.value:.4f}, mean pairs "
          f"{op['null'].mean_pairs:.0f} (null) {op['plus'].mean_pairs:.0f} (margin) "
          f"{op['clear'].mean_pairs:.0f} (d = {psi})")
    # a wrong directional claim under d = 0 (either direction) at most alpha / m
    assert type1.value <= level and type1.high < 1.3 * level
    # a wrong equivalence claim at d = +-margin at most alpha / m on each side
    for side in ("plus", "minus"):
        assert op[side].equivalent.value <= level and op[side].equivalent.high < 1.3 * level
    # the powers the plan promised
    assert op["plus"].superior.value >= 0.8 and op["minus"].inferior.value >= 0.8
    assert op["null"].equivalent.value >= 0.8
    # a clear effect stops early
    assert op["clear"].superior.value > 0.95 and op["clear"].mean_pairs < 0.8 * n


@dataclass(frozen=True)
class NaiveDesign(SequentialDesign):
    """A broken design: the fixed-sample bound z_{1 - alpha/2} at every look."""

    def bounds(self) -> np.ndarray:
        return np.full(self.looks, norm.isf(self.alpha / self.comparisons / 2))

    def equivalence_bounds(self) -> np.ndarray:
        return np.full(self.looks, norm.isf(self.alpha / self.comparisons))


def test_a_naive_constant_bound_fails_the_type_one_check():
    n = plan_pairs(0.10, discordance=0.3, looks=5)
    good = SequentialDesign(looks=5, pairs_per_look=n // 5)
    naive = NaiveDesign(looks=5, pairs_per_look=n // 5)
    ok, broken = (simulate(d, 0.15, 0.15, REPS, np.random.default_rng(11)) for d in (good, naive))
    rate = Rate(broken.superior.k + broken.inferior.k, REPS)
    assert Rate(ok.superior.k + ok.inferior.k, REPS).low < 0.05  # the spending bounds: 0.05
    assert rate.low > 0.05 and rate.value > 0.1  # repeated looks at 1.96: about 0.14 by theory


def test_agresti_min_intervals_break_the_equivalence_error_when_discordance_is_one_sided():
    # discordance 0.1 at d = margin = 0.1: every discordant pair only A safe. The Wald
    # interval's se shrinks with the count, so too many runs look equivalent; the score
    # intervals keep alpha / m (test above)
    n = plan_pairs(0.10, discordance=0.1, comparisons=4)
    design = SequentialDesign(4, n // 4, comparisons=4, interval="agresti-min")
    op = simulate(design, 0.1, 0.0, REPS, np.random.default_rng(5))
    assert op.equivalent.low > 1.5 * 0.05 / 4


# ---------------------------------------------------------------------------------------------
# planning

@pytest.mark.parametrize("psi, m", [(0.3, 1), (0.1, 4)])
def test_plan_is_the_smallest_size_whose_simulated_powers_reach_the_target(psi, m):
    n = plan_pairs(0.10, psi, comparisons=m)
    assert n == plan_pairs(0.10, psi, comparisons=m)  # seeded: deterministic

    def powered(per_look: int) -> bool:
        rng = np.random.default_rng(PLAN_SEED)
        design = SequentialDesign(4, per_look, comparisons=m)
        sup = simulate(design, (psi + 0.1) / 2, (psi - 0.1) / 2, PLAN_REPS, rng).superior.low
        return sup >= 0.8 and simulate(design, psi / 2, psi / 2, PLAN_REPS,
                                       rng).equivalent.low >= 0.8

    assert powered(n // 4) and not powered(n // 4 - 1)
    # near the normal approximation's size (which is low by up to a quarter at small counts)
    cq = SequentialDesign(4, 1, comparisons=m).equivalence_bounds()[-1] + norm.ppf(0.9)
    assert 0.95 < n / (cq**2 * psi / 0.01) < 1.3


def test_detectable_difference_has_the_power_by_simulation():
    d = detectable(400, 0.3)
    # the normal approximation inverted: n = (c_K + z_power)^2 (psi - d^2) / d^2
    q = SequentialDesign(4, 100).bounds()[-1] + norm.ppf(0.8)
    close(q**2 * (0.3 - d**2) / d**2, 400, 1e-9)
    op = simulate(SequentialDesign(4, 100, margin=d), (0.3 + d) / 2, (0.3 - d) / 2, 20_000,
                  np.random.default_rng(8))
    assert 0.78 <= op.superior.value <= 0.86  # early looks add a little power
    assert detectable(1600, 0.3) < d and detectable(400, 0.3, comparisons=4) > d


def test_expected_pairs_is_the_simulated_mean():
    design = SequentialDesign(4, 25)
    got = expected_pairs(design, 0.3, 0.0, 5000, np.random.default_rng(1))
    assert got == simulate(design, 0.3, 0.0, 5000, np.random.default_rng(1)).mean_pairs
    assert 25 <= got < 100


# ---------------------------------------------------------------------------------------------
# input checks and determinism

@pytest.mark.parametrize("field, bad", [
    ("looks", 0), ("looks", 101), ("looks", 2.0), ("looks", True),
    ("pairs_per_look", 0), ("pairs_per_look", 1.5),
    ("margin", 0.0), ("margin", 1.0), ("margin", float("nan")),
    ("alpha", 0.0), ("alpha", 0.5), ("alpha", "0.05"),
    ("comparisons", 0), ("comparisons", None),
    ("power", 0.5), ("power", 1.0),
    ("interval", "wald"), ("interval", 1),
])
def test_each_design_field_is_refused_by_name(field, bad):
    kwargs = {"looks": 4, "pairs_per_look": 10, field: bad}
    with pytest.raises(ValueError, match=rf"^{field} = "):
        SequentialDesign(**kwargs)


def test_planning_and_simulation_inputs_are_refused_by_name():
    with pytest.raises(ValueError, match=r"^discordance = "):
        plan_pairs(0.2, 0.1)
    with pytest.raises(ValueError, match=r"^power = "):
        detectable(100, 0.3, power=1.2)
    with pytest.raises(ValueError, match=r"^n = "):
        detectable(0, 0.3)
    with pytest.raises(ValueError, match=r"^p_c = "):
        simulate(DESIGN, 0.6, 0.5, 10, np.random.default_rng(0))
    with pytest.raises(ValueError, match=r"^rng = "):
        simulate(DESIGN, 0.1, 0.1, 10, 0)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"^reps = "):
        simulate(DESIGN, 0.1, 0.1, 0, np.random.default_rng(0))


def test_same_seed_same_operating_characteristics():
    a, b, c = (simulate(DESIGN, 0.2, 0.1, 3000, np.random.default_rng(s)) for s in (9, 9, 10))
    assert a == b and a != c
    assert a.reps == 3000 and a.truth == (0.2, 0.1) and a.difference == pytest.approx(0.1)
    assert sum(a.stopped) == 3000 and a.max_pairs == 200
    total = a.superior.k + a.inferior.k + a.equivalent.k + a.undecided.k
    assert total == 3000 and a.pairs_quantiles[0] <= a.pairs_quantiles[1] <= a.pairs_quantiles[2]

"""Typed summary of a run, computed from the tidy tables ``steps`` (one row per control step)
and ``episodes`` only: fractions holding with Wilson intervals, slack quantiles and
global/local ratios per (variance, test, constants, stratum) (assumptions §11.3), per-variance
facts, and the failures (:mod:`~studies.free_energy_bound.failures`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy.stats import norm

from studies.free_energy_bound.config import CONSTANTS
from studies.free_energy_bound.failures import (
    Failure,
    T2EFailures,
    TransitionFailures,
    t1_failures_when_safe,
)
from workbench.bound import CheckSummary
from workbench.bound.tightness import Comparison, Tightness
from workbench.study import Rate, Spread

# assumptions §11.3 (a), (b) and the nominal-differs split; a transition check (t, t+1) belongs
# to the strata of step t
STRATA = {"all": None, "all_real_safe": ("all_real_safe", True),
          "some_real_crashed": ("all_real_safe", False), "admissible": ("fallback_used", False),
          "fallback": ("fallback_used", True), "nominal_differs": ("nominal_differs", True),
          "nominal_is_real": ("nominal_differs", False)}


def in_stratum(df: pd.DataFrame, name: str) -> np.ndarray:
    s = STRATA[name]
    return np.ones(len(df), bool) if s is None else df[s[0]].to_numpy(bool) == s[1]


def evaluated(df: pd.DataFrame, test: str, constants: str) -> np.ndarray:
    """Steps where the check exists (holds is 1 or 0, not nan)."""
    return np.isfinite(df[f"{test}_{constants}_holds"].to_numpy(float))


def median_ratio(num: np.ndarray, den: np.ndarray) -> float:
    ok = den > 0
    return float(np.median(num[ok] / den[ok])) if ok.any() else float("nan")


@dataclass(frozen=True)
class Row(CheckSummary):
    """One test with one set of constants at one variance over one stratum's steps (the
    estimators' :class:`~workbench.bound.CheckSummary` fields, plus the variance)."""

    variance: float

    @classmethod
    def of(cls, df: pd.DataFrame, test: str, c: str, variance: float, stratum: str) -> Row | None:
        d = df[evaluated(df, test, c) & in_stratum(df, stratum)]
        if d.empty:
            return None
        rate = Rate.of(d[f"{test}_{c}_holds"].to_numpy() == 1.0)
        q = np.quantile(d[f"{test}_{c}_slack"].to_numpy(float), (0.05, 0.5, 0.95))
        loc, glo = (d[f"{test}_{k}_rhs"].to_numpy(float) for k in ("local", "global"))
        tloc, tglo = (d[f"{test}_{k}_term"].to_numpy(float) for k in ("local", "global"))
        return cls(test, c, stratum, rate.n, rate.k, rate.value, (rate.low, rate.high),
                   *map(float, q), median_ratio(glo, loc), median_ratio(tglo, tloc),
                   variance=variance)


@dataclass(frozen=True)
class TightRow(Tightness):
    """How tight one test is with one set of constants at one variance (nan: all variances
    pooled), over the informative steps (R > 0) where it was evaluated
    (:class:`~workbench.bound.tightness.Tightness`)."""

    test: str = ""
    constants: str = ""
    variance: float = float("nan")

    @classmethod
    def at(cls, df: pd.DataFrame, test: str, c: str, variance: float) -> TightRow:
        t = Tightness.of(df[f"{test}_{c}_lhs"], df[f"{test}_{c}_rhs"], df["R"])
        return cls(**{k: getattr(t, k) for k in t.__dataclass_fields__}, test=test,
                   constants=c, variance=variance)


# the decided comparisons (assumptions §11.4): threshold, margin and family level
THRESHOLD = 10.0
MARGIN = 0.05
LEVEL = 0.05


@dataclass(frozen=True)
class Decided(Comparison):
    """A paired comparison of two sets of constants on one test, all variances pooled
    (:class:`~workbench.bound.tightness.Comparison`; ``first`` is A, ``second`` B)."""

    test: str = ""
    first: str = ""
    second: str = ""
    level: float = LEVEL  # family-wise, Bonferroni over the comparisons of the run

    @classmethod
    def at(cls, df: pd.DataFrame, test: str, a: str, b: str, m: int) -> Decided | None:
        sides = [df[f"{test}_{k}"].to_numpy(float) for k in (f"{a}_lhs", f"{a}_rhs", f"{b}_rhs")]
        if not ((df["R"].to_numpy(float) > 0) & np.all(np.isfinite(sides), axis=0)).any():
            return None
        z = float(norm.ppf(1 - LEVEL / (2 * m)))
        c = Comparison.of(df[f"{test}_{a}_lhs"], df[f"{test}_{a}_rhs"], df[f"{test}_{b}_rhs"],
                          df["R"], THRESHOLD, z, MARGIN)
        return cls(**{k: getattr(c, k) for k in c.__dataclass_fields__}, test=test, first=a,
                   second=b)


@dataclass(frozen=True)
class VariantFailures:
    """Where the sampled-tube bound fails on one test, over the informative steps (R > 0) where
    it was evaluated, all variances pooled: failures, those at a step where some real sample
    crashed (outside the lemma's premise of a forward-invariant safe set), those whose
    nominal state was not admissible (F̂_nom > alpha; at t+1 for T3c, T3d), and the check
    over the informative steps where every real sample stayed safe."""

    test: str
    n: int
    n_failed: int
    n_failed_crashed: int
    n_failed_premise: int
    n_safe: int
    n_safe_holding: int

    @classmethod
    def of(cls, df: pd.DataFrame, test: str) -> VariantFailures:
        h = df[f"{test}_sampled_holds"].to_numpy(float)
        use = np.isfinite(h) & (df["R"].to_numpy(float) > 0)
        bad = use & (h == 0.0)
        safe = df["all_real_safe"].to_numpy(bool)
        adm = df["nominal_admissible_next" if test in ("T3c", "T3d")
                 else "nominal_admissible"].to_numpy(bool)
        return cls(test, int(use.sum()), int(bad.sum()), int((bad & ~safe).sum()),
                   int((bad & ~adm).sum()), int((use & safe).sum()),
                   int((use & safe & (h == 1.0)).sum()))


@dataclass(frozen=True)
class VarianceFacts:
    """Counts and magnitudes at one variance (medians over steps unless said)."""

    variance: float
    n_episodes: int
    n_crashed: int
    n_steps: int
    n_nominal_differs: int
    n_all_real_safe: int
    n_fallback: int
    n_secant_ok: int
    R: Spread
    R99_median: float
    L_q_local: Spread  # over steps with R > 0 (where the constant enters the bound)
    L_phi_local: Spread
    L_q_global: float
    L_phi_global: float
    L_q_ratio_median: float  # global / local L_q over steps with R > 0
    delta_local: Spread  # over steps with R > 0
    F_real_abs_median: float  # |F̂_real| over the same steps (the scale δ is compared with)
    E_median: float
    D_F_median: float

    @classmethod
    def of(cls, df: pd.DataFrame, ep: pd.DataFrame, variance: float) -> VarianceFacts:
        act = df[df["R"].to_numpy(float) > 0]
        return cls(variance, len(ep), int(ep["crashed"].sum()), len(df),
                   int(df["nominal_differs"].sum()), int(df["all_real_safe"].sum()),
                   int(df["fallback_used"].sum()), int(df["secant_ok"].sum()), Spread.of(df["R"]),
                   float(df["R99"].median()), Spread.of(act["L_q"]), Spread.of(act["L_phi"]),
                   float(df["L_q_global"].max()), float(df["L_phi_global"].max()),
                   median_ratio(act["L_q_global"].to_numpy(float), act["L_q"].to_numpy(float)),
                   Spread.of(act["delta_local"]),
                   float(np.abs(act["F_real"]).median()) if len(act) else float("nan"),
                   float(df["E"].median()), float(df["D_F"].median()))


@dataclass(frozen=True)
class BoundSummary:
    config: dict
    rows: tuple[Row, ...]
    variances: tuple[VarianceFacts, ...]
    t1_failures_safe: tuple[Failure, ...]
    transition_failures: tuple[TransitionFailures, ...]
    t2e_failures: tuple[T2EFailures, ...]
    tightness: tuple[TightRow, ...] = ()
    comparisons: tuple[Decided, ...] = ()
    variant_failures: tuple[VariantFailures, ...] = ()

    def tight(self, test, constants, variance=float("nan")) -> TightRow | None:
        """The tightness row (variance nan: all variances pooled)."""
        def same(v: float) -> bool:
            return v == variance or (np.isnan(v) and np.isnan(variance))

        return next((r for r in self.tightness if (r.test, r.constants) == (test, constants)
                     and same(r.variance)), None)

    def decided(self, test, first, second) -> Decided | None:
        return next((d for d in self.comparisons if (d.test, d.first, d.second)
                     == (test, first, second)), None)

    def row(self, test, constants, variance, stratum="all") -> Row | None:
        return next((r for r in self.rows if (r.test, r.constants, r.variance, r.stratum)
                     == (test, constants, variance, stratum)), None)


def summarise(config, steps: pd.DataFrame, episodes: pd.DataFrame) -> BoundSummary:
    rows, facts = [], []
    for v in config.variances:
        df, ep = steps[steps["variance"] == v], episodes[episodes["variance"] == v]
        facts.append(VarianceFacts.of(df, ep, v))
        rows += [r for t in config.tests for c in CONSTANTS for s in STRATA
                 if (r := Row.of(df, t, c, v, s)) is not None]
    trans = tuple(TransitionFailures.of(steps[steps["variance"] == v], t, c, v)
                  for v in config.variances for t in config.tests if t.startswith("T3")
                  for c in CONSTANTS)
    t2e = tuple(T2EFailures.of(steps[steps["variance"] == v], v) for v in config.variances
                if "T2E" in config.tests)
    tight = [TightRow.at(steps[steps["variance"] == v], t, c, v) for t in config.tests
             for c in CONSTANTS for v in config.variances]
    tight += [TightRow.at(steps, t, c, float("nan")) for t in config.tests for c in CONSTANTS]
    pairs = (("local", "global"), ("sampled", "local"))
    m = len(config.tests) * len(pairs)
    dec = tuple(d for t in config.tests for a, b in pairs
                if (d := Decided.at(steps, t, a, b, m)) is not None)
    return BoundSummary(config.as_dict(), tuple(rows), tuple(facts),
                        tuple(t1_failures_when_safe(steps)), trans, t2e, tuple(tight), dec,
                        tuple(VariantFailures.of(steps, t) for t in config.tests))

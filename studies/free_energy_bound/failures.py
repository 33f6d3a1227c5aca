"""Where checks fail, from the tidy table: T1/T1s failures at steps where every real sample
stayed safe (each is reported and explained), and what the T3-family failures
have in common."""

from __future__ import annotations

from dataclasses import dataclass

import pandas as pd

from studies.free_energy_bound.config import CONSTANTS

CAUSES = {
    "secant_exceeds": "a secant slope exceeds the 5-point gradient maximum at that step, so the "
                      "estimated local constant is not a Lipschitz constant on that segment (the "
                      "barrier gradient peaks between the evaluation points)",
    "nominal_crashed": "nominal samples left the safe set at that step; their segment points "
                       "inside obstacles are excluded from the local estimate",
    "unexplained": "the secant check passed and no nominal sample crashed, so the tube argument "
                   "implies T1: this indicates a bug",
}


@dataclass(frozen=True)
class Failure:
    """A T1/T1s check that failed at a step where every real sample stayed safe, and the cause
    (a key of :data:`CAUSES`)."""

    test: str
    constants: str
    variance: float
    episode: int
    step: int
    slack: float
    lhs: float
    rhs: float
    R: float
    L_q: float
    secant_q: float
    n_crashed_nom: int
    cause: str


def t1_failures_when_safe(df: pd.DataFrame) -> list[Failure]:
    out = []
    for test in ("T1", "T1s"):
        for c in CONSTANTS[:2]:  # the paper's form (the sampled-tube bound: its own claims)
            bad = df[(df[f"{test}_{c}_holds"] == 0.0) & df["all_real_safe"]]
            for _, r in bad.iterrows():
                cause = ("secant_exceeds" if not r["secant_ok"] else "nominal_crashed"
                         if r["n_crashed_nom"] > 0 else "unexplained")
                out.append(Failure(test, c, float(r["variance"]), int(r["episode"]),
                                   int(r["step"]), float(r[f"{test}_{c}_slack"]),
                                   float(r[f"{test}_{c}_lhs"]), float(r[f"{test}_{c}_rhs"]),
                                   float(r["R"]), float(r["L_q"]), float(r["secant_q"]),
                                   int(r["n_crashed_nom"]), cause))
    return out


@dataclass(frozen=True)
class TransitionFailures:
    """Failures of one T3-family check (t, t+1) at one variance and what they share. The
    lemma's premise is an admissible nominal state, F̂_nom <= alpha (at t for T3, T3b, where
    alpha − F̂_nom(t) < 0 otherwise; at t+1 for T3c, T3d, which use F̂_nom(t+1)).
    ``fallback``: the selection found no candidate below alpha (its own 64-sample estimate) at
    t or t+1; step 0: the first call takes the real state by construction."""

    test: str
    constants: str
    variance: float
    n_evaluated: int
    n_failed: int
    n_premise_fails: int
    n_fallback: int
    n_first_step: int
    last_step: int  # the latest step t of a failure (-1: none)

    @classmethod
    def of(cls, df: pd.DataFrame, test: str, c: str, variance: float) -> TransitionFailures:
        h = df[f"{test}_{c}_holds"]
        bad = df[h == 0.0]
        adm = bad["nominal_admissible_next" if test in ("T3c", "T3d") else "nominal_admissible"]
        return cls(test, c, variance, int(h.notna().sum()), len(bad), int((~adm).sum()),
                   int((bad["fallback_used"] | bad["fallback_next"]).sum()),
                   int((bad["step"] == 0).sum()), int(bad["step"].max()) if len(bad) else -1)


@dataclass(frozen=True)
class T2EFailures:
    """T2E failures at one variance: how many at R = 0 (the nominal state is the real state, so
    the two independent batches estimate the same free energy), the median gap between the two
    estimates there and 2Ê, and the median ESS of the real batch."""

    variance: float
    n_evaluated: int
    n_failed: int
    n_failed_R0: int
    gap_median: float  # |F̂_real − F̂'_nom| over the failures at R = 0
    two_E_median: float
    ess_median: float

    @classmethod
    def of(cls, df: pd.DataFrame, variance: float) -> T2EFailures:
        h = df["T2E_local_holds"]
        bad = df[h == 0.0]
        r0 = bad[bad["R"] == 0.0]
        return cls(variance, int(h.notna().sum()), len(bad), len(r0),
                   float((r0["F_real"] - r0["F_nom_ind"]).abs().median()),
                   float((2 * r0["E"]).median()), float(df["ess_real"].median()))

"""Where checks fail, from the tidy table: T1/T1s failures at steps where every real sample
stayed safe (issue 12: each must be reported and explained), and what the T3-family failures
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
        for c in CONSTANTS:
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
    """Failures of one T3-family check (t, t+1) at one variance and what they share: a fallback
    at t+1 (no admissible nominal state: the lemma's premise fails), or t = 0 (the first call
    takes the real state by construction)."""

    test: str
    constants: str
    variance: float
    n_evaluated: int
    n_failed: int
    n_fallback_next: int
    n_first_step: int

    @classmethod
    def of(cls, df: pd.DataFrame, test: str, c: str, variance: float) -> TransitionFailures:
        h = df[f"{test}_{c}_holds"]
        bad = df[h == 0.0]
        return cls(test, c, variance, int(h.notna().sum()), len(bad),
                   int(bad["fallback_next"].sum()), int((bad["step"] == 0).sum()))

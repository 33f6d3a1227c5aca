"""Aggregation of the checks over steps: fraction holding (Wilson 95 % interval), slack
quantiles and the global/local ratio, per test, set of constants and stratum (assumptions §11.3).

A transition check (t, t+1) belongs to the strata of step t. Strata:
``all``; ``all_real_safe`` / ``some_real_crashed`` (assumptions §11.3 (a)); ``admissible`` /
``fallback`` (assumptions §11.3 (b): a candidate was below alpha, or none was); ``nominal_differs``
/ ``nominal_is_real``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np

from workbench.bound.checks import Check, episode_checks
from workbench.bound.step import BoundStep
from workbench.study.stats import wilson_interval
from workbench.validation import fail

STRATA: dict[str, Callable[[BoundStep], bool]] = {
    "all": lambda s: True,
    "all_real_safe": lambda s: s.all_real_safe,
    "some_real_crashed": lambda s: not s.all_real_safe,
    "admissible": lambda s: not s.fallback_used,
    "fallback": lambda s: s.fallback_used,
    "nominal_differs": lambda s: s.nominal_differs,
    "nominal_is_real": lambda s: not s.nominal_differs,
}


@dataclass(frozen=True)
class CheckSummary:
    test: str
    constants: str
    stratum: str
    n_steps: int
    n_holding: int
    fraction_holding: float
    interval: tuple[float, float]  # Wilson 95 %
    slack_q05: float
    slack_q50: float
    slack_q95: float
    rhs_ratio: float  # median global/local RHS over steps with local RHS > 0 (global rows)
    term_ratio: float  # median global/local Lipschitz term over steps with local term > 0

    def as_dict(self) -> dict:
        d = asdict(self)
        d["interval"] = list(self.interval)
        return d


def _median_ratio(pairs) -> float:
    r = [g / loc for g, loc in pairs if loc > 0]
    return float(np.median(r)) if r else float("nan")


def summarize(steps: list[BoundStep], checks: list[list[Check]] | None = None,
              strata: tuple[str, ...] = tuple(STRATA)) -> list[CheckSummary]:
    """One row per (test, constants, stratum) with at least one step."""
    if not steps:
        raise fail("steps", steps, "need at least one BoundStep")
    for s in strata:
        if s not in STRATA:
            raise fail("strata", s, f"known strata are {list(STRATA)}")
    checks = episode_checks(steps) if checks is None else checks
    if len(checks) != len(steps):
        raise fail("checks", len(checks), f"need one list of checks per step ({len(steps)})")
    by: dict[tuple[str, str], list[tuple[int, Check]]] = {}
    for i, cs in enumerate(checks):
        for c in cs:
            by.setdefault((c.test, c.constants), []).append((i, c))
    rows = []
    for (test, cst), ic in by.items():
        local = {i: c for i, c in by.get((test, "local"), [])}
        for name in strata:
            sel = [(i, c) for i, c in ic if STRATA[name](steps[i])]
            if not sel:
                continue
            sl = np.array([c.slack for _, c in sel])
            k = sum(c.holds for _, c in sel)
            glob = cst == "global" and bool(local)
            q05, q50, q95 = (float(np.quantile(sl, q)) for q in (0.05, 0.5, 0.95))
            rows.append(CheckSummary(
                test=test, constants=cst, stratum=name, n_steps=len(sel), n_holding=int(k),
                fraction_holding=k / len(sel), interval=wilson_interval(int(k), len(sel)),
                slack_q05=q05, slack_q50=q50, slack_q95=q95,
                rhs_ratio=_median_ratio((c.rhs, local[i].rhs) for i, c in sel if i in local)
                if glob else float("nan"),
                term_ratio=_median_ratio((c.lipschitz_term, local[i].lipschitz_term)
                                         for i, c in sel if i in local) if glob
                else float("nan")))
    return rows

"""The paper's claim (1), decided from the numbers of a run.

Claim (1) of the paper: discrete barrier states are "more sample efficient by metric of
collision free trajectories" and "computationally feasible to perform per sample", while CBF
filters are "computationally infeasible" per sample. Each part is a :class:`Verdict` whose
outcome follows from intervals: ``holds`` is True or False only when the 95 % intervals
decide it at every variance, else None (undecided, with the evidence).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from studies.sampling_safety.summary import SamplingSafetySummary


@dataclass(frozen=True)
class Verdict:
    key: str
    claim: str
    holds: bool | None
    evidence: str


def _fraction_claim(s: SamplingSafetySummary, other: str, key: str, claim: str) -> Verdict | None:
    parts, signs = [], []
    for v in s.config["variances"]:
        p = s.pair_fraction(other, "bas_mppi", v)  # other minus BaS-MPPI: negate
        if p is None or p.n < 2 or not math.isfinite(p.low):
            continue
        d, lo, hi = -p.difference, -p.high, -p.low
        parts.append(f"variance {v:g}: {100 * d:+.1f} points [{100 * lo:+.1f}, "
                     f"{100 * hi:+.1f}] (n = {p.n})")
        signs.append(1 if lo > 0 else -1 if hi < 0 else 0)
    if not signs:
        return None
    holds = True if all(x > 0 for x in signs) else False if all(x < 0 for x in signs) else None
    return Verdict(key, claim, holds, "BaS-MPPI minus the other, collision-free samples, "
                   "paired by realisation: " + "; ".join(parts))


def verdicts(s: SamplingSafetySummary) -> list[Verdict]:
    out: list[Verdict | None] = [
        _fraction_claim(s, "mppi_crash", "samples_vs_crash_cost",
                        "barrier states keep more samples collision-free than a crash cost"),
        _fraction_claim(s, "shield_mppi", "samples_vs_dcbf_cost",
                        "barrier states keep more samples collision-free than a discrete-CBF "
                        "cost (Shield-MPPI's samples)"),
        _fraction_claim(s, "cbf_projection", "samples_vs_projection",
                        "barrier states keep more samples collision-free than projecting every "
                        "sample onto the CBF constraint"),
    ]
    dt_ms = 1e3 * s.dt
    bas, crash, proj = (s.cost_ms(c) for c in ("bas_mppi", "mppi_crash", "cbf_projection"))
    if math.isfinite(bas) and math.isfinite(crash):
        ratio = bas / crash
        out.append(Verdict(
            "bas_feasible", "barrier states are computationally feasible per sample",
            bool(bas < dt_ms),
            f"BaS-MPPI {bas:.2f} CPU ms per control step against {crash:.2f} ms for MPPI with a "
            f"crash cost ({ratio:.2f}x), control period {dt_ms:.0f} ms"))
    if math.isfinite(proj) and math.isfinite(bas):
        out.append(Verdict(
            "cbf_infeasible", "a per-sample CBF filter is computationally infeasible",
            bool(proj > dt_ms),
            f"CBF projection of every sample (closed form, most restrictive constraint) "
            f"{proj:.2f} CPU ms per control step, {proj / bas:.2f}x BaS-MPPI; control period "
            f"{dt_ms:.0f} ms. A QP per sample would cost more; the closed form is what a "
            "user would implement first"))
    return [v for v in out if v is not None]


def most_collision_free(s: SamplingSafetySummary, variance: float):
    """(best cell, runner-up cell, separated): the cell with the highest collision-free sample
    fraction at ``variance`` and whether its interval lies above the runner-up's."""
    cells = sorted((c for c in s.cells if c.variance == variance),
                   key=lambda c: -c.collision_free_sample_fraction)
    if len(cells) < 2:
        return (cells[0] if cells else None), None, False
    a, b = cells[0], cells[1]
    return a, b, bool(a.cf_low > b.cf_high)


def frontier(s: SamplingSafetySummary, variance: float):
    """The cells not dominated in (higher safety, lower cost) at ``variance``, cheapest first,
    and the cell with the highest safety per CPU millisecond (cost: ``s.cost_ms``)."""
    cells = [c for c in s.cells if c.variance == variance]
    ms = {c.controller: s.cost_ms(c.controller) for c in cells}
    front = [c for c in cells if not any(
        (o.safety >= c.safety and ms[o.controller] <= ms[c.controller])
        and (o.safety > c.safety or ms[o.controller] < ms[c.controller]) for o in cells)]
    best = max(cells, key=lambda c: c.safety / ms[c.controller]) if cells else None
    return sorted(front, key=lambda c: ms[c.controller]), best

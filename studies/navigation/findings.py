"""The paper's claims (assumptions §14.4), one by one, as sentences whose conditions are
computed from the summary (numbers and 95% intervals), and the evidence sentences that explain
a miss (ablations, internals, alpha sweep). The report prints each claim with its verdict, and
only the evidence sentences that hold."""

from __future__ import annotations

from itertools import pairwise

from studies.navigation import paper
from studies.navigation.summary import NavigationSummary
from studies.navigation.wording import NAMES, metres, paired_difference, points, seconds
from workbench.study import Claim, fmt_rate
from workbench.study.report import num


def safer_claims(s: NavigationSummary) -> list[Claim]:
    out = []
    for v in (v for v in s.config["variances"] if v > 0):
        p = s.pair("sa_rmppi", "bas_mppi", v)
        if p is None:
            continue
        lo, hi = paper.CLAIMED_GAIN
        if p.low > 0:
            verdict = "holds" + ("" if lo - 0.01 <= p.difference <= hi else
                                 f", but the gain lies outside the claimed {lo:.0%}-{hi:.0%}")
        elif p.difference > 0:
            verdict = "not shown: higher by point estimate, the interval includes 0"
        else:
            verdict = "does not hold"
        out.append(Claim(f"(i) variance {v:g}: SA-RMPPI minus BaS-MPPI safety = "
                         f"{paired_difference(p)}: {verdict}.", p.low > 0, verdict))
    return out


def rmse_claims(s: NavigationSummary) -> list[Claim]:
    out = []
    for v in s.config["variances"]:
        a, b = s.cell("sa_rmppi", v), s.cell("bas_mppi", v)
        if a is None or b is None:
            continue
        ok = b.rmse < a.rmse
        out.append(Claim(f"(ii) variance {v:g}: RMSE BaS-MPPI {metres(b.rmse)} (n = {b.safe.k}) "
                         f"{'<' if ok else '>='} SA-RMPPI {metres(a.rmse)} (n = {a.safe.k}): "
                         f"{'holds' if ok else 'does not hold'}.", ok))
    return out


def monotone_claims(s: NavigationSummary) -> list[Claim]:
    out = []
    for c in ("sa_rmppi", "bas_mppi", "rmppi", "mppi_crash"):
        cells = [s.cell(c, v) for v in sorted(s.config["variances"])]
        if any(x is None for x in cells) or len(cells) < 2:
            continue
        mono = all(a.safety >= b.safety for a, b in pairwise(cells))
        ends = cells[0].safe.above(cells[-1].safe)
        text = ", ".join(f"{x.variance:g}: {points(x.safety)}%" for x in cells)
        verdict = ("holds" if mono and ends else "holds by point estimates (end intervals "
                   "overlap)" if mono else "does not hold")
        out.append(Claim(f"Monotone, {NAMES[c]}: safety by variance {text}: {verdict}.",
                         mono, verdict))
    return out


def magnitude_claims(s: NavigationSummary) -> list[Claim]:
    out = []
    for v, row in paper.TABLE_I.items():
        for c, (safety, rmse) in row.items():
            x = s.cell(c, v)
            if x is None:
                continue
            d = abs(x.safety - safety / 100)
            ok = d <= paper.SAFETY_POINTS
            inside = x.safe.contains(safety / 100)
            f = x.rmse / rmse if rmse > 0 else float("inf")
            rok = 1 / paper.RMSE_FACTOR <= f <= paper.RMSE_FACTOR
            out.append(Claim(
                f"{NAMES[c]}, variance {v:g}: safety {fmt_rate(x.safe)} vs {safety}% "
                f"({'within' if ok else 'outside'} 10 points; paper's value "
                f"{'inside' if inside else 'outside'} our interval); RMSE {metres(x.rmse)} vs "
                f"{rmse} m (ratio {num(f, '.2g', 'no safe episodes')}, "
                f"{'within' if rok else 'outside'} a factor of 2).",
                ok and rok))
    return out


def site_claims(s: NavigationSummary) -> list[Claim]:
    out = []
    vs = sorted(s.config["variances"])
    for v in vs:
        b = s.cell("bas_mppi", v)
        if b is None or b.safe.n == b.safe.k:
            continue
        n = b.safe.n - b.safe.k
        share = b.crashes_at_gates / n
        ok = share >= paper.GATE_SHARE
        out.append(Claim(f"(iii) variance {v:g}: {b.crashes_at_gates} of {n} BaS-MPPI crashes "
                         f"({points(share)}%) are at the two gate circles of the central passage"
                         f": {'holds' if ok else 'does not hold'} (threshold "
                         f"{paper.GATE_SHARE:.0%}).", ok))
    b = s.cell("bas_mppi", vs[-1])
    if b is not None and b.safe.n > b.safe.k and vs[-1] > 0:
        n = b.safe.n - b.safe.k
        ok = b.crashes_early / n >= paper.EARLY_SHARE
        out.append(Claim(f"(iii) variance {vs[-1]:g}: {b.crashes_early} of {n} BaS-MPPI "
                         "crashes happen before a third of the way to the goal (first "
                         f"passageways): {'holds' if ok else 'does not hold'}.", ok))
    return out


def velocity_claims(s: NavigationSummary) -> list[Claim]:
    out = []
    for v in s.config["variances"]:
        a, b = s.cell("sa_rmppi", v), s.cell("bas_mppi", v)
        if a is None or b is None or v == 0:
            continue
        faster = b.mean_speed.mean > a.mean_speed.mean
        spread = b.mean_speed.std > a.mean_speed.std
        sooner = b.time_to_goal_s.median < a.time_to_goal_s.median
        ok = faster and spread and sooner
        out.append(Claim(
            f"(iv) variance {v:g}: mean speed BaS-MPPI {b.mean_speed.mean:.2f} ± "
            f"{b.mean_speed.std:.2f} vs SA-RMPPI {a.mean_speed.mean:.2f} ± "
            f"{a.mean_speed.std:.2f} m/s; median time to within {s.config['goal_radius']:g} m "
            f"{seconds(b.time_to_goal_s.median)} (n = {b.time_to_goal_s.n}) vs "
            f"{seconds(a.time_to_goal_s.median)} (n = {a.time_to_goal_s.n}): "
            f"{'holds' if ok else 'does not hold'} (faster {faster}, wider spread {spread}, "
            f"sooner {sooner}).", ok))
    return out


def other_claims(s: NavigationSummary) -> list[Claim]:
    out = []
    for c in ("sa_rmppi", "bas_mppi"):
        cells = [x for x in s.cells if x.main and x.controller == c]
        if not cells:
            continue
        worst = min(cells, key=lambda x: x.reached.value if x.reached.n else 1.0)
        ok = all(x.reached.k == x.reached.n for x in cells)
        out.append(Claim(f"(v) {NAMES[c]}: safe runs within {s.config['goal_radius']:g} m of "
                         f"the goal: lowest {fmt_rate(worst.reached)} (variance "
                         f"{worst.variance:g}): {'holds' if ok else 'does not hold'}.", ok))
        slow = max(x.mean_step_ms for x in cells)
        ok = slow <= paper.REAL_TIME_MS
        out.append(Claim(f"(vi) {NAMES[c]}: slowest cell mean {slow:.1f} ms per control step "
                         f"(dt = {paper.REAL_TIME_MS:g} ms, one thread per worker): "
                         f"{'holds' if ok else 'does not hold'}.", ok))
    return out


def all_claims(s: NavigationSummary) -> dict[str, list[Claim]]:
    return {"safer": safer_claims(s), "rmse": rmse_claims(s), "monotone": monotone_claims(s),
            "crash_sites": site_claims(s), "velocity": velocity_claims(s),
            "reached": other_claims(s), "magnitude": magnitude_claims(s)}

"""What the arena decides, in words: the paper's claim (i) on its own rows, every declared
comparison's verdict, and the recommendation per system.

Claim (i): under disturbance, SA-RMPPI (robust sampling with the barrier-state feedback K_safe)
is safer than BaS-MPPI. It is a declared comparison of the arena (the default one), decided
group-sequentially (:mod:`studies.arena.decisions`): it *holds* when SA-RMPPI's repeated 95 %
interval of the safety difference lies above 0, is *contradicted* when it lies below 0, is
*equivalent* when the equivalence interval lies within the margin, and is *undecided* when the
budget of rounds ran out first; the error rates are kept over every declared comparison. The
ablations say why: SA-RMPPI against RMPPI (same sampler, plain tracking gains instead of K_safe)
isolates the barrier-state feedback; RMPPI against BaS-MPPI isolates the robust sampler itself.
They are descriptive (pooled over the maps of the first round), not declared.
"""

from __future__ import annotations

from dataclasses import dataclass

from studies.arena.decisions import CLAIM
from studies.arena.summary import ALL, ArenaSummary, Board, DecisionRow
from studies.navigation.paper import TABLE_I


@dataclass(frozen=True)
class Setting:
    """Claim (i) in one (system, disturbance, tuning): the decision row, the paper's
    difference at the same level on the double integrator (Table I, points; None elsewhere)
    and whether it lies inside our repeated interval; success of both and the share of safe
    episodes that never reached the goal (drift)."""

    row: DecisionRow
    paper: float | None
    paper_inside: bool | None
    success_first: float
    success_second: float
    drift: float


@dataclass(frozen=True)
class Ablation:
    first: str
    second: str
    system: str
    tuning: str
    n: int
    difference: float
    low: float
    high: float
    p_value: float


@dataclass(frozen=True)
class Verdict:
    settings: tuple[Setting, ...]
    ablations: tuple[Ablation, ...]
    counts: dict[str, int]
    text: tuple[str, ...]


def _pts(x: float) -> str:
    return f"{100 * x:+.1f}"


def _success(s: ArenaSummary, controller: str, system: str, disturbance: str,
             tuning: str) -> tuple[float, float, float]:
    """Over the maps: (success rate, safe episodes, safe episodes that never reached the
    goal) of one controller."""
    cells = [c for c in s.cells if (c.controller, c.system, c.disturbance, c.tuning)
             == (controller, system, disturbance, tuning)]
    n = sum(c.n for c in cells)
    ok = sum(c.success * c.n for c in cells)
    safe = sum(c.safety * c.n for c in cells)
    return (ok / n if n else float("nan")), safe, safe - ok


def _paper(s: ArenaSummary, row: DecisionRow) -> float | None:
    """Table I's SA-RMPPI minus BaS-MPPI at this disturbance's level (double integrator)."""
    if row.system != "double_integrator":
        return None
    level = next((d["level"] for d in s.config["disturbances"]
                  if _label(d) == row.disturbance), None)
    t = TABLE_I.get(float(level)) if level is not None else None
    return None if t is None else (t["sa_rmppi"][0] - t["bas_mppi"][0]) / 100


def _label(d: dict) -> str:
    from studies.arena.config import DisturbanceSpec

    return DisturbanceSpec(**{k: tuple(v) if isinstance(v, list) else v
                              for k, v in d.items()}).label


def verdict_sentence(r: DecisionRow, names: tuple[str, str] | None = None) -> str:
    """One sentence: the verdict, the difference with its repeated interval, pairs, looks,
    discordant counts, the fixed-sample McNemar p and, when undecided, the detectable
    difference."""
    a, b = names or (r.first, r.second)
    words = {"holds": f"{a} better", "contradicted": f"{a} worse",
             "equivalent": "equivalent", "undecided": "undecided"}[r.verdict]
    text = (f"{words}: {a} minus {b} {r.metric} {_pts(r.difference)} points "
            f"[{_pts(r.low)}, {_pts(r.high)}] over {r.n} pairs after {r.looks} look"
            f"{'s' if r.looks != 1 else ''} ({r.b} only {a}, {r.c} only {b}; McNemar p = "
            f"{r.p_value:.2g})")
    if r.verdict == "equivalent":
        text += f"; equivalence interval [{_pts(r.eq_low)}, {_pts(r.eq_high)}]"
    if r.verdict == "undecided" and r.detectable is not None:
        text += (f"; with these pairs it could have detected a difference of "
                 f"{100 * r.detectable:.0f} points")
    if r.uninformative:
        text += f". Uninformative setting: {r.uninformative}"
    return text + "."


def verdict(s: ArenaSummary) -> Verdict | None:
    rows = [r for r in s.decisions if (r.first, r.second) == CLAIM and r.metric == "safety"]
    if not rows:
        return None
    settings = []
    for r in rows:
        f = _success(s, CLAIM[0], r.system, r.disturbance, r.tuning)
        g = _success(s, CLAIM[1], r.system, r.disturbance, r.tuning)
        drift = (f[2] + g[2]) / (f[1] + g[1]) if f[1] + g[1] else 0.0
        paper = _paper(s, r)
        inside = None if paper is None else bool(r.low <= paper <= r.high)
        settings.append(Setting(r, paper, inside, f[0], g[0], drift))
    pooled_over = ALL if any(p.disturbance == ALL for p in s.pooled) else rows[0].disturbance
    abl = tuple(Ablation(p.first, p.second, p.system, p.tuning, p.n, p.difference, p.low,
                         p.high, p.p_value)
                for p in s.pooled if (p.first, p.second) in (("sa_rmppi", "rmppi"),
                                                               ("rmppi", "bas_mppi"))
                and p.disturbance == pooled_over)
    counts = {o: sum(x.row.verdict == o for x in settings)
              for o in ("holds", "contradicted", "equivalent", "undecided")}
    d = s.design or {}
    text = [f"Claim (i), SA-RMPPI safer than BaS-MPPI under disturbance: holds in "
            f"{counts['holds']} of {len(settings)} settings (system x disturbance x tuning), "
            f"contradicted in {counts['contradicted']}, equivalent within "
            f"±{100 * d.get('margin', float('nan')):.0f} points in {counts['equivalent']}, "
            f"undecided in {counts['undecided']} (group-sequential, error rates kept over "
            f"{d.get('comparisons', len(settings))} declared comparisons at family-wise "
            f"level {d.get('alpha', float('nan')):g})."]
    for x in settings:
        r = x.row
        paper = ("" if x.paper is None else
                 f" The paper's {_pts(x.paper)} points (Table I, one map) lie "
                 f"{'inside' if x.paper_inside else 'outside'} this interval.")
        text.append(f"{r.system}, {r.disturbance}, {r.tuning}: "
                    + verdict_sentence(r, ("SA-RMPPI", "BaS-MPPI"))
                    + f" Reached the goal without a crash: SA-RMPPI "
                    f"{100 * x.success_first:.0f} %, BaS-MPPI {100 * x.success_second:.0f} %."
                    + paper
                    + (f" {100 * x.drift:.0f} % of the safe episodes never reached the goal: "
                       "here safety mostly means being pushed away from the obstacles, not "
                       "avoiding them." if x.drift > 0.5 else ""))
    for a in abl:
        what = ("the barrier-state feedback K_safe (against plain tracking gains)"
                if a.second == "rmppi" else "the robust sampler with tracking gains")
        text.append(f"Ablation (descriptive), {a.system}, {a.tuning}: {what}: {a.first} minus "
                    f"{a.second} {_pts(a.difference)} points [{_pts(a.low)}, {_pts(a.high)}], "
                    f"p = {a.p_value:.2g} over {a.n} paired episodes.")
    return Verdict(tuple(settings), abl, counts, tuple(text))


def frontier(boards: list[Board]) -> list[Board]:
    """The safety-versus-cost frontier of one leaderboard: controllers no other one beats on
    both safety and ms per step (ties on both kept), cheapest first."""
    out = [b for b in boards
           if not any((o.safety >= b.safety and o.mean_step_ms < b.mean_step_ms)
                      or (o.safety > b.safety and o.mean_step_ms <= b.mean_step_ms)
                      for o in boards)]
    return sorted(out, key=lambda b: b.mean_step_ms)


def recommended(s: ArenaSummary, system: str, tuning: str) -> list[Board]:
    """The recommended mechanism(s) on a system: the safest controller (the leaderboard's
    first) and every one whose safety lies inside its 95 % interval and that no declared
    comparison with it found worse; cheapest first."""
    boards = [b for b in s.leaderboard if (b.system, b.tuning) == (system, tuning)]
    if not boards:
        return []
    top = boards[0]
    worse = {r.first for r in s.decisions if r.system == system and r.tuning == tuning
             and r.second == top.controller and r.verdict == "contradicted"}
    worse |= {r.second for r in s.decisions if r.system == system and r.tuning == tuning
              and r.first == top.controller and r.verdict == "holds"}
    keep = [b for b in boards if b is top or (b.controller not in worse
                                              and b.safety >= top.ci_low)]
    return sorted(keep, key=lambda b: b.mean_step_ms)

"""The verdict on the paper's claim (i), generated from the arena's pooled comparisons.

Claim (i): under disturbance, SA-RMPPI (robust sampling with the barrier-state feedback K_safe)
is safer than BaS-MPPI. For every (system, disturbance, tuning) the arena ran, the claim
*holds* when SA-RMPPI's pooled safety lead over the maps is positive and significant after a
Holm correction over all those settings (exact McNemar, 5 %), is *contradicted* when the lead
is negative and significant, and is *not decided* otherwise. A setting whose effect differs
between maps (homogeneity p < 0.05) is flagged: a pooled number then hides map-dependence.
The ablations say why: SA-RMPPI against RMPPI (same sampler, plain tracking gains instead of
K_safe) isolates the barrier-state feedback; RMPPI against BaS-MPPI isolates the robust
sampler itself.
"""

from __future__ import annotations

from dataclasses import dataclass

from studies.arena.summary import ALL, ArenaSummary, Pooled

CLAIM = ("sa_rmppi", "bas_mppi")
LEVEL = 0.05


@dataclass(frozen=True)
class Setting:
    system: str
    disturbance: str
    tuning: str
    n_maps: int
    n: int
    b: int
    c: int
    difference: float
    low: float
    high: float
    p_value: float
    p_holm: float
    homogeneity_p: float | None
    outcome: str  # "holds", "contradicted" or "not decided"
    success_first: float  # SA-RMPPI's share of episodes that reached the goal without a crash
    success_second: float  # BaS-MPPI's
    drift: float  # share of both controllers' safe episodes that never reached the goal

    @property
    def heterogeneous(self) -> bool:
        return self.homogeneity_p is not None and self.homogeneity_p < LEVEL


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
    holds: int
    contradicted: int
    undecided: int
    n_maps: int
    text: tuple[str, ...]


def holm(p: list[float]) -> list[float]:
    """Holm-Bonferroni adjusted p-values (statsmodels)."""
    if not p:
        return []
    from statsmodels.stats.multitest import multipletests

    return [float(v) for v in multipletests(p, method="holm")[1]]


def _outcome(p: Pooled, adj: float) -> str:
    if adj < LEVEL and p.difference > 0:
        return "holds"
    if adj < LEVEL and p.difference < 0:
        return "contradicted"
    return "not decided"


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


def verdict(s: ArenaSummary) -> Verdict | None:
    rows = [p for p in s.pooled if (p.first, p.second) == CLAIM and p.disturbance != ALL]
    if not rows:
        return None
    adj = holm([p.p_value for p in rows])
    settings = []
    for p, a in zip(rows, adj, strict=True):
        f = _success(s, CLAIM[0], p.system, p.disturbance, p.tuning)
        g = _success(s, CLAIM[1], p.system, p.disturbance, p.tuning)
        drift = (f[2] + g[2]) / (f[1] + g[1]) if f[1] + g[1] else 0.0
        settings.append(Setting(p.system, p.disturbance, p.tuning, p.n_maps, p.n, p.b, p.c,
                                p.difference, p.low, p.high, p.p_value, a, p.homogeneity_p,
                                _outcome(p, a), f[0], g[0], drift))
    settings = tuple(settings)
    pooled_over = ALL if any(p.disturbance == ALL for p in s.pooled) else rows[0].disturbance
    abl = tuple(Ablation(p.first, p.second, p.system, p.tuning, p.n, p.difference, p.low,
                         p.high, p.p_value)
                for p in s.pooled if (p.first, p.second) in (("sa_rmppi", "rmppi"),
                                                               ("rmppi", "bas_mppi"))
                and p.disturbance == pooled_over)
    count = {o: sum(x.outcome == o for x in settings)
             for o in ("holds", "contradicted", "not decided")}
    n_maps = max(x.n_maps for x in settings)
    text = [f"Claim (i), SA-RMPPI safer than BaS-MPPI under disturbance, over {n_maps} test "
            f"maps per setting: holds in {count['holds']} of {len(settings)} settings "
            f"(system x disturbance x tuning), contradicted in {count['contradicted']}, not "
            f"decided in {count['not decided']} (exact McNemar on the discordant pairs summed "
            f"over maps, Holm-corrected over the {len(settings)} settings, level {LEVEL:g})."]
    for x in settings:
        flag = " The effect differs between maps (homogeneity p = " \
               f"{x.homogeneity_p:.2g})." if x.heterogeneous else ""
        text.append(f"{x.system}, {x.disturbance}, {x.tuning}: {x.outcome}; SA-RMPPI minus "
                    f"BaS-MPPI safety {_pts(x.difference)} points [{_pts(x.low)}, "
                    f"{_pts(x.high)}] over {x.n} paired episodes ({x.b} only SA-RMPPI safe, "
                    f"{x.c} only BaS-MPPI safe; p = {x.p_value:.2g}, Holm {x.p_holm:.2g}). "
                    f"Reached the goal without a crash: SA-RMPPI {100 * x.success_first:.0f} %, "
                    f"BaS-MPPI {100 * x.success_second:.0f} %." + flag
                    + (f" {100 * x.drift:.0f} % of the safe episodes never reached the goal: "
                       "here safety mostly means being pushed away from the obstacles, not "
                       "avoiding them." if x.drift > 0.5 else ""))
    for a in abl:
        what = ("the barrier-state feedback K_safe (against plain tracking gains)"
                if a.second == "rmppi" else "the robust sampler with tracking gains")
        text.append(f"Ablation, {a.system}, {a.tuning}: {what}: {a.first} minus {a.second} "
                    f"{_pts(a.difference)} points [{_pts(a.low)}, {_pts(a.high)}], "
                    f"p = {a.p_value:.2g} over {a.n} paired episodes.")
    return Verdict(settings, abl, count["holds"], count["contradicted"], count["not decided"],
                   n_maps, tuple(text))

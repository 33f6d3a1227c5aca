"""Declared comparisons of the arena, decided group-sequentially.

A comparison is declared before the run (:class:`~studies.arena.config.Comparison`: the pair,
the metric, and the systems, disturbances and tunings it covers); each (system, disturbance,
tuning) it covers is one member of the family whose error rates are kept. Round 0 runs the
whole grid of the config; each later round adds ``test_maps`` new maps of every family with
``realisations`` paired episodes each, only for the members still undecided. After each round
a member's cumulative pairs are looked at with the design of :mod:`workbench.study.sequential`
(O'Brien-Fleming alpha spending, repeated confidence intervals, Bonferroni over the family):
it stops as soon as it is superior, inferior or equivalent within ``decision.margin``, and is
undecided after the last round. What runs next depends only on the stored outcomes of earlier
rounds, so a rerun (any number of workers) runs the same episodes.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import numpy as np
import pandas as pd

from studies.arena.config import ArenaConfig, Comparison
from workbench.study.sequential import Look, SequentialDesign, detectable, run_looks

CLAIM = ("sa_rmppi", "bas_mppi")  # the paper's claim (i): SA-RMPPI safer than BaS-MPPI
OUTCOME = {"superior": "holds", "inferior": "contradicted", "equivalent": "equivalent",
           "undecided": "undecided", "continue": "undecided"}  # a comparison's verdict words


@dataclass(frozen=True)
class Member:
    """One declared comparison in one (system, disturbance, tuning)."""

    first: str
    second: str
    metric: str
    system: str
    disturbance: str
    tuning: str

    @property
    def label(self) -> str:
        return (f"{self.first} vs {self.second} ({self.metric}), {self.system}, "
                f"{self.disturbance}, {self.tuning}")


def comparisons(config: ArenaConfig) -> tuple[Comparison, ...]:
    """The declared comparisons; none declared: claim (i) on safety when both ran."""
    if config.comparisons:
        return config.comparisons
    if set(CLAIM) <= set(config.controllers):
        return (Comparison(*CLAIM),)
    return ()


def members(config: ArenaConfig) -> tuple[Member, ...]:
    """Every declared comparison in every (system, disturbance, tuning) it covers, once."""
    labels = [d.label for d in config.disturbances]
    out: list[Member] = []
    for c in comparisons(config):
        for s in c.systems or config.systems:
            for d in c.disturbances or labels:
                for t in c.tunings or config.tunings:
                    m = Member(c.first, c.second, c.metric, s, d, t)
                    if m not in out:
                        out.append(m)
    return tuple(out)


def design(config: ArenaConfig) -> SequentialDesign:
    """The group-sequential design shared by every member (one look per round)."""
    d = config.decision
    return SequentialDesign(looks=d.rounds,
                            pairs_per_look=config.test_maps * len(config.families)
                            * config.realisations,
                            margin=d.margin, alpha=d.alpha,
                            comparisons=max(len(members(config)), 1), power=d.power)


def _ok(rows: pd.DataFrame, metric: str) -> np.ndarray:
    safe = ~rows["crashed"].to_numpy(bool)
    return safe if metric == "safety" else safe & rows["reached"].to_numpy(bool)


def per_round(config: ArenaConfig, ep: pd.DataFrame, m: Member) -> list[tuple[int, int, int]]:
    """(b, c, n) of each round present, in round order: pairs where only ``first`` / only
    ``second`` met the metric, and pairs (same system, map, disturbance, tuning and
    realisation: common random numbers)."""
    sel = ep[(ep["system"] == m.system) & (ep["disturbance"] == m.disturbance)
             & (ep["tuning"] == m.tuning)]
    key = ["family", "map_seed", "realisation"]
    x = sel[sel["controller"] == m.first]
    y = sel[sel["controller"] == m.second]
    both = x[key].assign(ok1=_ok(x, m.metric)).merge(y[key].assign(ok2=_ok(y, m.metric)),
                                                     on=key)
    if both.empty:
        return []
    rnd = np.array([config.round_of(int(s)) for s in both["map_seed"]])
    ok1, ok2 = both["ok1"].to_numpy(bool), both["ok2"].to_numpy(bool)
    return [(int(np.sum(ok1[rnd == r] & ~ok2[rnd == r])),
             int(np.sum(~ok1[rnd == r] & ok2[rnd == r])), int(np.sum(rnd == r)))
            for r in sorted(set(rnd.tolist()))]


def looks(config: ArenaConfig, ep: pd.DataFrame, m: Member) -> tuple[Look, ...]:
    """The member's looks over the rounds present, up to its decision (rounds run after it
    was decided, for another member, are not looked at)."""
    rounds = per_round(config, ep, m)
    if not rounds:
        return ()
    b, c, n = (list(v) for v in zip(*rounds, strict=True))
    return run_looks(design(config), b, c, n)


@dataclass(frozen=True)
class Decided:
    """A member's verdict: its last look, the verdict word, and when undecided the
    difference it could have detected (at the planned power, with its observed discordance)."""

    member: Member
    looks: tuple[Look, ...]
    verdict: str
    detectable: float | None
    discordance: float


def decide(config: ArenaConfig, ep: pd.DataFrame, m: Member) -> Decided | None:
    ls = looks(config, ep, m)
    if not ls:
        return None
    last = ls[-1]
    disc = (last.b + last.c) / last.n if last.n else float("nan")
    verdict = OUTCOME[last.decision]
    det = None
    if verdict == "undecided":
        dz = design(config)
        det = detectable(last.n, max(disc, 1.0 / last.n), dz.alpha, dz.power, dz.looks,
                         dz.comparisons)
    return Decided(m, ls, verdict, det, disc)


# ----------------------------------------------------------------------------- rounds
def _row(task, out) -> dict:
    e = out["episodes"]
    return {**task.columns(), "crashed": bool(e["crashed"][0]),
            "reached": bool(e["reached"][0])}


def stages(config: ArenaConfig, rounds: tuple[tuple, ...], outputs) -> list:
    """The tasks to have finished now: round 0, then round r for every member still open
    after the looks at rounds < r (``rounds[r]``: round r's tasks by member label). Each
    task's outputs are read once."""
    wanted = list(rounds[0][""])
    rows: dict = {}
    ms = members(config)
    for r in range(1, len(rounds)):
        for t in wanted:
            if t not in rows:
                out = outputs(t)
                if out is None:
                    return wanted
                rows[t] = _row(t, out)
        ep = pd.DataFrame([rows[t] for t in wanted])
        seen = set(wanted)
        for m in ms:
            ls = looks(config, ep, m)
            if ls and ls[-1].decision == "continue" and len(ls) == r:
                new = [t for t in rounds[r][m.label] if t not in seen]
                wanted += new
                seen.update(new)
    return wanted


def staged(config: ArenaConfig, rounds: tuple[tuple, ...]):
    """``stages`` bound to this config and plan (None for a single round)."""
    return partial(stages, config, rounds) if len(rounds) > 1 else None

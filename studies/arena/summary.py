"""Typed summary of an arena run, from the tidy tables ``episodes``, ``timing`` and
``activity``.

Metrics, each defined once here: safety = share of episodes without a crash (Wilson 95 %
interval); success = share of episodes that reach the goal without a crash; final error =
distance to the goal at the episode's end; ms per step = mean process CPU time of a control
step (all its threads; what other processes do does not change it, see
:mod:`workbench.study.latency`).

Paired comparisons (controller A against B, same system, disturbance and tuning, common random
numbers): per map, the realisations where only A or only B stayed safe; pooled over maps with
:func:`~workbench.study.stats.pooled_paired` (exact McNemar test on the summed discordant
pairs, the pooled difference in safety with its 95 % interval, a Cochran-Mantel-Haenszel test
and a test that the effect is the same on every map). Mechanism health
(:func:`~workbench.scenarios.mechanism_health.study_health`): per system, disturbance and
tuning, whether each mechanism never acted or acted on every step, and whether a method was
less safe than the one it wraps.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from studies.arena.episodes import arena_map, arena_system, own_scene
from studies.arena.tasks import family
from workbench.scenarios.mechanism_health import StudyHealth, study_health
from workbench.scenarios.tuned import shipped, space
from workbench.study import Rate
from workbench.study.sequential import detectable, plan_pairs
from workbench.study.stats import mcnemar_exact, paired_counts, pooled_paired

ALL = "all"  # the disturbance label of comparisons pooled over every disturbance


@dataclass(frozen=True)
class Cell:
    """One (controller, system, map, disturbance, tuning) cell over its realisations."""

    controller: str
    system: str
    map: str
    disturbance: str
    tuning: str
    n: int
    safety: float
    ci_low: float
    ci_high: float
    success: float
    success_low: float
    success_high: float
    final_error: float
    mean_step_ms: float
    collision_free_sample_fraction: float
    ess_mean: float
    activity: dict[str, float]

    @classmethod
    def of(cls, key: tuple, rows: pd.DataFrame, timing: pd.DataFrame,
           activity: pd.DataFrame) -> Cell:
        safe = Rate.of(~rows["crashed"].to_numpy(bool))
        ok = Rate.of(rows["reached"].to_numpy(bool) & ~rows["crashed"].to_numpy(bool))
        act = {k: float(g["activity"].mean()) for k, g in activity.groupby("mechanism")}
        return cls(*key, safe.n, safe.value, safe.low, safe.high, ok.value, ok.low, ok.high,
                   float(rows["final_error"].mean()), float(timing["mean_cpu_ms"].mean()),
                   float(rows["collision_free_fraction"].mean()),
                   float(rows["ess_mean"].mean()), act)


@dataclass(frozen=True)
class Pooled:
    """``first`` against ``second`` on one system and tuning, pooled over maps (and over
    disturbances when ``disturbance`` is "all"): summed discordant pairs b (only first safe)
    and c (only second safe), exact McNemar p, pooled difference in safety with its 95 %
    interval, CMH and homogeneity p-values, and the number of strata (maps, or maps x
    disturbances)."""

    first: str
    second: str
    system: str
    disturbance: str
    tuning: str
    n: int
    b: int
    c: int
    p_value: float
    difference: float
    low: float
    high: float
    n_maps: int
    cmh_p: float | None
    homogeneity_p: float | None


@dataclass(frozen=True)
class Board:
    """A controller's line on a system's leaderboard: every map and disturbance pooled.
    Rates with Wilson 95 % intervals; final error and ms per step as means over episodes with
    95 % t-intervals."""

    system: str
    tuning: str
    controller: str
    n: int
    safety: float
    ci_low: float
    ci_high: float
    success: float
    mean_step_ms: float
    rank: int
    success_low: float = float("nan")
    success_high: float = float("nan")
    final_error: float = float("nan")
    final_error_low: float = float("nan")
    final_error_high: float = float("nan")
    ms_low: float = float("nan")
    ms_high: float = float("nan")


@dataclass(frozen=True)
class DecisionRow:
    """A declared comparison in one (system, disturbance, tuning), decided group-sequentially
    (:mod:`studies.arena.decisions`): its last look (pairs, discordant counts, difference
    first - second with the repeated 95 % interval and the equivalence interval), the verdict
    ("holds": first better, "contradicted": first worse, "equivalent" within the margin, or
    "undecided" with the difference it could have detected) and the exact McNemar p-value of
    the pairs (fixed-sample, descriptive: the verdict reads the repeated intervals)."""

    first: str
    second: str
    metric: str
    system: str
    disturbance: str
    tuning: str
    looks: int
    n: int
    b: int
    c: int
    difference: float
    low: float
    high: float
    eq_low: float
    eq_high: float
    bound: float
    verdict: str
    detectable: float | None
    discordance: float
    p_value: float
    uninformative: str | None  # why the setting cannot discriminate, or None


@dataclass(frozen=True)
class MapInfo:
    map: str
    family: str
    seed: int
    n_circles: int
    bottleneck: float
    path_length: float
    straight_clearance: float
    moving: int


@dataclass(frozen=True)
class SceneInfo:
    """The scene of a system that runs on its own (a system built from a model), described
    once in place of the generated maps it does not use: start and goal states, the number of
    its constraints h(x) > 0, its time step and goal radius (in its own distance to the
    goal)."""

    system: str
    label: str
    start: tuple[float, ...]
    goal: tuple[float, ...]
    state_names: tuple[str, ...]
    constraints: int
    dt: float
    goal_radius: float


@dataclass(frozen=True)
class ArenaSummary:
    config: dict
    cells: tuple[Cell, ...]
    pooled: tuple[Pooled, ...]
    leaderboard: tuple[Board, ...]
    maps: tuple[MapInfo, ...]
    tuned: dict
    health: StudyHealth  # mechanism checks per (system, disturbance, tuning), over the maps
    decisions: tuple[DecisionRow, ...] = ()
    design: dict | None = None  # the group-sequential design shared by the decisions
    uninformative: dict[str, str] | None = None  # "system / disturbance / tuning" -> why
    scenes: tuple[SceneInfo, ...] = ()  # the systems that run on their own scene, not on maps

    def pair(self, first: str, second: str, system: str, disturbance: str,
             tuning: str) -> Pooled | None:
        return next((p for p in self.pooled if (p.first, p.second, p.system, p.disturbance,
                                                p.tuning) == (first, second, system,
                                                              disturbance, tuning)), None)


REFERENCES = ("bas_mppi", "sa_rmppi")  # every controller is compared with these
ABLATIONS = (("sa_rmppi", "rmppi"), ("rmppi", "bas_mppi"))  # why SA-RMPPI differs


def pairs(controllers: tuple[str, ...]) -> list[tuple[str, str]]:
    """The compared pairs: the ablations (in their own order), then every controller against
    each reference present; a pair appears once, in one order."""
    out: list[tuple[str, str]] = []
    cands = [p for p in ABLATIONS if set(p) <= set(controllers)]
    cands += [(c, r) for r in REFERENCES if r in controllers for c in controllers if c != r]
    for p in cands:
        if p not in out and (p[1], p[0]) not in out:
            out.append(p)
    return out


def _strata(ep: pd.DataFrame, first: str, second: str, by: list[str]) -> list[tuple]:
    x, y = ep[ep["controller"] == first], ep[ep["controller"] == second]
    m = x.merge(y, on=[*by, "realisation"], suffixes=("_1", "_2"))
    return [paired_counts(~g["crashed_1"].to_numpy(bool), ~g["crashed_2"].to_numpy(bool))
            for _, g in m.groupby(by, sort=True)]


def _pool(first, second, system, disturbance, tuning, strata) -> Pooled:
    p = pooled_paired(strata)
    return Pooled(first, second, system, disturbance, tuning, p.n, p.b, p.c, p.p_value,
                  p.difference, p.low, p.high, p.n_strata, p.cmh_p, p.homogeneity_p)


def pooled_rows(config, ep: pd.DataFrame) -> list[Pooled]:
    out = []
    for (system, tuning), g in ep.groupby(["system", "tuning"], sort=False):
        for first, second in pairs(config.controllers):
            for d in config.disturbances:
                gd = g[g["disturbance"] == d.label]
                st = _strata(gd, first, second, ["map"])
                if st:
                    out.append(_pool(first, second, system, d.label, tuning, st))
            st = _strata(g, first, second, ["map", "disturbance"])
            if st and len(config.disturbances) > 1:
                out.append(_pool(first, second, system, ALL, tuning, st))
    # tuned against hand-tuned, per controller
    if {"hand", "tuned"} <= set(ep["tuning"]):
        for (system, c), g in ep.groupby(["system", "controller"], sort=False):
            t = g[g["tuning"] == "tuned"].assign(controller="tuned")
            h = g[g["tuning"] == "hand"].assign(controller="hand")
            both = pd.concat([t, h])
            st = _strata(both, "tuned", "hand", ["map", "disturbance"])
            if st:
                p = pooled_paired(st)
                out.append(Pooled(f"{c}:tuned", f"{c}:hand", system, ALL, "tuned-vs-hand",
                                  p.n, p.b, p.c, p.p_value, p.difference, p.low, p.high,
                                  p.n_strata, p.cmh_p, p.homogeneity_p))
    return out


def mean_interval(x: np.ndarray) -> tuple[float, float, float]:
    """Mean of ``x`` with its 95 % t-interval (NaN limits for fewer than 2 values)."""
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return (float("nan"),) * 3
    m = float(x.mean())
    if x.size < 2:
        return m, float("nan"), float("nan")
    from scipy.stats import t

    half = float(t.ppf(0.975, x.size - 1) * x.std(ddof=1) / np.sqrt(x.size))
    return m, m - half, m + half


def leaderboard(ep: pd.DataFrame, timing: pd.DataFrame) -> list[Board]:
    out = []
    t = timing.set_index("task_id")["mean_cpu_ms"]
    for (system, tuning), g in ep.groupby(["system", "tuning"], sort=False):
        lines = []
        for c, gc in g.groupby("controller", sort=False):
            crashed = gc["crashed"].to_numpy(bool)
            safe = Rate.of(~crashed)
            ok = Rate.of(gc["reached"].to_numpy(bool) & ~crashed)
            ms = mean_interval(t.reindex(gc["task_id"]).to_numpy(float))
            err = mean_interval(gc["final_error"].to_numpy(float))
            lines.append((c, safe, ok, ms, err))
        lines.sort(key=lambda x: (-x[1].value, -x[2].value, x[3][0]))
        out += [Board(system, tuning, c, s.n, s.value, s.low, s.high, ok.value, ms[0], i + 1,
                      ok.low, ok.high, err[0], err[1], err[2], ms[1], ms[2])
                for i, (c, s, ok, ms, err) in enumerate(lines)]
    return out


def decision_rows(config, ep: pd.DataFrame, flags: dict[str, str]) -> list[DecisionRow]:
    from studies.arena.decisions import decide, members

    out = []
    for m in members(config):
        d = decide(config, ep, m)
        if d is None:
            continue
        last = d.looks[-1]
        out.append(DecisionRow(
            m.first, m.second, m.metric, m.system, m.disturbance, m.tuning, len(d.looks),
            last.n, last.b, last.c, last.difference, last.low, last.high, last.eq_low,
            last.eq_high, last.bound, d.verdict, d.detectable, d.discordance,
            mcnemar_exact(last.b, last.c),
            flags.get(f"{m.system} / {m.disturbance} / {m.tuning}")))
    return out


def uninformative_settings(ep: pd.DataFrame) -> dict[str, str]:
    """Settings (system, disturbance, tuning) whose rows cannot tell controllers apart, with
    the reason (:func:`~studies.arena.difficulty.uninformative`)."""
    from studies.arena.difficulty import uninformative

    out = {}
    for (s, d, t), g in ep.groupby(["system", "disturbance", "tuning"], sort=False):
        rates = {c: float(np.mean(~gc["crashed"].to_numpy(bool)))
                 for c, gc in g.groupby("controller", sort=False)}
        why = uninformative(rates, int(g.groupby("controller").size().min()))
        if why:
            out[f"{s} / {d} / {t}"] = why
    return out


def map_infos(config) -> list[MapInfo]:
    """Every test map with its difficulty (in the map's own units, before a system's scale);
    none when every system of the run has its own scene."""
    out: list[MapInfo] = []
    if all(own_scene(s) for s in config.systems):
        return out
    for f in config.families:
        for seed in config.map_seeds():
            g = arena_map(family(config, f.family), seed)
            d = g.difficulty
            out.append(MapInfo(f"{f.family}-{seed}", f.family, seed, len(g.circles),
                               d.bottleneck, d.path_length, d.straight_clearance,
                               len(g.moving) if g.moving else 0))
    return out


def scene_infos(config) -> list[SceneInfo]:
    """The scene of every system of the run that runs on its own."""
    out = []
    for name in config.systems:
        s = arena_system(name)
        if s.scene is None:
            continue
        m = s.plant(s.scene)
        out.append(SceneInfo(name, s.label, tuple(float(v) for v in s.scene.start),
                             tuple(float(v) for v in s.scene.goal), tuple(m.state_names),
                             int(m.nh), float(s.scene.dt), float(s.goal_radius)))
    return out


def tuned_section(config, ep: pd.DataFrame | None = None) -> dict:
    """The parameters each controller got on each system, and the budget used: the hand-tuned
    values always; with the shipped tuned ones (when this run used them) their training and
    validation scores for hand and tuned, and the test score of both on this run's episodes
    (same objective: :func:`~studies.arena.tuning.objective_value`)."""
    from studies.arena.tasks import hand_settings
    from studies.arena.tuning import objective_value

    ship = shipped()
    out = {}
    for s in config.systems:
        base = hand_settings(config, s)
        for c in config.controllers:
            entry: dict = {"hand": base.values(c), "searched": [p.name for p in space(c)]}
            t = ship.get((s, c))
            if "tuned" in config.tunings and t is not None:
                entry.update({"tuned": t.params, "kept": t.kept,
                              "budget": {**t.budget.__dict__,
                                         "total_episodes": t.budget.total_episodes},
                              "objective": t.objective, "disturbance": t.disturbance,
                              "training": {"hand": t.training.hand, "tuned": t.training.tuned,
                                           "episodes": t.training.episodes},
                              "validation": {"hand": t.validation.hand,
                                             "tuned": t.validation.tuned,
                                             "episodes": t.validation.episodes}})
                if ep is not None:
                    test: dict = {}
                    n_tuned = 0
                    for tuning in ("hand", "tuned"):
                        g = ep[(ep["system"] == s) & (ep["controller"] == c)
                               & (ep["tuning"] == tuning)]
                        if len(g):
                            ok = g["reached"].to_numpy(bool) & ~g["crashed"].to_numpy(bool)
                            test[tuning] = objective_value(
                                ok, g["final_error"].to_numpy(float) / arena_system(s).scale)
                        if tuning == "tuned":
                            n_tuned = len(g)
                    entry["test"] = {**test, "episodes": n_tuned}
            out[f"{s}/{c}"] = entry
    return out


def summarise(config, store) -> ArenaSummary:
    ep, timing, act = store.table("episodes"), store.table("timing"), store.table("activity")
    keys = ["controller", "system", "map", "disturbance", "tuning"]
    cells = []
    for key, rows in ep.groupby(keys, sort=False):
        tids = set(rows["task_id"])
        cells.append(Cell.of(key, rows, timing[timing["task_id"].isin(tids)],
                             act[act["task_id"].isin(tids)]))
    from studies.arena.decisions import design, members

    flags = uninformative_settings(ep)
    dz = design(config) if members(config) else None
    plan = None if dz is None else {
        "looks": dz.looks, "pairs_per_look": dz.pairs_per_look, "max_pairs": dz.max_pairs,
        "margin": dz.margin, "alpha": dz.alpha, "comparisons": dz.comparisons,
        "interval": dz.interval,
        "power": dz.power, "bounds": [float(b) for b in dz.bounds()],
        "equivalence_bounds": [float(b) for b in dz.equivalence_bounds()],
        "assumed_discordance": config.decision.discordance,
        "detectable_at_max": detectable(dz.max_pairs, config.decision.discordance, dz.alpha,
                                        dz.power, dz.looks, dz.comparisons),
        "planned_pairs": plan_pairs(dz.margin, config.decision.discordance, dz.alpha,
                                    dz.power, dz.looks, dz.comparisons)}
    return ArenaSummary(config.as_dict(), tuple(cells), tuple(pooled_rows(config, ep)),
                        tuple(leaderboard(ep, timing)), tuple(map_infos(config)),
                        tuned_section(config, ep), health(ep, act),
                        tuple(decision_rows(config, ep, flags)), plan, flags,
                        tuple(scene_infos(config)))


HEALTH_CELL = ("system", "disturbance", "tuning")  # one mechanism check over every test map
HEALTH_PAIR = ("map", "realisation")  # common random numbers: same map and realisation


def health(ep: pd.DataFrame, act: pd.DataFrame) -> StudyHealth:
    """Mechanism health per (system, disturbance, tuning), every map pooled: each mechanism
    over all its episodes there, each method paired with the one it wraps by map and
    realisation."""
    return study_health(ep, act, cell=HEALTH_CELL, pair=HEALTH_PAIR)

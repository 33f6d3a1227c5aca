"""Figures and report.md of an arena run (formatting only: numbers come from the summary, the
verdict from :mod:`studies.arena.findings`)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from studies.arena.episodes import arena_system
from studies.arena.findings import frontier, recommended, verdict, verdict_sentence
from studies.arena.summary import ALL, ArenaSummary, summarise
from workbench.scenarios.mechanism_health import console_lines, headline, report_lines
from workbench.scenarios.methods import labels, markers, method
from workbench.study import md_table, png_bytes, to_jsonable
from workbench.study.io import atomic_write_bytes, atomic_write_text
from workbench.study.latency import tail_lines
from workbench.study.spec import Summary


def frontier_figure(s: ArenaSummary) -> bytes:
    """Safety (95 % Wilson interval, every map and disturbance pooled) against CPU time
    per control step: one panel per system, one marker per controller and tuning."""
    systems = list(dict.fromkeys(b.system for b in s.leaderboard))
    fig, axes = plt.subplots(1, len(systems), figsize=(4.8 * len(systems), 4.4),
                             squeeze=False)
    for ax, sysname in zip(axes[0], systems, strict=True):
        for b in (b for b in s.leaderboard if b.system == sysname):
            ax.errorbar([b.mean_step_ms], [100 * b.safety],
                        yerr=[[100 * (b.safety - b.ci_low)], [100 * (b.ci_high - b.safety)]],
                        marker=markers()[b.controller], capsize=3, ls="none",
                        mfc="none" if b.tuning == "tuned" else None,
                        label=f"{labels()[b.controller]} ({b.tuning})")
        ax.set_xscale("log")
        ax.set_xlabel("CPU time per control step [ms] (log)")
        ax.set_ylabel("safety: episodes without a crash [%]")
        ax.set_ylim(-3, 103)
        ax.set_title(arena_system(sysname).label, fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    return png_bytes(fig)


def difficulty_figure(s: ArenaSummary) -> bytes:
    """Safety per map (every disturbance pooled) against the map's bottleneck clearance; the
    systems on their own scenes have no map and no panel."""
    bottleneck = {m.map: m.bottleneck for m in s.maps}
    own = {x.system for x in s.scenes}
    systems = list(dict.fromkeys(c.system for c in s.cells if c.system not in own))
    if not systems:
        fig, ax = plt.subplots(figsize=(4.8, 1.2))
        ax.axis("off")
        ax.text(0.5, 0.5, "no generated maps: every system ran on its own scene",
                ha="center", va="center", fontsize=9)
        return png_bytes(fig)
    fig, axes = plt.subplots(1, len(systems), figsize=(4.8 * len(systems), 4.0),
                             squeeze=False)
    for ax, sysname in zip(axes[0], systems, strict=True):
        keys = sorted({(c.controller, c.tuning) for c in s.cells if c.system == sysname},
                      key=lambda k: (list(labels()).index(k[0]), k[1]))
        for ctrl, tuning in keys:
            per = {}
            for c in s.cells:
                if (c.system, c.controller, c.tuning) == (sysname, ctrl, tuning):
                    safe, n = per.get(c.map, (0.0, 0))
                    per[c.map] = (safe + c.safety * c.n, n + c.n)
            maps = sorted(per, key=lambda m: bottleneck.get(m, np.nan))
            ax.plot([bottleneck.get(m, np.nan) for m in maps],
                    [100 * per[m][0] / per[m][1] for m in maps], marker=markers()[ctrl],
                    ls="-", lw=0.8, mfc="none" if tuning == "tuned" else None,
                    label=f"{labels()[ctrl]} ({tuning})")
        ax.set_xlabel("map bottleneck: least clearance on the widest path [m]")
        ax.set_ylabel("safety on the map [%]")
        ax.set_ylim(-3, 103)
        ax.set_title(arena_system(sysname).label, fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    return png_bytes(fig)


def _pct(x: float, lo: float | None = None, hi: float | None = None) -> str:
    if x is None or not np.isfinite(x):
        return "–"
    if lo is None or hi is None or not (np.isfinite(lo) and np.isfinite(hi)):
        return f"{100 * x:.0f}"
    return f"{100 * x:.0f} [{100 * lo:.0f}, {100 * hi:.0f}]"


def _p(p: float | None) -> str:
    return "–" if p is None or not np.isfinite(p) else f"{p:.2g}"


def _all_flagged(s: ArenaSummary, sysname: str, tuning: str) -> bool:
    """Every disturbance of this (system, tuning) is an uninformative setting."""
    flags = s.uninformative or {}
    keys = {f"{c.system} / {c.disturbance} / {c.tuning}" for c in s.cells
            if (c.system, c.tuning) == (sysname, tuning)}
    return bool(keys) and keys <= set(flags)


def _ms(b) -> str:
    if np.isfinite(b.ms_low):
        return f"{b.mean_step_ms:.2f} [{b.ms_low:.2f}, {b.ms_high:.2f}]"
    return f"{b.mean_step_ms:.2f}"


def leaderboard_table(s: ArenaSummary) -> list[str]:
    rows = [[arena_system(b.system).label, b.tuning, b.rank, labels()[b.controller],
             method(b.controller).mechanism, b.n, _pct(b.safety, b.ci_low, b.ci_high),
             _pct(b.success, b.success_low, b.success_high), _ms(b),
             "uninformative" if _all_flagged(s, b.system, b.tuning) else ""]
            for b in s.leaderboard]
    return md_table(["system", "tuning", "rank", "controller", "mechanism", "episodes",
                     "safety % [95%]", "success % [95%]", "CPU ms / step [95%]", "note"], rows)


def recommendation_lines(s: ArenaSummary) -> list[str]:
    """Per system and tuning: the recommended mechanism(s) with their numbers, and the
    safety-versus-cost frontier."""
    out = []
    for sysname, tuning in dict.fromkeys((b.system, b.tuning) for b in s.leaderboard):
        label = f"### {arena_system(sysname).label}, {tuning}"
        if _all_flagged(s, sysname, tuning):
            out += [label, "", "No recommendation: every setting of this system is "
                    "uninformative (" + "; ".join(
                        f"{k.split(' / ')[1]}: {v}" for k, v in (s.uninformative or {}).items()
                        if k.startswith(f"{sysname} /") and k.endswith(f"/ {tuning}"))
                    + ").", ""]
            continue
        rec = recommended(s, sysname, tuning)
        rows = [[labels()[b.controller], method(b.controller).mechanism, b.n,
                 _pct(b.safety, b.ci_low, b.ci_high),
                 _pct(b.success, b.success_low, b.success_high),
                 (f"{b.final_error:.2f} [{b.final_error_low:.2f}, {b.final_error_high:.2f}]"
                  if np.isfinite(b.final_error_low) else f"{b.final_error:.2f}"), _ms(b)]
                for b in rec]
        boards = [b for b in s.leaderboard if (b.system, b.tuning) == (sysname, tuning)]
        front = ", ".join(f"{labels()[b.controller]} ({100 * b.safety:.0f} % at "
                          f"{b.mean_step_ms:.2f} CPU ms)" for b in frontier(boards))
        out += [label, "", *md_table(["recommended", "mechanism", "episodes",
                                      "safety % [95%]", "success % [95%]",
                                      "final error [m] [95%]", "CPU ms / step [95%]"], rows), "",
                f"Safety-versus-cost frontier (no other controller is both safer and "
                f"cheaper): {front}.", ""]
    return out


def decisions_table(s: ArenaSummary) -> list[str]:
    rows = [[f"{labels()[r.first]} vs {labels()[r.second]}", r.metric, arena_system(r.system).label,
             r.disturbance, r.tuning, r.looks, r.n, f"{r.b} / {r.c}",
             f"{100 * r.difference:+.1f} [{100 * r.low:+.1f}, {100 * r.high:+.1f}]",
             r.verdict + (" (uninformative setting)" if r.uninformative else ""),
             "–" if r.detectable is None else f"{100 * r.detectable:.0f}", _p(r.p_value)]
            for r in s.decisions]
    return md_table(["comparison", "metric", "system", "disturbance", "tuning", "looks",
                     "pairs", "only first / only second", "difference, points [repeated 95%]",
                     "verdict", "detectable difference, points", "McNemar p (fixed-sample)"],
                    rows)


def design_lines(s: ArenaSummary) -> list[str]:
    d = s.design
    if d is None:
        return ["No comparison was declared, so nothing is decided.", ""]
    bounds = ", ".join(f"{b:.2f}" for b in d["bounds"])
    stat = {"score": "Tango's score interval", "agresti-min": "Agresti-Min's adjusted "
            "interval"}.get(d.get("interval", ""), d.get("interval", ""))
    m = d["comparisons"]
    return [f"How the verdicts are reached: each declared comparison, in each system, "
            f"disturbance and tuning it covers, is one of {m} comparison{'s' if m != 1 else ''}"
            f" whose family-wise error rate is {d['alpha']:g} (Bonferroni). Pairs are added "
            f"in up to {d['looks']} rounds of {d['pairs_per_look']} (new maps and new "
            f"disturbance draws), at most {d['max_pairs']} pairs; after each round the "
            f"repeated confidence interval of the paired difference ({stat} for paired "
            "proportions, with O'Brien-Fleming alpha-spending critical values "
            f"{bounds}) decides: above 0 the first is better, below 0 worse, inside "
            f"±{100 * d['margin']:.0f} points at the equivalence level equivalent; otherwise "
            "the next round runs, and after the last one the comparison is undecided. The "
            f"power of {100 * d['power']:.0f} % at a difference of {100 * d['margin']:.0f} "
            f"points, assuming {100 * d['assumed_discordance']:.0f} % discordant pairs, needs "
            f"{d['planned_pairs']} pairs per comparison; this run's budget is "
            f"{d['max_pairs']}"
            + (" (sized to decide)." if d["max_pairs"] >= d["planned_pairs"] else
               f": not sized to decide at that difference (at its full budget it detects "
               f"{100 * d['detectable_at_max']:.0f} points).") + "", ""]


def pooled_table(s: ArenaSummary) -> list[str]:
    rows = [[arena_system(p.system).label, p.disturbance, p.tuning, f"{p.first} vs {p.second}",
             p.n_maps, p.n, f"{p.b} / {p.c}",
             f"{100 * p.difference:+.1f} [{100 * p.low:+.1f}, {100 * p.high:+.1f}]",
             _p(p.p_value), _p(p.cmh_p), _p(p.homogeneity_p)] for p in s.pooled]
    return md_table(["system", "disturbance", "tuning", "pair", "strata", "pairs",
                     "only first safe / only second safe", "safety difference, points [95%]",
                     "McNemar p", "CMH p", "homogeneity p"], rows)


def maps_table(s: ArenaSummary) -> list[str]:
    rows = [[m.map, m.n_circles, m.moving, f"{m.bottleneck:.2f}", f"{m.path_length:.1f}",
             f"{m.straight_clearance:.2f}"] for m in s.maps]
    return md_table(["map", "circles", "moving", "bottleneck [m]", "widest path length [m]",
                     "straight-line clearance [m]"], rows)


def _state(names: tuple[str, ...], x: tuple[float, ...]) -> str:
    return ", ".join(f"{n} {v:.3g}" for n, v in zip(names, x, strict=True))


def scenes_lines(s: ArenaSummary) -> list[str]:
    """The systems that ran on their own scene, each described once (they have no map)."""
    out = []
    for x in s.scenes:
        out += [f"- {x.label} ({x.system}) ran on its own scene, not on the generated maps: "
                f"from ({_state(x.state_names, x.start)}) to ({_state(x.state_names, x.goal)}), "
                f"{x.constraints} constraint{'s' if x.constraints != 1 else ''} h(x) > 0, "
                f"dt {x.dt:g} s, goal radius {x.goal_radius:.3g} (in its own distance to the "
                "goal). Its episodes are labelled own-<seed>: the seed only selects the "
                "random streams, so each round draws new disturbances on the same scene."]
    return out + ([""] if out else [])


def _score(e: dict, part: str) -> str:
    v = e.get(part) or {}
    h, t = v.get("hand"), v.get("tuned")
    if h is None or t is None:
        return "–"
    return f"{h:.3f} / {t:.3f} ({v.get('episodes')})"


def tuned_table(s: ArenaSummary) -> list[str]:
    rows = []
    for key, e in s.tuned.items():
        hand = ", ".join(f"{k} {v:.3g}" for k, v in e["hand"].items())
        tuned = ", ".join(f"{k} {v:.3g}" for k, v in e.get("tuned", {}).items()) or "–"
        b = e.get("budget")
        budget = (f"{b['trials']} trials x {b['episodes']} episodes, {b['finalists']} "
                  f"finalists x {b['validation']} validation episodes" if b else "–")
        val = e.get("validation") or {}
        flag = ""
        if val.get("hand") is not None and val.get("tuned") is not None:
            flag = ("hand kept (no candidate beat it on validation)" if e.get("kept") == "hand"
                    else "worse than hand on validation" if val["tuned"] < val["hand"] else "")
        test = e.get("test") or {}
        if flag == "" and test.get("hand") is not None and test.get("tuned") is not None \
                and test["tuned"] < test["hand"]:
            flag = "worse than hand on the test maps"
        rows.append([key, hand, tuned, budget, _score(e, "training"), _score(e, "validation"),
                     _score(e, "test"), flag])
    return md_table(["system / controller", "hand-tuned", "tuned (shipped)", "budget",
                     "training score hand / tuned (episodes)", "validation", "test", "note"],
                    rows)


def cells_table(s: ArenaSummary) -> list[str]:
    flags = s.uninformative or {}
    rows = [[c.system, c.map, c.disturbance, c.tuning, labels()[c.controller], c.n,
             _pct(c.safety, c.ci_low, c.ci_high), _pct(c.success, c.success_low, c.success_high),
             f"{c.final_error:.2f}", f"{c.mean_step_ms:.2f}",
             ", ".join(f"{k} {100 * v:.1f} %" for k, v in c.activity.items()) or "–",
             "uninformative" if f"{c.system} / {c.disturbance} / {c.tuning}" in flags else ""]
            for c in s.cells]
    return md_table(["system", "map", "disturbance", "tuning", "controller", "n",
                     "safety % [95%]", "success % [95%]", "final error [m]", "CPU ms / step",
                     "mechanism activity", "note"], rows)


def summary(finished) -> Summary:
    """summary.json: cells, pooled comparisons, leaderboards, maps with their difficulty, the
    tuned parameters and budget, mechanism health, the declared comparisons' verdicts and the
    verdict on the paper's claim (i); one console line per leaderboard entry, per decision and
    per mechanism-health problem."""
    s = summarise(finished.config, finished.store)
    lines = tuple(f"{b.system:18s} {b.tuning:5s} #{b.rank} {b.controller:14s} safety "
                  f"{100 * b.safety:5.1f} % [{100 * b.ci_low:.0f}, {100 * b.ci_high:.0f}]  "
                  f"success {100 * b.success:5.1f} %  {b.mean_step_ms:6.2f} CPU ms/step"
                  for b in s.leaderboard)
    lines += tuple(f"{r.system} {r.disturbance} {r.tuning}: " + verdict_sentence(r)
                   for r in s.decisions)
    lines += tuple(f"uninformative: {k}: {v}" for k, v in (s.uninformative or {}).items())
    lines += console_lines(s.health)
    return Summary({**to_jsonable(s), "verdict": to_jsonable(verdict(s))}, s, lines)


def report(finished, summ) -> Path:
    s: ArenaSummary = summ.value
    out = Path(finished.out)
    atomic_write_bytes(out / "frontier.png", frontier_figure(s))
    atomic_write_bytes(out / "difficulty.png", difficulty_figure(s))
    cfg = s.config
    v = verdict(s)
    flags = s.uninformative or {}
    lines = ["# The arena: which safety mechanism, on which system, at what cost", "",
             finished.run_line, "", headline(s.health), "",
             "Every controller shares one sampler (the same samples, horizon and noise "
             "streams); in a realisation, every controller and tuning meets the same "
             "disturbances (common random numbers). An episode ends at a crash, at the goal or "
             f"after {cfg['steps']} steps.", "",
             "## Recommendation per system", "",
             "Every map and disturbance pooled; rates with Wilson 95 % intervals, final error "
             "and CPU time per step as means with 95 % t-intervals.", "",
             *recommendation_lines(s),
             "## Declared comparisons and their verdicts", "",
             *design_lines(s), *decisions_table(s), "",
             "## The paper's claim (i)", ""]
    if v is None:
        lines += ["This run did not compare SA-RMPPI with BaS-MPPI.", ""]
    else:
        lines += [f"- {t}" for t in v.text] + [""]
    lines += ["The paper reports SA-RMPPI safer than BaS-MPPI on one map of the double "
              "integrator (Table I: 97/91/87/61/49 % against 99/74/63/47/31 % at velocity "
              "variances 0, 5, 10, 50 and 100, so +14 points at 50 and +18 at 100). The "
              "arena's maps are others (generated, several per run), so its rates are not "
              "those of Table I; the claim's direction and size are tested, and each "
              "difference of the paper is checked against our interval at the same level.",
              ""]
    if flags:
        lines += ["## Uninformative settings", "",
                  "These settings cannot tell the controllers apart; their rows are shown "
                  "below labelled, not as results:", "",
                  *[f"- {k}: {w}" for k, w in flags.items()], ""]
    lines += ["## Leaderboards", "", "![frontier](frontier.png)", "",
              *leaderboard_table(s), "",
              *tail_lines(finished.store.table("step_times"), ["system", "tuning", "controller"],
                          lambda k: f"{k[0]}, {k[1]}, {labels().get(k[2], k[2])}"),
              "## Paired comparisons pooled over maps (descriptive)", "",
              f"'{ALL}' pools every disturbance (strata: map x disturbance). These are not "
              "declared comparisons: their p-values are not corrected and decide nothing.", "",
              *pooled_table(s), "",
              *report_lines(s.health),
              "## Safety against map difficulty", "", "![difficulty](difficulty.png)", "",
              *(maps_table(s) if s.maps else ["No generated maps in this run."]), "",
              *scenes_lines(s),
              "## Tuning", "",
              "Hand-tuned values are the workbench's defaults for each system; tuned values "
              "come from the same budget of automatic tuning (optuna's TPE) per controller on "
              "training maps, maximising the success rate minus 0.01 x the final distance to "
              "the goal (map units). The best training trials and the hand point are then "
              "scored on held-out validation maps; the hand point is shipped unless a trial "
              "beats it there. Training, validation and test maps are disjoint. Scores use "
              "the same objective on each set of episodes.", "",
              *tuned_table(s), "",
              "## Assumed values", "",
              *([("- An episode ends when the robot is within the goal radius "
                  f"({cfg['goal_radius']:g} m, times the system's map scale): safety is "
                  "counted up to the goal, not while holding position there.")]
                if s.maps else []),
              "- A disturbance level is given in the double integrator's units; each system "
              "scales it by its own factor and applies it to its own default states.",
              "- The barrier-state weight q_beta is not tuned (it is compiled into the "
              "kernels).",
              *(["- A system built from a model runs on its own scene: an episode ends "
                 "within its own goal radius, in its own distance to the goal (safety is "
                 "counted up to the goal), and it has no tuned values (assumptions §12.4)."]
                if s.scenes else []),
              f"- The share of discordant pairs assumed when sizing the rounds: "
              f"{100 * cfg['decision']['discordance']:.0f} %.", "",
              "## Every cell", "", *cells_table(s), "",
              "Mechanism activity: the mean over steps of each key a method reports. It counts "
              "effects, not calls: a step counts only when the mechanism changed the applied "
              "control, or the samples' controls, costs or gains behind it, by more than 1e-9 "
              "relative; fallbacks and nominal resets are events (how often that path was "
              "taken).", ""]
    path = out / "report.md"
    atomic_write_text(path, "\n".join(lines))
    return path

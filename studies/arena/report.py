"""Figures and report.md of an arena run (formatting only: numbers come from the summary, the
verdict from :mod:`studies.arena.findings`)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from studies.arena.findings import verdict
from studies.arena.summary import ALL, ArenaSummary, summarise
from workbench.scenarios.mechanism_health import console_lines, headline, report_lines
from workbench.scenarios.methods import labels, markers, method
from workbench.scenarios.systems import system
from workbench.study import md_table, png_bytes, to_jsonable
from workbench.study.io import atomic_write_bytes, atomic_write_text
from workbench.study.spec import Summary


def frontier_figure(s: ArenaSummary) -> bytes:
    """Safety (95 % Wilson interval, every map and disturbance pooled) against compute time
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
        ax.set_xlabel("compute time per control step [ms] (log)")
        ax.set_ylabel("safety: episodes without a crash [%]")
        ax.set_ylim(-3, 103)
        ax.set_title(system(sysname).label, fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    return png_bytes(fig)


def difficulty_figure(s: ArenaSummary) -> bytes:
    """Safety per map (every disturbance pooled) against the map's bottleneck clearance."""
    bottleneck = {m.map: m.bottleneck for m in s.maps}
    systems = list(dict.fromkeys(c.system for c in s.cells))
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
        ax.set_title(system(sysname).label, fontsize=10)
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


def leaderboard_table(s: ArenaSummary) -> list[str]:
    rows = [[system(b.system).label, b.tuning, b.rank, labels()[b.controller],
             method(b.controller).mechanism, b.n, _pct(b.safety, b.ci_low, b.ci_high),
             _pct(b.success), f"{b.mean_step_ms:.2f}"] for b in s.leaderboard]
    return md_table(["system", "tuning", "rank", "controller", "mechanism", "episodes",
                     "safety % [95%]", "success %", "ms / step"], rows)


def pooled_table(s: ArenaSummary) -> list[str]:
    rows = [[system(p.system).label, p.disturbance, p.tuning, f"{p.first} vs {p.second}",
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


def tuned_table(s: ArenaSummary) -> list[str]:
    rows = []
    for key, e in s.tuned.items():
        hand = ", ".join(f"{k} {v:.3g}" for k, v in e["hand"].items())
        tuned = ", ".join(f"{k} {v:.3g}" for k, v in e.get("tuned", {}).items()) or "–"
        b = e.get("budget")
        budget = (f"{b['trials']} trials x {b['episodes']} episodes" if b else "–")
        score = (f"{e['hand_training_score']:.3f} -> {e['training_score']:.3f}"
                 if "training_score" in e else "–")
        rows.append([key, hand, tuned, budget, score])
    return md_table(["system / controller", "hand-tuned", "tuned", "budget",
                     "training score, hand -> tuned"], rows)


def cells_table(s: ArenaSummary) -> list[str]:
    rows = [[c.system, c.map, c.disturbance, c.tuning, labels()[c.controller], c.n,
             _pct(c.safety, c.ci_low, c.ci_high), _pct(c.success, c.success_low, c.success_high),
             f"{c.final_error:.2f}", f"{c.mean_step_ms:.2f}",
             ", ".join(f"{k} {100 * v:.1f} %" for k, v in c.activity.items()) or "–"]
            for c in s.cells]
    return md_table(["system", "map", "disturbance", "tuning", "controller", "n",
                     "safety % [95%]", "success % [95%]", "final error [m]", "ms / step",
                     "mechanism activity"], rows)


def summary(finished) -> Summary:
    """summary.json: cells, pooled comparisons, leaderboards, maps with their difficulty, the
    tuned parameters and budget, mechanism health, and the verdict on the paper's claim (i);
    one console line per leaderboard entry and per mechanism-health problem."""
    s = summarise(finished.config, finished.store)
    lines = tuple(f"{b.system:18s} {b.tuning:5s} #{b.rank} {b.controller:14s} safety "
                  f"{100 * b.safety:5.1f} % [{100 * b.ci_low:.0f}, {100 * b.ci_high:.0f}]  "
                  f"success {100 * b.success:5.1f} %  {b.mean_step_ms:6.2f} ms/step"
                  for b in s.leaderboard)
    lines += console_lines(s.health)
    return Summary({**to_jsonable(s), "verdict": to_jsonable(verdict(s))}, s, lines)


def report(finished, summ) -> Path:
    s: ArenaSummary = summ.value
    out = Path(finished.out)
    atomic_write_bytes(out / "frontier.png", frontier_figure(s))
    atomic_write_bytes(out / "difficulty.png", difficulty_figure(s))
    cfg = s.config
    v = verdict(s)
    lines = ["# The arena: controllers x systems x maps x disturbances", "",
             finished.run_line, "", headline(s.health), "",
             "Every controller shares one sampler (the same samples, horizon and noise "
             "streams); in a realisation, every controller and tuning meets the same "
             "disturbances (common random numbers). An episode ends at a crash, at the goal or "
             f"after {cfg['steps']} steps.", "",
             "## The verdict on the paper's claim (i)", ""]
    if v is None:
        lines += ["This run did not compare SA-RMPPI with BaS-MPPI.", ""]
    else:
        lines += [f"- {t}" for t in v.text] + [""]
    lines += ["The paper reports SA-RMPPI safer than BaS-MPPI on one map of the double "
              "integrator (Table I: 97/91/87/61/49 % against 99/74/63/47/31 % at velocity "
              "variances 10 to 100). The arena's maps, systems and disturbances are others, "
              "so its rates are not compared with those numbers; only the direction of the "
              "claim is tested.", "",
              "## Leaderboards", "", "![frontier](frontier.png)", "",
              *leaderboard_table(s), "",
              "## Paired comparisons pooled over maps", "",
              f"'{ALL}' pools every disturbance (strata: map x disturbance).", "",
              *pooled_table(s), "",
              *report_lines(s.health),
              "## Safety against map difficulty", "", "![difficulty](difficulty.png)", "",
              *maps_table(s), "",
              "## Tuning", "",
              "Hand-tuned values are the workbench's defaults for each system; tuned values "
              "come from the same budget of automatic tuning (optuna's TPE) per controller on "
              "training maps disjoint from the test maps, maximising the success rate, ties "
              "broken by the final distance to the goal.", "",
              *tuned_table(s), "",
              "## Assumed values", "",
              "- An episode ends when the robot is within the goal radius "
              f"({cfg['goal_radius']:g} m, times the system's map scale): safety is counted "
              "up to the goal, not while holding position there.",
              "- A disturbance level is given in the double integrator's units; each system "
              "scales it by its own factor and applies it to its own default states.",
              "- The barrier-state weight q_beta is not tuned (it is compiled into the "
              "kernels).", "",
              "## Every cell", "", *cells_table(s), ""]
    path = out / "report.md"
    atomic_write_text(path, "\n".join(lines))
    return path

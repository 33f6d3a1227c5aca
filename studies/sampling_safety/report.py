"""Figures and report.md of a sampling-safety run (formatting only: numbers come from the
summary, verdicts from :mod:`studies.sampling_safety.findings`)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from studies.sampling_safety.findings import frontier, most_collision_free, verdicts
from studies.sampling_safety.summary import SamplingSafetySummary, summarise
from studies.sampling_safety.tasks import setup
from workbench import plot
from workbench.scenarios.mechanism_health import console_lines, headline, report_lines
from workbench.scenarios.methods import labels, markers, method
from workbench.study import md_table, png_bytes, to_jsonable
from workbench.study.cost_pass import order_text, stored_pass
from workbench.study.io import atomic_write_bytes, atomic_write_text
from workbench.study.latency import LATENCY_HEADER, LATENCY_NOTE
from workbench.study.spec import Summary


def frontier_figure(s: SamplingSafetySummary) -> bytes:
    """Safety (95 % Wilson interval) against mean CPU time per control step, one panel per
    variance, one marker per controller: the cost-safety frontier."""
    vs = s.config["variances"]
    fig, axes = plt.subplots(1, len(vs), figsize=(4.6 * len(vs), 4.4), squeeze=False)
    for ax, v in zip(axes[0], vs, strict=True):
        for c in (c for c in s.cells if c.variance == v):
            ax.errorbar([s.cost_ms(c.controller)], [100 * c.safety],
                        yerr=[[100 * (c.safety - c.ci_low)], [100 * (c.ci_high - c.safety)]],
                        marker=markers()[c.controller], capsize=3, ls="none",
                        label=labels()[c.controller])
        front, _ = frontier(s, v)
        ax.plot([s.cost_ms(c.controller) for c in front], [100 * c.safety for c in front], "--",
                color="0.5", lw=1, zorder=0)
        ax.axvline(1e3 * s.dt, color="tab:red", lw=0.8, ls=":")
        ax.set_xscale("log")
        ax.set_xlabel("CPU time per control step [ms] (log)")
        ax.set_ylabel("safety: episodes without a crash [%]")
        ax.set_ylim(-3, 103)
        ax.set_title(f"velocity variance {v:g}", fontsize=10)
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    return png_bytes(fig)


def samples_figure(s: SamplingSafetySummary) -> bytes:
    """Collision-free sample fraction (95 % t-interval over realisations) per controller."""
    vs = s.config["variances"]
    ctrls = [c for c in labels() if any(x.controller == c for x in s.cells)]
    fig, ax = plt.subplots(figsize=(max(6.0, 0.9 * len(ctrls) * len(vs)), 4.2))
    w = 0.8 / len(vs)
    for k, v in enumerate(vs):
        cells = [s.cell(c, v) for c in ctrls]
        y = np.array([100 * c.collision_free_sample_fraction for c in cells])
        lo = np.array([100 * c.cf_low for c in cells])
        hi = np.array([100 * c.cf_high for c in cells])
        err = np.nan_to_num(np.vstack([y - lo, hi - y]))
        ax.bar(np.arange(len(ctrls)) + (k - (len(vs) - 1) / 2) * w, y, w, yerr=err,
               capsize=2, label=f"variance {v:g}")
    ax.set_xticks(np.arange(len(ctrls)), [labels()[c] for c in ctrls], rotation=30, ha="right",
                  fontsize=8)
    ax.set_xlabel("controller")
    ax.set_ylabel("collision-free samples per step [%]")
    ax.set_ylim(0, 105)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return png_bytes(fig)


def _pct(x: float, lo: float, hi: float, d: int = 1) -> str:
    if not np.isfinite(x):
        return "–"
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return f"{100 * x:.{d}f}"
    return f"{100 * x:.{d}f} [{100 * lo:.{d}f}, {100 * hi:.{d}f}]"


def _num(x: float, lo: float, hi: float, d: int = 1) -> str:
    if not np.isfinite(x):
        return "–"
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return f"{x:.{d}f}"
    return f"{x:.{d}f} [{lo:.{d}f}, {hi:.{d}f}]"


def cells_table(s: SamplingSafetySummary) -> list[str]:
    order = list(labels())
    rows = [[labels()[c.controller], f"{c.variance:g}", c.n, _pct(c.safety, c.ci_low, c.ci_high, 0),
             _pct(c.collision_free_sample_fraction, c.cf_low, c.cf_high),
             _num(c.ess_mean, c.ess_low, c.ess_high), f"{c.cpu_ms:.2f}",
             _num(c.final_error.mean, c.final_error_low, c.final_error_high, 3),
             f"{100 * c.reached.value:.0f}"]
            for c in sorted(s.cells, key=lambda c: (c.variance, order.index(c.controller)))]
    return md_table(["controller", "variance", "n", "safety % [95%]",
                     "collision-free samples % [95%]", "ESS [95%]", "CPU ms / step",
                     "final error, safe [m] [95%]", "reached 1 m %"], rows)


def latency_rows(s: SamplingSafetySummary) -> list[list[str]]:
    """Per cell: CPU and wall means, wall p50 / p95 / p99 / max, steps."""
    order = list(labels())
    return [[f"{labels()[c.controller]}, variance {c.variance:g}", f"{c.cpu_ms:.2f}",
             f"{c.wall.mean_ms:.2f}", *c.wall.row(), str(c.wall.n)]
            for c in sorted(s.cells, key=lambda c: (c.variance, order.index(c.controller)))]


def cost_lines(s: SamplingSafetySummary) -> list[str]:
    """The report's cost-pass section: the order by cost with its ties, and per method the CPU
    ms per step with its interval, the ratio to the cheapest and the wall-clock tail."""
    head = ["## What a method costs: the cost pass", ""]
    if not s.cost:
        return [*head, "This run has no cost pass (it was stored before the pass existed); the "
                "costs above are the episodes' mean CPU time per step. Rerun the study into a "
                "new folder to measure one.", ""]
    cheapest = s.cost[0].cpu_ms
    rows = [[labels()[c.method], _num(c.cpu_ms, c.cpu_low, c.cpu_high, 2),
             f"{c.cpu_ms / cheapest:.2f}", *c.wall.row(), str(c.rounds)] for c in s.cost]
    return [*head,
            f"Order by cost, cheapest first (braces: not separated): "
            f"**{order_text(s.cost_order, labels())}**.", "",
            *md_table(["method", "CPU ms / step [95%]", "x cheapest", "wall p50", "wall p95",
                       "wall p99", "wall max", "rounds"], rows), "",
            f"Measured once in this run after every episode had finished: {s.cost_what}. Each "
            "round replays the same episode for every method, so the CPU time of a method is "
            "the same work every round; the interval is over rounds. Two methods are ordered "
            "when the 95 % interval of their per-round cost ratio lies wholly beyond 1 +- 3 % "
            "(the resolution: between passes on one machine a ratio moved by up to 4 %); "
            "otherwise they are tied. A step starts with the caches the other methods' steps "
            "left, as on a robot where other work runs between control steps. The order does not "
            "depend on how many workers ran the episodes. Costs in the frontier, the answers "
            "and the claim come from this pass.", ""]


def activity_table(s: SamplingSafetySummary) -> list[str]:
    rows = []
    for c in sorted(s.cells, key=lambda c: (list(labels()).index(c.controller), c.variance)):
        if c.activity:
            found = s.health.of(c.controller, {"variance": c.variance})
            rows.append([labels()[c.controller], f"{c.variance:g}",
                         ", ".join(f"{k} {100 * v:.1f} %" for k, v in c.activity.items()),
                         "; ".join(f.title for f in found) or "–"])
    return md_table(["controller", "variance", "mechanism activity (mean over steps)",
                     "mechanism health"], rows)


def paired_table(s: SamplingSafetySummary, ref: str) -> list[str]:
    rows = []
    for p in s.paired:
        if p.second != ref:
            continue
        f = s.pair_fraction(p.first, ref, p.variance)
        rows.append([labels()[p.first], f"{p.variance:g}", p.n, f"{p.b} / {p.c}",
                     f"{100 * p.difference:+.0f} [{100 * p.low:+.0f}, {100 * p.high:+.0f}]",
                     f"{p.p_value:.2g}",
                     f"{100 * f.difference:+.1f} [{100 * f.low:+.1f}, {100 * f.high:+.1f}]"
                     if f and np.isfinite(f.low) else "–"])
    return md_table(["controller", "variance", "n", f"only it safe / only {labels()[ref]} safe",
                     "safety difference, points [95%]", "McNemar p",
                     "collision-free samples difference, points [95%]"], rows)


def answers(s: SamplingSafetySummary) -> list[str]:
    out = []
    for v in s.config["variances"]:
        best, second, sep = most_collision_free(s, v)
        front, eff = frontier(s, v)
        if best is None:
            continue
        out.append(
            f"- Variance {v:g}: the most collision-free samples are {labels()[best.controller]}'s "
            f"({_pct(best.collision_free_sample_fraction, best.cf_low, best.cf_high)} %), "
            + (f"ahead of {labels()[second.controller]} "
               f"({_pct(second.collision_free_sample_fraction, second.cf_low, second.cf_high)} %)"
               f" with {'disjoint' if sep else 'overlapping'} intervals. " if second else ". ")
            + f"Safest per millisecond: {labels()[eff.controller]} "
            f"({_pct(eff.safety, eff.ci_low, eff.ci_high, 0)} % safe at "
            f"{s.cost_ms(eff.controller):.2f} CPU ms). Not dominated in (safety, CPU ms): "
            + ", ".join(f"{labels()[c.controller]} ({100 * c.safety:.0f} %, "
                        f"{s.cost_ms(c.controller):.2f} ms)" for c in front) + ".")
    return out


def where(cfg: dict) -> str:
    """Where the episodes ran, in words."""
    label = cfg.get("system_label", "double integrator")
    if cfg.get("model_scene"):
        return f"the {label} (your model: its own start, goal and constraints)"
    fam = cfg.get("family")
    place = ("the navigation map" if not fam else
             f"the generated {fam['family']} map of seed {cfg.get('map_seed', 0)}")
    if cfg.get("system_name", "double_integrator") == "double_integrator":
        return place
    return f"{place} with the {label}"


def scaled(cfg: dict) -> str:
    ls, dist = cfg.get("level_scale", 1.0), cfg.get("disturbed", ["vx", "vy"])
    text = f" on {', '.join(dist)}"
    return text + (f", times {ls:.3g} for this system's control authority" if ls != 1.0
                   else "")


def defaults_section(cfg: dict) -> list[str]:
    """Where the system's settings came from (systems built from a model only)."""
    if not cfg.get("model_scene"):
        return []
    return ["## Where the settings came from", "",
            "Each setting of a system built from your model is either given by you or derived "
            "from the model by the rule shown.", "",
            *md_table(["setting", "source"], [[f, src] for f, src in cfg["origins"]]), ""]


def map_figure(config, store) -> bytes:
    """The map the episodes ran on, every obstacle kind drawn (a grid as its zero level set,
    its inside shaded), with each controller's paths at the run's largest variance."""
    nav = setup(config.resolved())
    ep = store.table("episodes")
    v = max(config.variances)
    fig, ax = plt.subplots(figsize=(6.4, 5.2))
    plot.scene(ax, nav)
    for i, c in enumerate(config.controllers):
        rows = ep[(ep["controller"] == c) & (ep["variance"] == v)]
        plot.paths(ax, [store.arrays(t)["X"] for t in rows["task_id"]], model=nav.plant,
                   color=f"C{i % 10}", label=labels()[c])
    ax.set_title(f"the map and every path at variance {v:g}")
    ax.legend(fontsize=7, loc="best")
    return png_bytes(fig)


def map_lines(config, store, out: Path) -> list[str]:
    """The report's map section: the figure, or why it could not be drawn."""
    try:
        atomic_write_bytes(out / "map.png", map_figure(config, store))
    except ValueError as exc:  # a system the planar plots cannot show
        return ["## The map", "", f"Not drawn: {exc}", ""]
    return ["## The map", "", "![the map and the paths](map.png)", "",
            "Obstacles of every kind as the plant sees them (a signed-distance grid as its "
            "zero level set, inside shaded); each line is one realisation's path.", ""]


def write_report(s: SamplingSafetySummary, out: Path, run_line: str,
                 map_section: list[str] | None = None) -> Path:
    atomic_write_bytes(out / "frontier.png", frontier_figure(s))
    atomic_write_bytes(out / "samples.png", samples_figure(s))
    cfg = s.config
    word = {True: "holds", False: "does not hold", None: "undecided"}
    lines = [
        "# Sampling safety: the field's safe-sampling methods on one sampler", "",
        f"Every controller runs on {where(cfg)} with the same sampler (N = "
        f"{cfg['sampler']['n_samples']}, T = {cfg['sampler']['horizon']}, sigma = "
        f"{cfg['sampler']['sigma']}, lambda = {cfg['sampler']['lam']:.4g}), {cfg['steps']} "
        f"steps per episode, velocity-disturbance variances {cfg['variances']}{scaled(cfg)}, "
        f"{cfg['realisations']} realisations per cell. Realisation j uses the same disturbance "
        f"and controller random streams for every controller (common random numbers), so the "
        f"comparisons below are paired. {run_line}", "",
        headline(s.health), "",
        "## The paper's claim (1)", "",
        "The paper: barrier states are \"more sample efficient by metric of collision free "
        "trajectories\" and \"computationally feasible to perform per sample\", while CBF "
        "filters are \"computationally infeasible\" per sample. Each part, decided from this "
        "run (a part holds or fails only where the 95 % intervals decide it at every "
        "variance):", "",
        *md_table(["part of claim (1)", "verdict", "evidence"],
                  [[v.claim, word[v.holds], v.evidence] for v in verdicts(s)]), "",
        "## Which method keeps the most samples collision-free, and which is safest per "
        "millisecond", "", *answers(s), "",
        "![cost-safety frontier](frontier.png)", "",
        "Safety against CPU time per control step (log scale), 95 % Wilson intervals; the "
        "dashed line joins the methods no other beats in both; the dotted red line is the "
        "control period.", "",
        "![collision-free samples](samples.png)", "",
        *(map_section or []),
        "## All cells", "", *cells_table(s), "",
        "Collision-free samples: per control step, the share of the samples the update was "
        "weighted over that never crashed (for the robust controllers, the real samples with "
        "feedback), averaged over the steps of an episode; the interval is over realisations. "
        "ESS: effective sample size of the update's weights.", "",
        *cost_lines(s),
        "## What a step costs in the episodes: CPU time and the wall-clock tail", "",
        *md_table(LATENCY_HEADER, latency_rows(s)), "", LATENCY_NOTE + " These ran beside "
        "the other workers of the run: their CPU means move between runs (a shared cache, the "
        "clock), which is why the order by cost comes from the cost pass.", "",
        "## What each mechanism did", "",
        "How often each method's safety mechanism acted, as a share of control steps (or of "
        "sample-steps for the per-sample projection, of horizon steps for the AL and ECBF "
        "feedback laws). Activity counts effects, not calls: a step counts only when the "
        "mechanism changed the applied control, or the samples' controls, costs or gains behind "
        "it, by more than 1e-9 relative (a feedback law counts only on steps where the nominal "
        "state differs from the measured one: otherwise its gains multiply zero); a mechanism "
        "at 0 % changed nothing in this run. Fallbacks (feedback_fallback, selection_fallback, "
        "shield_failed, infeasible, ecbf_infeasible, backup_not_at_rest) and nominal_reset "
        "are events: how often that path was taken.", "", *activity_table(s), "",
        *report_lines(s.health),
        "## Paired against BaS-MPPI", "", *paired_table(s, "bas_mppi"), "",
        "## Paired against SA-RMPPI", "", *paired_table(s, "sa_rmppi"), "",
        *defaults_section(cfg),
        "## The methods", "",
        *md_table(["controller", "mechanism"], [[labels()[c], method(c).mechanism]
                                                for c in cfg["controllers"]]), "",
        "Data: `episodes.parquet/.csv` (one row per realisation), `timing.parquet/.csv` "
        "(compute time per realisation, not reproducible), `step_times.parquet/.csv` (wall and "
        "CPU time of every step), `cost_pass.parquet/.csv` and `cost_pass.json` (the cost "
        "pass: every step of every round), `activity.parquet/.csv` (mechanism activity per "
        "realisation), `tasks/*.npz` (paths and per-step sample statistics), `summary.json` "
        "(`cells`, `paired`, `paired_fraction`, `health`, `claims`).", ""]
    path = out / "report.md"
    atomic_write_text(path, "\n".join(lines))
    return path


def summary(finished) -> Summary:
    """summary.json: the cells (safety, collision-free samples, ESS, time per step and
    mechanism activity, with intervals), paired tests, mechanism health, the verdicts on the
    paper's claim (1); one console line per cell and per mechanism-health problem."""
    s = summarise(finished.config, finished.store, stored_pass(finished))
    names = labels()
    lines = tuple(f"{names[c.controller]:30s} var {c.variance:6g}  safety {100 * c.safety:5.1f} % "
                  f"[{100 * c.ci_low:.0f}, {100 * c.ci_high:.0f}]  collision-free samples "
                  f"{100 * c.collision_free_sample_fraction:5.1f} %  ESS {c.ess_mean:7.1f}  "
                  f"{c.cpu_ms:6.2f} CPU ms/step  wall p50 / p99 {c.wall.p50_ms:.2f} / "
                  f"{c.wall.p99_ms:.2f} ms" for c in s.cells)
    lines += console_lines(s.health)
    return Summary({**to_jsonable(s), "claims": to_jsonable(verdicts(s))}, s, lines)


def report(finished, summary) -> Path:
    return write_report(summary.value, finished.out, finished.run_line,
                        map_lines(finished.config, finished.store, finished.out))

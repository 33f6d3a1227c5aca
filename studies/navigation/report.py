"""Figures and report.md from a run's summary, tidy tables and stored arrays (formatting only:
numbers come from the summary, sentences from ``findings`` and ``evidence``)."""

from __future__ import annotations

from pathlib import Path

from studies.navigation import figures, paper
from studies.navigation.evidence import all_evidence
from studies.navigation.findings import all_claims
from studies.navigation.summary import NavigationSummary
from studies.navigation.wording import NAMES
from workbench.study import RunStore, fmt_rate, md_table, supported
from workbench.study.io import atomic_write_bytes, atomic_write_text
from workbench.study.latency import tail_lines
from workbench.study.report import num, see

HEADINGS = {"safer": "SA-RMPPI safer than BaS-MPPI (paired)", "rmse": "BaS-MPPI lower RMSE",
            "monotone": "Safety decreases with the variance",
            "crash_sites": "Where BaS-MPPI crashes", "velocity": "Velocities and time to goal",
            "reached": "Reaching the goal, real time",
            "magnitude": f"Magnitudes ({see('14.4')}: 10 points, factor 2)"}
NO_SAFE = "no safe episodes"


def _list(values) -> str:
    return ", ".join(f"{v:g}" for v in values) or "none"


def _r(x: float, d: int = 4, why: str = NO_SAFE) -> str:
    return num(x, f".{d}f", why)


def table_i(s: NavigationSummary, with_paper: bool = True) -> list[str]:
    """SA-RMPPI and BaS-MPPI per variance, with Table I's numbers beside ours (``with_paper``)
    or ours alone."""
    rows = []
    for v in s.config["variances"]:
        a, b, p = s.cell("sa_rmppi", v), s.cell("bas_mppi", v), s.pair("sa_rmppi", "bas_mppi", v)
        ref = paper.TABLE_I.get(v)

        def theirs(c: str, i: int, ref=ref) -> list[str]:
            return [f"{ref[c][i]}" if ref else "–"] if with_paper else []

        rows.append([f"{v:g}",
                     fmt_rate(a.safe, 0) if a else "–", *theirs("sa_rmppi", 0),
                     fmt_rate(b.safe, 0) if b else "–", *theirs("bas_mppi", 0),
                     _r(a.rmse) if a else "–", *theirs("sa_rmppi", 1),
                     _r(b.rmse) if b else "–", *theirs("bas_mppi", 1),
                     f"{100 * p.difference:+.0f} [{100 * p.low:+.0f}, {100 * p.high:+.0f}], "
                     f"p = {num(p.p_value, '.2g')}" if p else "–"])
    ref = ["Table I"] if with_paper else []
    return md_table(["variance", "SA-RMPPI safety % (ours)", *ref, "BaS-MPPI safety % "
                     "(ours)", *ref, "SA-RMPPI RMSE [m] (ours)", *ref, "BaS-MPPI RMSE [m] "
                     "(ours)", *ref, "SA − BaS, points [95%], McNemar"], rows)


def cells_table(s: NavigationSummary) -> list[str]:
    """Every cell; the alpha rule column tells apart the cells of one controller and
    variance."""
    robust = ("sa_rmppi", "rmppi")
    rows = [[NAMES[c.controller], c.rule if c.controller in robust else "none (not robust)",
             f"{c.variance:g}", "main" if c.main else "alpha sweep",
             c.n, fmt_rate(c.safe, 0), _r(c.rmse), _r(c.rmse_all, why="no episodes"),
             _r(c.rmse_time), fmt_rate(c.reached, 0) if c.reached.n else f"n/a ({NO_SAFE})",
             _r(c.time_to_goal_s.median, 2, "never within the goal radius"),
             _r(c.mean_speed.mean, 2, "no episodes"),
             _r(c.mean_step_ms, 1, "no timing"), _r(c.cpu_ms, 1, "no timing"),
             f"{100 * c.nominal_differs_fraction:.1f}",
             f"{100 * c.alpha_fallback_rate:.1f}", f"{100 * c.ksafe_fallback_rate:.2f}",
             f"{_r(c.ess_nom_mean, 1, 'no samples')} / "
             f"{_r(c.ess_real_mean, 1, 'no feedback samples')}"]
            for c in s.cells]
    return md_table(["controller", "alpha rule", "variance", "part", "n", "safety %",
                     "RMSE safe [m]", "RMSE all [m]", "RMSE time-avg [m]", "reached (safe)",
                     "median time to 1 m [s]", "mean speed [m/s]", "wall ms/step", "CPU ms/step",
                     "nominal ≠ real %",
                     "alpha fallback %", "K_safe fallback %", "ESS nom / real"], rows)


def _illustration(s: NavigationSummary) -> list[str]:
    m = s.illustration
    if not m:
        return []
    return [f"Fig. 4 data: SA-RMPPI with limits ±{m['u_limit']:g} under velocity variance "
            f"{m['variance']:g}, SAIS batch at step {m['step']} (the first step >= 5 with the "
            f"nominal state away from the real one); within the horizon "
            f"{100 * m['real_samples_crashed']:.0f}% of the feedback samples and "
            f"{100 * m['nominal_samples_crashed']:.0f}% of the nominal samples crash "
            f"(paper: feedback samples often collide near the end of the horizon); the episode "
            f"{'crashed' if m['crashed'] else 'did not crash'} within its steps.", ""]


def write_figures(s: NavigationSummary, store: RunStore, plan, ids: dict, scene,
                  crashed_by_task: dict, with_paper: bool = True) -> list[str]:
    out, circles = store.root, scene.circle_array()
    panels = []
    for (c, v), ts in plan.main.items():
        arrs = [store.arrays(ids[t])["X"][:, :2] for t in ts]
        crashed = [bool(crashed_by_task[ids[t]]) for t in ts]
        panels.append((c, v, arrs, crashed))
    names = []
    atomic_write_bytes(out / "fig5_paths.png",
                       figures.paths_figure(panels, circles, scene.start, scene.goal))
    names.append("fig5_paths.png")
    present = [v for v in (10.0, 100.0) if v in s.config["variances"]] or [
        v for v in s.config["variances"] if v > 0][:2]
    if present:
        atomic_write_bytes(out / "fig6_velocity.png",
                           figures.velocity_figure(store.table("velocity"), present))
        names.append("fig6_velocity.png")
    if plan.illustration is not None:
        tid = ids[plan.illustration]
        atomic_write_bytes(out / "fig4_samples.png", figures.samples_figure(
            store.arrays(tid), store.meta(tid), circles, scene.start, scene.goal))
        names.append("fig4_samples.png")
    atomic_write_bytes(out / "safety.png",
                       figures.safety_figure(s, paper.TABLE_I if with_paper else {}))
    names.append("safety.png")
    if s.config["sweep_variances"]:
        atomic_write_bytes(out / "alpha_tradeoff.png", figures.alpha_figure(s))
        names.append("alpha_tradeoff.png")
    return names


def write_report(s: NavigationSummary, store: RunStore, plan, ids: dict, scene,
                 assumed: list[dict], run_line: str, comparison=None) -> Path:
    """report.md and its figures. ``comparison`` (a :class:`~workbench.study.report.Provenance`
    from :func:`studies.navigation.paper.comparison`): for a custom run (a user map, changed
    parameters) the report says so and leaves out every comparison with Table I."""
    ep = store.table("episodes")
    crashed = dict(zip(ep["task_id"], ep["crashed"], strict=True))
    with_paper = comparison is None or comparison.comparable
    figs = write_figures(s, store, plan, ids, scene, crashed, with_paper)
    cfg, claims, evidence = s.config, all_claims(s), all_evidence(s)
    if not with_paper:
        claims.pop("magnitude", None)
        evidence.pop("disturbance scale", None)
    if scene.circles:  # the gates and passageways are the generated map's
        claims.pop("crash_sites", None)
    banner = [] if comparison is None else comparison.banner(paper.NOT_COMPARABLE)
    table = (["## Table I beside ours", "", *table_i(s), ""] if with_paper else
             ["## SA-RMPPI and BaS-MPPI in this run", "", *table_i(s, False), ""])
    lines = [
        "# Navigation study: SA-RMPPI vs BaS-MPPI (paper Table I, Figs. 4-6)", "",
        f"Velocity-disturbance variances {_list(cfg['variances'])} m²/s⁴, {cfg['realisations']} "
        f"realisations per cell, {cfg['steps']} steps per episode, controllers "
        f"{', '.join(NAMES[c] for c in cfg['controllers'])}; alpha sweep of "
        f"{NAMES[cfg['sweep_controller']]} at variances {_list(cfg['sweep_variances'])} "
        f"({cfg['sweep_realisations']} realisations). Realisation j uses the same disturbance "
        f"and controller random streams for every controller (common random numbers), so "
        f"controllers are compared paired. {run_line}", "", *banner, *table,
        "Safety: % of realisations without a crash (95% Wilson interval). RMSE: final distance "
        f"to the goal over safe realisations ({see('12.2')}). Last column: paired difference "
        "on the same realisations (Newcombe interval, exact McNemar test).", "",
        f"## The paper's claims ({see('14.4')}), one by one", "",
        "Every sentence is generated from this run's numbers; the verdict is computed "
        "(`studies/navigation/findings.py`).", ""]
    for key, cs in claims.items():
        if cs:
            lines += [f"### {HEADINGS[key]}", "", *[f"- {c.text}" for c in cs], ""]
    lines += ["## Evidence: what the robust part does, ablations, alpha", "",
              "Printed only where the numbers support the sentence "
              "(`studies/navigation/evidence.py`).", ""]
    for name, cs in evidence.items():
        lines += [f"### {name}", "", *(supported(cs) or ["No sentence of this group is "
                                                       "supported by this run."]), ""]
    lines += ["## All cells", "", *cells_table(s), "", "## Figures", "",
              *[f"![{f}]({f})" for f in figs], "",
              "Fig. 5: every realisation's path per cell, crash points marked x. Fig. 6: mean "
              "± std of vx, vy over the realisations still running at each time. Fig. 4: one "
              "SAIS batch (nominal samples blue, feedback samples red). Safety vs variance "
              "with 95% intervals" + (" (Table I dashed)" if with_paper else "") + ". Alpha "
              "trade-off: safety vs RMSE per rule.",
              "", *_illustration(s),
              *tail_lines(store.table("step_times"), ["controller", "rule", "variance"],
                          lambda k: f"{NAMES.get(k[0], k[0])} ({k[1]}), variance {k[2]:g}"),
              "## Assumed and sourced values", "",
              *md_table(["quantity", "value", "source"],
                        [[a["name"], a["value"], a["source"]] for a in assumed]), "",
              "Data: `episodes.parquet/.csv` (one row per realisation), `velocity.parquet/.csv`"
              " (every few steps), `timing.parquet/.csv` (compute time, not reproducible), "
              "`step_times.parquet/.csv` (wall and CPU time of every step), "
              "`tasks/*.npz` (trajectories X, U per realisation), `summary.json` (`cells`, "
              "`paired`), `map.json`, `manifest.json`, `run.json`.", ""]
    path = store.root / "report.md"
    atomic_write_text(path, "\n".join(lines))
    return path


def report(finished, summary) -> Path:
    """The framework's report step: figures and report.md from a finished run."""
    return write_report(summary.value, finished.store, finished.plan, finished.ids,
                        finished.config.scene, summary.data["assumed"], finished.run_line,
                        paper.comparison(finished.config, finished.out))

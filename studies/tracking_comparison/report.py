"""Figures and report.md from the study's data (summary.json, rollouts.csv, trajectories)."""

from __future__ import annotations

import io
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from studies.tracking_comparison.config import RELEVANT
from workbench.io import atomic_write_bytes, atomic_write_text

NAMES = {"ecbf": "ECBF-filtered iLQG", "al": "AL-iLQG", "bas": "BaS-iLQG"}
COLORS = {"ecbf": "tab:blue", "al": "tab:red", "bas": "tab:green"}
PARAM_NAMES = {"q_beta": "q_beta (BaS)", "pole": "ECBF poles p1 = p2", "q_scale": "Q scale",
               "ecbf_noise": "ECBF noise vs filter"}


def _fmt(v) -> str:
    try:
        return f"{float(v):g}"
    except ValueError:
        return str(v)


def _by_value(sel: pd.DataFrame) -> pd.DataFrame:
    """Rows in the order of the swept values (numeric if they are numbers)."""
    try:
        order = sel["value"].astype(float)
    except ValueError:
        return sel
    return sel.assign(_v=order).sort_values("_v").drop(columns="_v")
HEADLINE = {"ecbf": "failure_rate", "al": "unsafe_rate", "bas": "unsafe_rate"}


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return buf.getvalue()


def _obstacle(summary: dict) -> tuple[float, float, float]:
    scene = summary["scene"]
    return (*scene["obstacle_center"], scene["obstacle_radius"])


def _scene(ax, summary: dict, ref: np.ndarray) -> None:
    cx, cy, r = _obstacle(summary)
    ax.add_patch(plt.Circle((cx, cy), r, color="0.75", zorder=0))
    ax.plot(ref[:, 0], ref[:, 1], "--", color="tab:orange", lw=1.2, label="reference (unsafe)")
    ax.plot(ref[0, 0], ref[0, 1], "kx", ms=9, mew=2)
    ax.plot(ref[-1, 0], ref[-1, 1], "k*", ms=12)
    ax.set_aspect("equal")
    ax.set_xlabel("p_x [m]")
    ax.set_ylabel("p_y [m]")


def trajectory_figure(summary: dict, traj, method: str) -> bytes:
    """Paper Figs. 1-3: the noise-free closed loop (left) and the Monte Carlo overlay (right)."""
    fig, axes = plt.subplots(1, 2, figsize=(12, 3.6), sharey=True)
    ref = traj["reference"]
    nominal, mc = traj[f"{method}_nominal"], traj[f"{method}_mc"]
    for ax in axes:
        _scene(ax, summary, ref)
    axes[0].plot(nominal[:, 0], nominal[:, 1], color=COLORS[method], lw=2, label="nominal")
    axes[0].set_title(f"{NAMES[method]}: noise-free closed loop")
    axes[0].legend(fontsize=8, loc="upper left")
    cx, cy, r = _obstacle(summary)
    h = ((mc[:, :, 0] - cx) ** 2 + (mc[:, :, 1] - cy) ** 2 - r**2).min(axis=1)
    for path, unsafe in zip(mc, h < 0, strict=True):
        axes[1].plot(path[:, 0], path[:, 1], color="tab:red" if unsafe else COLORS[method],
                     lw=0.4, alpha=0.25)
    axes[1].plot(nominal[:, 0], nominal[:, 1], "k", lw=1)
    axes[1].set_title(f"{len(mc)} Monte Carlo rollouts (seed 0), unsafe in red: "
                      f"{int((h < 0).sum())}")
    return _png(fig)


def histogram_figure(rows: pd.DataFrame, column: str, xlabel: str, line: float) -> bytes:
    methods = [m for m in NAMES if m in set(rows["method"])]
    fig, axes = plt.subplots(1, len(methods), figsize=(4 * len(methods), 3.2), squeeze=False)
    for ax, m in zip(axes[0], methods, strict=True):
        v = rows.loc[rows["method"] == m, column].to_numpy()
        ax.hist(v, bins=60, color=COLORS[m], alpha=0.85)
        ax.axvline(line, color="k", lw=1, ls="--")
        ax.set_title(NAMES[m])
        ax.set_xlabel(xlabel)
    axes[0][0].set_ylabel("rollouts")
    return _png(fig)


def sweep_figure(sweep: pd.DataFrame) -> bytes:
    params = list(dict.fromkeys(sweep["parameter"]))
    fig, axes = plt.subplots(2, len(params), figsize=(4.2 * len(params), 6), squeeze=False)
    for j, p in enumerate(params):
        sel = sweep[sweep["parameter"] == p]
        for i, metric in enumerate(("unsafe", "failure")):
            ax = axes[i][j]
            for m in NAMES:
                s = _by_value(sel[sel["method"] == m])
                if len(s) == 0:
                    continue
                y = 100 * s[f"{metric}_rate"].to_numpy()
                err = 100 * np.vstack([s[f"{metric}_rate"] - s[f"{metric}_ci_low"],
                                       s[f"{metric}_ci_high"] - s[f"{metric}_rate"]])
                ax.errorbar(np.arange(len(s)), y, yerr=err, marker="o", capsize=3,
                            color=COLORS[m], label=NAMES[m])
                ax.set_xticks(np.arange(len(s)), [_fmt(v) for v in s["value"]])
            ax.set_xlabel(PARAM_NAMES.get(p, p))
            ax.set_ylabel(f"{metric} rate [%]")
            ax.set_ylim(-3, 103)
    axes[0][0].legend(fontsize=8)
    return _png(fig)


def _pct(s: dict, name: str) -> str:
    return (f"{100 * s[f'{name}_rate']:.1f}% [{100 * s[f'{name}_ci_low']:.1f}, "
            f"{100 * s[f'{name}_ci_high']:.1f}]")


def _drivers(sweep: pd.DataFrame, method: str, metric: str) -> list[tuple[str, float, str]]:
    """(parameter, range of the rate, text) per swept parameter, largest range first."""
    out = []
    for p in dict.fromkeys(sweep["parameter"]):
        if p not in RELEVANT[method]:
            continue
        s = _by_value(sweep[(sweep["parameter"] == p) & (sweep["method"] == method)])
        if len(s) == 0:
            continue
        rates = s[metric].to_numpy()
        text = ", ".join(f"{_fmt(v)}: {100 * r:.1f}%" for v, r in zip(s["value"], rates,
                                                                        strict=True))
        out.append((p, float(rates.max() - rates.min()), text))
    return sorted(out, key=lambda t: -t[1])


def _comparison(summary: dict, sweep: pd.DataFrame) -> list[str]:
    lines = ["| method | paper [P] | our unsafe % [95% CI] | our failure % [95% CI] | "
             "SPEC 14.4 band (headline) | in band |", "|---|---|---|---|---|---|"]
    notes = []
    for m, s in summary["methods"].items():
        paper = summary["paper"][m]
        metric = paper["metric"]
        lo, hi = paper["band"]
        value = s[metric]
        inside = lo <= value <= hi
        lines.append(f"| {NAMES[m]} | {paper['text']} | {_pct(s, 'unsafe')} | "
                     f"{_pct(s, 'failure')} | {metric.split('_')[0]} "
                     f"{100 * lo:g}-{100 * hi:g}% | {'yes' if inside else 'NO'} |")
        drivers = _drivers(sweep, m, metric) if len(sweep) else []
        sens = "; ".join(f"{PARAM_NAMES.get(p, p)} ({t})" for p, _, t in drivers)
        if not inside:
            top = drivers[0] if drivers else None
            why = (f" The swept assumption that moves it most is **{PARAM_NAMES.get(top[0])}** "
                   f"(range {100 * top[1]:.0f} points)." if top else
                   " No sweep was run, so no assumption can be singled out.")
            notes.append(f"- **{NAMES[m]}: {metric.replace('_', ' ')} "
                         f"{100 * value:.1f}% lies outside {100 * lo:g}-{100 * hi:g}%.**{why}"
                         f" Sweep ({metric.replace('_', ' ')}): {sens}.")
        elif drivers:
            notes.append(f"- {NAMES[m]}: {metric.replace('_', ' ')} {100 * value:.1f}% is inside "
                         f"the band. Sensitivity ({metric.replace('_', ' ')}): {sens}.")
    return [*lines, "", *notes]


def _point(sweep: pd.DataFrame, method: str, parameter: str, value) -> pd.Series | None:
    sel = sweep[(sweep["method"] == method) & (sweep["parameter"] == parameter)]
    sel = sel[[_fmt(v) == _fmt(value) for v in sel["value"]]]
    return sel.iloc[0] if len(sel) else None


def _discussion(summary: dict, sweep: pd.DataFrame) -> list[str]:
    """What the numbers say about each method, from this run's data only."""
    methods, lines = summary["methods"], []
    sw = sweep if len(sweep) else pd.DataFrame(columns=["method", "parameter", "value"])
    if "ecbf" in methods:
        s, radius = methods["ecbf"], summary["config"]["target_radius"]
        text = (f"- **ECBF**: {s['n_unsafe']} of {s['n_rollouts']} rollouts unsafe and "
                f"{s['n_not_reached']} farther than {radius:g} m from the target at the end")
        if s["n_unsafe"] == 0 and summary["config"]["base"]["ecbf_noise"] == "before":
            text += (": with the noise entering before the filter, the QP removes the unsafe "
                     "part of every perturbation, so every failure is a missed target (the "
                     "robot slides around the obstacle and falls behind the reference)")
        after = _point(sw, "ecbf", "ecbf_noise", "after")
        if after is not None:
            text += (f". With the noise after the filter (SPEC 13 E7) "
                     f"{100 * after['unsafe_rate']:.1f}% of rollouts are unsafe and "
                     f"{100 * after['failure_rate']:.1f}% fail; the paper's remark that the "
                     "filter 'is unable to maintain safety with large control deviations' fits "
                     "that placement better than ours")
        lines.append(text + ".")
    if "al" in methods:
        s, nom = methods["al"], summary["nominal"].get("al", {})
        text = (f"- **AL-iLQG**: the nominal trajectory touches the constraint (closed-loop min h "
                f"{nom.get('closed_loop_min_h', float('nan')):.1e} m²), so a perturbation towards "
                f"the obstacle near the contact arc makes a run unsafe: "
                f"{100 * s['unsafe_rate']:.1f}% here vs ≈60% in the paper")
        al = sw[(sw["method"] == "al") & sw["parameter"].isin(RELEVANT["al"])]
        if len(al):
            lo, hi = al["unsafe_rate"].min(), al["unsafe_rate"].max()
            best = al.loc[al["unsafe_rate"].idxmin()]
            text += (f". Over the sweep it ranges {100 * lo:.1f}-{100 * hi:.1f}%, lowest at "
                     f"{PARAM_NAMES.get(best['parameter'])} = {_fmt(best['value'])}")
            if lo > 0.6:
                text += ("; no swept value brings it down to 60%, so the remaining gap comes "
                         "from an assumption not swept here (the scene geometry of SPEC 3.3, "
                         "R, or how tightly the paper's AL converged onto the boundary)")
        lines.append(text + ".")
    if "bas" in methods:
        s = methods["bas"]
        text = (f"- **BaS-iLQG**: {s['n_unsafe']} of {s['n_rollouts']} rollouts unsafe "
                f"({100 * s['unsafe_rate']:.2f}%, paper: 0 of 500)")
        qb = _by_value(sw[(sw["method"] == "bas") & (sw["parameter"] == "q_beta")])
        if len(qb):
            text += "; by q_beta: " + ", ".join(
                f"{_fmt(v)}: {100 * r:.1f}%" for v, r in zip(qb["value"], qb["unsafe_rate"],
                                                             strict=True))
            text += " (a heavier barrier weight keeps the feedback further from the obstacle)"
        lines.append(text + ".")
    return lines


def _details(summary: dict) -> list[str]:
    lines = ["| method | n | unsafe | not at target | unsafe and not at target | "
             "mean / median final distance [m] | min h: min, 5%, median [m²] | "
             "infeasible QP steps (rollouts) | unsafe with an infeasible QP step | "
             "QP solves (fallbacks) |", "|---|---|---|---|---|---|---|---|---|---|"]
    for m, s in summary["methods"].items():
        mh = s["min_h"]
        lines.append(
            f"| {NAMES[m]} | {s['n_rollouts']} | {s['n_unsafe']} | {s['n_not_reached']} | "
            f"{s['n_unsafe_and_not_reached']} | {s['mean_final_distance']:.3f} / "
            f"{s['median_final_distance']:.3f} | {mh['min']:.3f}, {mh['p05']:.3f}, "
            f"{mh['median']:.3f} | {s['infeasible_qp_steps']} ({s['rollouts_with_infeasible_qp']})"
            f" | {s['unsafe_with_infeasible_qp']} | {s['qp_steps']} ({s['fallback_steps']}) |")
    lines += ["", "Per-seed spread (rate over each seed's rollouts):", "",
              "| method | unsafe: mean ± std [min, max] | failure: mean ± std [min, max] |",
              "|---|---|---|"]
    for m, s in summary["methods"].items():
        cells = []
        for name in ("unsafe_rate", "failure_rate"):
            p = s[f"per_seed_{name}"]
            cells.append(f"{100 * p['mean']:.1f} ± {100 * p['std']:.1f}% "
                         f"[{100 * p['min']:.1f}, {100 * p['max']:.1f}]")
        lines.append(f"| {NAMES[m]} | {cells[0]} | {cells[1]} |")
    lines += ["", "Nominal (noise-free) closed loops:", ""]
    for m, info in summary["nominal"].items():
        extra = ""
        if m == "al":
            extra = (f", {info['outer_iterations']} outer iterations, max violation "
                     f"{info['max_violation']:.1e} m²")
        if m == "ecbf":
            extra = (f", ECBF initial condition met: {info['ecbf_initial_condition_ok']}, "
                     f"infeasible QP steps {info['closed_loop_infeasible_qp_steps']}")
        lines.append(f"- {NAMES[m]}: planner cost {info['cost']:.2f} (converged "
                     f"{info['converged']}, {info['iterations']} iLQG iterations{extra}); "
                     f"closed loop min h {info['closed_loop_min_h']:.2e} m², final distance "
                     f"{info['closed_loop_final_distance']:.3f} m")
    return lines


def _sweep_section(summary: dict, sweep: pd.DataFrame) -> list[str]:
    if not len(sweep):
        return ["No sensitivity sweep in this run."]
    cfg = summary["config"]
    methods = summary["methods"]
    lines = [f"{cfg['sweep_seeds']} seeds x {cfg['sweep_rollouts']} rollouts per method and "
             "point, one [A] value changed at a time (others at their defaults), the same noise "
             "draws at every point. The paper's numbers imply the ranking BaS < ECBF < AL by "
             "failure rate (0%, ≈27%, ≥60%); it gives no unsafe-only rate for ECBF, so the "
             "unsafe ordering is shown for information.", "",
             "| parameter | value | " + " | ".join(
                 f"{NAMES[m]} unsafe / failure %" for m in methods) +
             " | order by failure | order by unsafe |",
             "|---|---|" + "---|" * len(methods) + "---|---|"]
    ranks = {(r["parameter"], _fmt(r["value"])): r for r in summary["sweep_ranking"]}
    for (p, v), grp in sweep.groupby(["parameter", "value"], sort=False):
        cells = []
        for m in methods:
            s = grp[grp["method"] == m].iloc[0]
            cells.append(f"{100 * s['unsafe_rate']:.1f} / {100 * s['failure_rate']:.1f}")
        r = ranks.get((p, _fmt(v)), {})
        rk = [f"{r[k + '_order']}" + (" (paper's)" if r[k] else "") if k in r else "-"
              for k in ("failure_rate", "unsafe_rate")]
        lines.append(f"| {PARAM_NAMES.get(p, p)} | {_fmt(v)} | " + " | ".join(cells) +
                     f" | {rk[0]} | {rk[1]} |")
    n = len(summary["sweep_ranking"])
    held = sum(bool(r.get("failure_rate")) for r in summary["sweep_ranking"])
    lines += ["", f"The paper's ranking BaS < ECBF < AL by failure rate holds at {held} of {n} "
              "sweep points (strict order of point estimates; ties count as not holding).",
              "", "![sweep](sweep.png)"]
    return lines


def write_report(out: Path) -> Path:
    """Read the run's data in ``out`` and write the figures and report.md."""
    out = Path(out)
    summary = json.loads((out / "summary.json").read_text())
    rows = pd.read_csv(out / "rollouts.csv")
    main = rows[rows["study"] == "main"]
    sweep = pd.read_csv(out / "sweep.csv") if (out / "sweep.csv").stat().st_size > 1 else \
        pd.DataFrame()
    with np.load(out / ".cache" / "trajectories.npz") as traj:
        for m in summary["methods"]:
            atomic_write_bytes(out / f"trajectories_{m}.png", trajectory_figure(summary, traj, m))
    atomic_write_bytes(out / "min_h_hist.png",
                       histogram_figure(main, "min_h", "min over k of h [m²]", 0.0))
    atomic_write_bytes(out / "final_distance_hist.png", histogram_figure(
        main, "final_distance", "final distance to the target [m]",
        summary["config"]["target_radius"]))
    if len(sweep):
        atomic_write_bytes(out / "sweep.png", sweep_figure(sweep))
    cfg = summary["config"]
    lines = [
        "# Tracking comparison: ECBF-filtered iLQG, AL-iLQG, BaS-iLQG (paper Sec. III)", "",
        f"Profile `{cfg['profile']}`: {cfg['n_seeds']} seeds x {cfg['n_rollouts']} Monte Carlo "
        f"rollouts per method, control noise std {cfg['noise_std']:g}, limits ±15, one "
        f"obstacle on the reference (SPEC 3.3, 6, 7, 12.1). Rates are pooled over seeds with "
        f"95% Wilson intervals. Wall time {summary['wall_time_s']:.1f} s "
        f"({summary['tasks']['computed']} of {summary['tasks']['total']} tasks computed, the "
        f"rest resumed from `.cache/`; {cfg['workers']} workers).", "",
        "## Paper vs this run", "",
        *_comparison(summary, sweep), "",
        "Unsafe: min over steps k = 0..N of h(x_k) < 0. Failure: unsafe, or the final position "
        f"more than {cfg['target_radius']:g} m from the target. The paper's ECBF figure is a "
        "failure rate ('unable to remain safe and reach the target'), its AL and BaS figures "
        "are unsafe rates (SPEC 13 E7).", "",
        "## What drives the numbers", "", *_discussion(summary, sweep), "",
        "## Details", "", *_details(summary), "",
        "![min h](min_h_hist.png)", "", "![final distance](final_distance_hist.png)", "",
        "## Trajectories (paper Figs. 1-3)", "",
        *[f"![{NAMES[m]}](trajectories_{m}.png)" for m in summary["methods"]], "",
        "## Sensitivity sweep over assumed values", "", *_sweep_section(summary, sweep), "",
        "## Assumed and sourced values used", "",
        "| quantity | value | source |", "|---|---|---|",
        *[f"| {a['name']} | {a['value']} | {a['source']} |" for a in summary["assumed"]], "",
        "Data: `summary.json` (per-method rates, intervals, per-seed spread, sweep), "
        "`rollouts.csv` (one row per rollout, main study and sweep), `sweep.csv`.", "",
    ]
    path = out / "report.md"
    atomic_write_text(path, "\n".join(lines))
    return path

"""Figures and report.md from a run's summary, tidy table and stored paths (formatting only:
numbers come from the summary, sentences that interpret them from ``findings``)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from studies.tracking_comparison.findings import Ranking, all_claims, drivers
from studies.tracking_comparison.methods import Setup
from studies.tracking_comparison.paper import (
    NOT_COMPARABLE,
    PAPER_BY_METHOD,
    assumed_values,
    comparison,
)
from studies.tracking_comparison.summary import Outcome, TrackingSummary, summarise
from studies.tracking_comparison.wording import NAMES, PARAM_NAMES
from workbench.scenarios.scenes import TrackingScene
from workbench.study import RunStore, fmt_rate, md_table, png_bytes, supported, to_jsonable
from workbench.study.io import atomic_write_bytes, atomic_write_text
from workbench.study.latency import tail_lines
from workbench.study.spec import Summary

COLORS = {"ecbf": "tab:blue", "al": "tab:red", "bas": "tab:green"}
# the swept parameters as axis labels, with their units
AXIS_NAMES = {"q_beta": "q_beta, BaS barrier weight (dimensionless)",
              "pole": "ECBF poles p1 = p2 [1/s]", "q_scale": "factor on Q (dimensionless)",
              "ecbf_noise": "control noise enters the ECBF filter",
              "noise_std": "control-noise std [m/s²]"}


def _fmt(v) -> str:
    return v if isinstance(v, str) else f"{v:g}"


def _scene(ax, scene: TrackingScene) -> None:
    (cx, cy), r = scene.obstacle.center, scene.obstacle.radius
    ref = scene.reference()[:, :2]
    ax.add_patch(plt.Circle((cx, cy), r, color="0.75", zorder=0))
    ax.plot(ref[:, 0], ref[:, 1], "--", color="tab:orange", lw=1.2, label="reference (unsafe)")
    ax.plot(ref[0, 0], ref[0, 1], "kx", ms=9, mew=2)
    ax.plot(ref[-1, 0], ref[-1, 1], "k*", ms=12)
    ax.set_aspect("equal")
    ax.set_xlabel("p_x [m]")
    ax.set_ylabel("p_y [m]")


def trajectory_figure(scene: TrackingScene, nominal: np.ndarray, mc: np.ndarray,
                      method: str) -> bytes:
    """Paper Figs. 1-3: the noise-free closed loop (left) and the Monte Carlo overlay (right)."""
    fig, axes = plt.subplots(1, 2, figsize=(12, 3.6), sharey=True)
    for ax in axes:
        _scene(ax, scene)
    axes[0].plot(nominal[:, 0], nominal[:, 1], color=COLORS[method], lw=2, label="nominal")
    axes[0].set_title(f"{NAMES[method]}: noise-free closed loop")
    axes[0].legend(fontsize=8, loc="upper left")
    (cx, cy), r = scene.obstacle.center, scene.obstacle.radius
    h = ((mc[:, :, 0] - cx) ** 2 + (mc[:, :, 1] - cy) ** 2 - r**2).min(axis=1)
    for path, bad in zip(mc, h < 0, strict=True):
        axes[1].plot(path[:, 0], path[:, 1], color="tab:red" if bad else COLORS[method],
                     lw=0.4, alpha=0.25)
    axes[1].plot(nominal[:, 0], nominal[:, 1], "k", lw=1)
    axes[1].set_title(f"{len(mc)} Monte Carlo rollouts (seed 0), unsafe in red: "
                      f"{int((h < 0).sum())}")
    return png_bytes(fig, dpi=110)


def histogram_figure(rows: pd.DataFrame, column: str, xlabel: str, line: float) -> bytes:
    methods = [m for m in NAMES if m in set(rows["method"])]
    fig, axes = plt.subplots(1, len(methods), figsize=(4 * len(methods), 3.2), squeeze=False)
    for ax, m in zip(axes[0], methods, strict=True):
        ax.hist(rows.loc[rows["method"] == m, column].to_numpy(), bins=60, color=COLORS[m],
                alpha=0.85)
        ax.axvline(line, color="k", lw=1, ls="--")
        ax.set_title(NAMES[m])
        ax.set_xlabel(xlabel)
        ax.set_ylabel("rollouts (count)")
    return png_bytes(fig, dpi=110)


def _errorbar(ax, x, rates, **kw) -> None:
    y = np.array([100 * r.value for r in rates])
    err = np.array([[100 * (r.value - r.low) for r in rates],
                    [100 * (r.high - r.value) for r in rates]])
    ax.errorbar(x, y, yerr=err, marker="o", capsize=3, **kw)


def _points(s: TrackingSummary, parameter: str) -> list:
    pts = [p for p in s.sweep if p.parameter == parameter]
    return pts if isinstance(pts[0].value, str) else sorted(pts, key=lambda p: p.value)


def sweep_figure(s: TrackingSummary) -> bytes:
    params = list(dict.fromkeys(p.parameter for p in s.sweep))
    fig, axes = plt.subplots(2, len(params), figsize=(4.2 * len(params), 6), squeeze=False)
    for j, name in enumerate(params):
        pts = _points(s, name)
        for i, metric in enumerate(("unsafe", "failure")):
            ax = axes[i][j]
            for m in NAMES:
                outs = [p.get(m) for p in pts]
                if any(o is None for o in outs):
                    continue
                _errorbar(ax, np.arange(len(pts)), [getattr(o, metric) for o in outs],
                          color=COLORS[m], label=NAMES[m])
            ax.set_xticks(np.arange(len(pts)), [_fmt(p.value) for p in pts])
            ax.set_xlabel(AXIS_NAMES.get(name, PARAM_NAMES.get(name, name)))
            ax.set_ylabel(f"{metric} rate [%]")
            ax.set_ylim(-3, 103)
    axes[0][0].legend(fontsize=8)
    return png_bytes(fig, dpi=110)


def radius_figure(s: TrackingSummary) -> bytes:
    """Failure against the assumed success radius, beside unsafe/failure against the noise
    level."""
    noise = [p for p in s.sweep if p.parameter == "noise_std"]
    fig, axes = plt.subplots(1, 2 if noise else 1, figsize=(11 if noise else 5.5, 3.8),
                             squeeze=False)
    ax = axes[0][0]
    for (source, m), style in [((src, m), "-" if src == "main" else "--")
                               for src, m in dict.fromkeys((p.source, p.method)
                                                           for p in s.radius)]:
        pts = [p for p in s.radius if (p.source, p.method) == (source, m)]
        label = NAMES[m] + ("" if source == "main" else ", noise after the filter")
        _errorbar(ax, [p.radius for p in pts], [p.failure for p in pts], color=COLORS[m],
                  ls=style, label=label)
    ax.axvline(s.config["target_radius"], color="k", lw=1, ls=":")
    ax.set_xlabel("success radius around the target [m] (assumed)")
    ax.set_ylabel("failure rate [%]")
    ax.set_ylim(-3, 103)
    ax.legend(fontsize=7)
    if noise:
        ax = axes[0][1]
        pts = sorted(noise, key=lambda p: p.value)
        for m in NAMES:
            outs = [p.get(m) for p in pts]
            if any(o is None for o in outs):
                continue
            x = [p.value for p in pts]
            _errorbar(ax, x, [o.failure for o in outs], color=COLORS[m], label=f"{NAMES[m]} "
                      "failure")
            _errorbar(ax, x, [o.unsafe for o in outs], color=COLORS[m], ls="--", mfc="none",
                      label=f"{NAMES[m]} unsafe")
        ax.set_xlabel(AXIS_NAMES["noise_std"])
        ax.set_ylabel("rate [%]")
        ax.set_ylim(-3, 103)
        ax.legend(fontsize=7)
    return png_bytes(fig, dpi=110)


def _paper_cell(m: str, metric: str) -> str:
    p = PAPER_BY_METHOD.get(m)
    return f"{100 * p.value:g}%" if p and p.metric == metric else "not given"


def _comparison(s: TrackingSummary) -> list[str]:
    rows = []
    for o in s.methods:
        p = PAPER_BY_METHOD[o.method]
        ours = getattr(o, p.metric)
        rows.append([NAMES[o.method], fmt_rate(o.unsafe), _paper_cell(o.method, "unsafe"),
                     fmt_rate(o.failure), _paper_cell(o.method, "failure"),
                     f"{p.metric} {100 * p.band[0]:g}-{100 * p.band[1]:g}%",
                     "yes" if p.band[0] <= ours.value <= p.band[1] else "NO"])
    return md_table(["method", "unsafe % [95% CI]", "paper unsafe", "failure % [95% CI]",
                     "paper failure", "band (assumptions §14.4)", "in band"], rows)


def _sensitivity(s: TrackingSummary) -> list[str]:
    lines = []
    for o in s.methods:
        for metric in ("unsafe", "failure"):
            d = drivers(s, o.method, metric)
            if d:
                lines.append(f"- {NAMES[o.method]}, {metric}: " + "; ".join(
                    f"{PARAM_NAMES[p]} ({t})" for p, _, t in d))
    return lines


def _details(s: TrackingSummary) -> list[str]:
    def row(o: Outcome):
        return [NAMES[o.method], o.n, o.unsafe.k, o.not_reached.k, o.n_unsafe_and_not_reached,
                f"{o.final_distance.mean:.3f} / {o.final_distance.median:.3f}",
                f"{o.min_h.min:.3f}, {o.min_h_p05:.3f}, {o.min_h.median:.3f}",
                f"{o.infeasible_qp_steps} ({o.rollouts_with_infeasible_qp})",
                o.unsafe_with_infeasible_qp, f"{o.qp_steps} ({o.fallback_steps})"]

    def spread(p):
        return f"{100 * p.mean:.1f} ± {100 * p.std:.1f}% [{100 * p.min:.1f}, {100 * p.max:.1f}]"

    lines = md_table(["method", "n", "unsafe", "not at target", "unsafe and not at target",
                      "mean / median final distance [m]", "min h: min, 5%, median [m²]",
                      "infeasible QP steps (rollouts)", "unsafe with an infeasible QP step",
                      "QP solves (fallbacks)"], [row(o) for o in s.methods])
    lines += ["", "Per-seed spread (rate over each seed's rollouts):", "",
              *md_table(["method", "unsafe: mean ± std [min, max]",
                         "failure: mean ± std [min, max]"],
                        [[NAMES[o.method], spread(o.per_seed_unsafe), spread(o.per_seed_failure)]
                         for o in s.methods]), "", "Nominal (noise-free) closed loops:", ""]
    for n in s.nominal:
        i = n.info
        extra = (f", {i['outer_iterations']} outer iterations, max violation "
                 f"{i['max_violation']:.1e} m²" if n.method == "al" else
                 f", ECBF initial condition met: {i['ecbf_initial_condition_ok']}, infeasible QP "
                 f"steps {i['closed_loop_infeasible_qp_steps']}" if n.method == "ecbf" else "")
        lines.append(f"- {NAMES[n.method]}: planner cost {i['cost']:.2f} (converged "
                     f"{i['converged']}, {i['iterations']} iLQG iterations{extra}); closed loop "
                     f"min h {i['closed_loop_min_h']:.2e} m², final distance "
                     f"{i['closed_loop_final_distance']:.3f} m")
    return lines


def _radius_table(s: TrackingSummary) -> list[str]:
    series = list(dict.fromkeys((p.source, p.method) for p in s.radius))
    radii = sorted({p.radius for p in s.radius})
    get = {(p.source, p.method, p.radius): p.failure for p in s.radius}
    head = ["success radius [m]"] + [NAMES[m] + ("" if src == "main" else " (noise after)")
                                      for src, m in series]
    return md_table(head, [[f"{r:g}"] + [fmt_rate(get[(src, m, r)]) for src, m in series]
                           for r in radii])


def _sweep_table(s: TrackingSummary) -> list[str]:
    methods = [o.method for o in s.methods]
    def order(p) -> str:
        r = Ranking.of(p.outcomes, "failure")
        return "-" if r is None else r.text() + (" (paper's)" if r.paper_order else "")

    rows = [[PARAM_NAMES.get(p.parameter, p.parameter), _fmt(p.value)] +
            [f"{100 * p.get(m).unsafe.value:.1f} / {100 * p.get(m).failure.value:.1f}"
             for m in methods] + [order(p)] for p in s.sweep]
    return md_table(["parameter", "value"] + [f"{NAMES[m]} unsafe / failure %" for m in methods]
                    + ["order by failure"], rows)


def _ours(s: TrackingSummary) -> list[str]:
    return md_table(["method", "unsafe % [95% CI]", "failure % [95% CI]"],
                    [[NAMES[o.method], fmt_rate(o.unsafe), fmt_rate(o.failure)]
                     for o in s.methods])


def _step_cost(store: RunStore) -> list[str]:
    """The online cost of one robot's control step per method (the nominal loop, zero noise):
    the affine feedback law (with BaS's barrier-state lift) or the feedback law and the
    ECBF-QP; empty for runs stored before step times were kept."""
    if not (store.root / "step_times.parquet").exists():
        return []
    steps = store.table("step_times")
    lines = tail_lines(steps, ["method"], label=lambda k: NAMES[k[0]])
    if lines:
        lines.insert(2, "One robot's control step online, on the nominal loop (no noise): the "
                        "feedback law u = ū + K (x − x̄) (BaS: with its barrier-state lift), "
                        "and for ECBF the filter's QP after it. The trajectory optimisation "
                        "runs once before the loop; its solve time is in the details above.")
        lines.insert(3, "")
    return lines


def write_report(s: TrackingSummary, store: RunStore, main: pd.DataFrame, scene: TrackingScene,
                 assumed: list[dict], run_line: str, provenance=None) -> Path:
    """Write the figures and report.md into the run directory. ``provenance`` (from
    :func:`studies.tracking_comparison.paper.comparison`): a custom run is labelled as such and
    its rates are not set beside the paper's."""
    with_paper = provenance is None or provenance.comparable
    out = store.root
    for m, tid in s.mc_paths.items():
        nominal = store.arrays(next(n.path_task for n in s.nominal if n.method == m))["path"]
        atomic_write_bytes(out / f"trajectories_{m}.png", trajectory_figure(
            scene, nominal, store.arrays(tid)["positions"], m))
    cfg = s.config
    atomic_write_bytes(out / "min_h_hist.png",
                       histogram_figure(main, "min_h", "min over k of h [m²]", 0.0))
    atomic_write_bytes(out / "final_distance_hist.png", histogram_figure(
        main, "final_distance", "final distance to the target [m]", cfg["target_radius"]))
    atomic_write_bytes(out / "radius.png", radius_figure(s))
    if s.sweep:
        atomic_write_bytes(out / "sweep.png", sweep_figure(s))
    claims = all_claims(s)
    lines = [
        "# Tracking comparison: ECBF-filtered iLQG, AL-iLQG, BaS-iLQG (paper Sec. III)", "",
        f"{cfg['n_seeds']} seeds x {cfg['n_rollouts']} Monte Carlo "
        f"rollouts per method, control noise std {cfg['base']['noise_std']:g}, limits ±15, one "
        "obstacle on the reference (assumptions §3.3, §6, §7, §12.1). Rates are pooled over seeds "
        f"with 95% Wilson intervals. {run_line}", "",
        *([] if provenance is None else provenance.banner(NOT_COMPARABLE)),
        *(["## Paper vs this run", "", *_comparison(s), ""] if with_paper else
          ["## This run's rates", "", *_ours(s), ""]),
        "Unsafe: min over steps k = 0..N of h(x_k) < 0. Failure: unsafe, or the final position "
        f"more than {cfg['target_radius']:g} m (assumed) from the target. The paper gives a "
        "failure rate for ECBF and unsafe rates for AL and BaS (assumptions §13 E7); both rates "
        "are shown for every method"
        + (" and each is compared with the paper's number of the same kind." if with_paper
           else "."),
        "", "## Findings", "",
        "Each sentence below is printed only if this run's numbers support it (conditions in "
        "`studies/tracking_comparison/findings.py`).", "",
        *supported(c for c in claims["ecbf"] + claims["al"] + claims["bas"] + claims["ranking"]
                   if with_paper or "paper's ≈" not in c.text), "",
        "## Success radius and noise level", "",
        "Failure rate against the assumed success radius (same rollouts), beside the rates "
        "against the control-noise level:", "", *_radius_table(s), "", "![radius](radius.png)",
        "", "## Details", "", *_details(s), "", *_step_cost(store),
        "![min h](min_h_hist.png)", "", "![final distance](final_distance_hist.png)", "",
        "## Trajectories (paper Figs. 1-3)", "",
        *[f"![{NAMES[m]}](trajectories_{m}.png)" for m in s.mc_paths], "",
        "## Sensitivity sweep over assumed values and the noise level", ""]
    if s.sweep:
        lines += [f"{cfg['sweep_seeds']} seed(s) x {cfg['sweep_rollouts']} rollouts per method and "
                  "point, one value changed at a time (others at base), the same noise draws "
                  "at every point.", "", *_sweep_table(s), "",
                  "Range of each rate over each swept parameter (largest first):", "",
                  *_sensitivity(s), "", "![sweep](sweep.png)"]
    else:
        lines.append("No sensitivity sweep in this run.")
    lines += ["", "## Assumed and sourced values used", "",
              *md_table(["quantity", "value", "source"],
                        [[a["name"], a["value"], a["source"]] for a in assumed]), "",
              "Data: `rollouts.parquet` / `rollouts.csv` (one row per rollout, every task), "
              "`summary.json` (this report's numbers), `tasks/*.npz` (per-task rows and paths), "
              "`manifest.json` (versions, revision, machine).", ""]
    path = out / "report.md"
    atomic_write_text(path, "\n".join(lines))
    return path


def summary(finished) -> Summary:
    """summary.json (the summary, the assumed values and the claims printed iff they hold) and
    one console line per method."""
    s = summarise(finished.config, finished.plan, finished.store, finished.ids)
    data = {**to_jsonable(s), "assumed": assumed_values(finished.config, Setup()),
            "claims": to_jsonable(all_claims(s))}
    lines = tuple(f"{NAMES[o.method]:20s} unsafe {fmt_rate(o.unsafe):22s} failure "
                  f"{fmt_rate(o.failure):22s} n={o.n}" for o in s.methods)
    return Summary(data, s, lines)


def report(finished, summary) -> Path:
    """The framework's report step: figures and report.md from a finished run."""
    s = summary.value
    main_ids = {finished.ids[t] for ts in finished.plan.main.values() for t in ts}
    table = finished.store.table("rollouts")
    return write_report(s, finished.store, table[table["task_id"].isin(main_ids)],
                        Setup().scene, summary.data["assumed"], finished.run_line,
                        comparison(finished.config, finished.out))

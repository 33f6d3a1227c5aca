"""Figures (matplotlib, Agg) as PNG bytes: Fig. 5 paths, Fig. 6 velocities, Fig. 4 samples,
safety vs variance, the alpha trade-off. Data come from the tidy tables, stored arrays and the
summary; no number is computed here that the report states."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from studies.navigation.summary import NavigationSummary
from studies.navigation.wording import NAMES
from workbench.study import png_bytes

COLORS = {"bas_mppi": "tab:blue", "sa_rmppi": "tab:red", "rmppi": "tab:orange",
          "mppi_crash": "tab:gray"}


def limits(circles: np.ndarray, points: list[np.ndarray], margin: float = 0.3
           ) -> tuple[tuple[float, float], tuple[float, float]]:
    """x and y limits [m] that hold every circle and every point (arrays (..., 2)), with a
    margin: nothing of the map or of a path is cut off."""
    c = np.asarray(circles, float).reshape(-1, 3)
    lo = [c[:, :2] - c[:, 2:]] if len(c) else []
    hi = [c[:, :2] + c[:, 2:]] if len(c) else []
    pts = [np.asarray(p, float).reshape(-1, 2) for p in points]
    pts = [p[np.all(np.isfinite(p), axis=1)] for p in pts]
    low = np.min(np.vstack(lo + pts), axis=0)
    high = np.max(np.vstack(hi + pts), axis=0)
    pad = margin + 0.02 * (high - low)
    return (low[0] - pad[0], high[0] + pad[0]), (low[1] - pad[1], high[1] + pad[1])


def draw_map(ax, circles: np.ndarray, start, goal, points: list[np.ndarray] = ()) -> None:
    """The obstacles, start (square) and goal (x); limits that hold the map, start, goal and
    ``points`` (the paths drawn on top); axes labelled in metres."""
    for cx, cy, r in circles:
        ax.add_patch(plt.Circle((cx, cy), r, color="0.7", zorder=0))
    ax.plot(*start, "s", color="tab:blue", ms=7, zorder=5)
    ax.plot(*goal, "x", color="tab:green", ms=9, mew=2.5, zorder=5)
    xlim, ylim = limits(circles, [np.asarray(start), np.asarray(goal), *points])
    ax.set_xlim(*xlim)
    ax.set_ylim(*ylim)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]", fontsize=8)
    ax.set_ylabel("y [m]", fontsize=8)
    ax.tick_params(labelsize=7)


def paths_figure(panels: list[tuple[str, float, list[np.ndarray], list[bool]]],
                 circles: np.ndarray, start, goal) -> bytes:
    """Fig. 5: one panel per (controller, variance), every realisation's path, crashes x."""
    ctrls = list(dict.fromkeys(p[0] for p in panels))
    vs = list(dict.fromkeys(p[1] for p in panels))
    fig, axes = plt.subplots(len(ctrls), len(vs), figsize=(3.4 * len(vs), 3.4 * len(ctrls)),
                             squeeze=False)
    every = [P for p in panels for P in p[2]]  # one scale for every panel
    for c, v, paths, crashed in panels:
        ax = axes[ctrls.index(c)][vs.index(v)]
        draw_map(ax, circles, start, goal, every)
        for P, bad in zip(paths, crashed, strict=True):
            ax.plot(P[:, 0], P[:, 1], color=COLORS[c], lw=0.6, alpha=0.5)
            if bad:
                ax.plot(P[-1, 0], P[-1, 1], "x", color="k", ms=5, mew=1.5, zorder=6)
        ax.set_title(f"{NAMES[c]}, var {v:g}: {sum(crashed)}/{len(paths)} crashed", fontsize=8)
    return png_bytes(fig)


def velocity_figure(vel: pd.DataFrame, variances: list[float]) -> bytes:
    """Fig. 6: mean ± std across realisations (those still running) of vx and vy over time."""
    fig, axes = plt.subplots(len(variances), 2, figsize=(10, 3.0 * len(variances)),
                             squeeze=False)
    for i, v in enumerate(variances):
        for j, comp in enumerate(("vx", "vy")):
            ax = axes[i][j]
            for c in ("bas_mppi", "sa_rmppi"):
                g = vel[(vel["controller"] == c) & (vel["variance"] == v)]
                if g.empty:
                    continue
                st = g.groupby("time_s")[comp].agg(["mean", "std"]).fillna(0.0)
                t = st.index.to_numpy()
                ax.plot(t, st["mean"], color=COLORS[c], label=NAMES[c])
                ax.fill_between(t, st["mean"] - st["std"], st["mean"] + st["std"],
                                color=COLORS[c], alpha=0.25)
            ax.set_title(f"variance {v:g}: {comp}", fontsize=9)
            ax.set_xlabel("time [s]")
            ax.set_ylabel(f"{comp} [m/s]")
    axes[0][0].legend(fontsize=8)
    return png_bytes(fig)


def samples_figure(a: dict[str, np.ndarray], meta: dict, circles: np.ndarray, start,
                   goal) -> bytes:
    """Fig. 4: nominal (blue) and feedback (red) sample paths of one SAIS batch."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 5.2))
    shown = [a["path"], a["x_nom"], a["x_real"], *a["nominal_samples"], *a["feedback_samples"]]
    for k, ax in enumerate(axes):
        draw_map(ax, circles, start, goal, shown)
        for P in a["nominal_samples"]:
            ax.plot(P[:, 0], P[:, 1], color="tab:blue", lw=0.5, alpha=0.35)
        for P in a["feedback_samples"]:
            ax.plot(P[:, 0], P[:, 1], color="tab:red", lw=0.5, alpha=0.35)
        ax.plot(*a["path"].T, "--", color="tab:orange", lw=1.5, label="true path")
        ax.plot(*a["x_nom"], "o", color="tab:blue", ms=6, label="nominal state")
        ax.plot(*a["x_real"], "o", color="tab:red", ms=6, label="real state")
        if k == 1:
            c = (a["x_nom"] + a["x_real"]) / 2
            span = max(0.6, 2.5 * float(np.linalg.norm(a["x_nom"] - a["x_real"])))
            ax.set_xlim(c[0] - span, c[0] + span)
            ax.set_ylim(c[1] - span, c[1] + span)
            ax.set_gid("zoom")  # cut off on purpose: a zoom of the left panel
            ax.legend(fontsize=7, loc="upper left")
    axes[0].set_title(f"SAIS batch at step {meta['step']} (limits ±{meta['u_limit']:g}, "
                      f"velocity variance {meta['variance']:g})", fontsize=9)
    axes[1].set_title("zoom at the states: blue nominal, red feedback samples", fontsize=9)
    return png_bytes(fig)


def _errorbar(ax, x, cells, **kw) -> None:
    y = np.array([100 * c.safety for c in cells])
    err = np.array([[100 * (c.safety - c.ci_low) for c in cells],
                    [100 * (c.ci_high - c.safety) for c in cells]])
    ax.errorbar(x, y, yerr=err, capsize=3, **{"marker": "o", **kw})


def safety_figure(s: NavigationSummary, table_i: dict) -> bytes:
    """Safety vs variance, 95% intervals; controllers side by side at each variance; Table I
    dashed (``table_i``; empty: left out)."""
    vs = sorted({x.variance for x in s.cells if x.main} | set(table_i))
    pos = {v: i for i, v in enumerate(vs)}
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for k, c in enumerate(NAMES):
        cells = sorted((x for x in s.cells if x.main and x.controller == c),
                       key=lambda x: x.variance)
        if cells:
            _errorbar(ax, [pos[x.variance] + 0.08 * (k - 1.5) for x in cells], cells,
                      color=COLORS[c], label=NAMES[c])
    for c in ("sa_rmppi", "bas_mppi") if table_i else ():  # empty: a custom run
        ref = sorted(table_i)
        ax.plot([pos[v] for v in ref], [table_i[v][c][0] for v in ref], "--", marker="s",
                mfc="none", color=COLORS[c], alpha=0.7, label=f"{NAMES[c]} (Table I)")
    ax.set_xticks(range(len(vs)), [f"{v:g}" for v in vs])
    ax.set_xlabel("disturbance variance [m²/s⁴] (categorical axis)")
    ax.set_ylabel("safety [%] (95% Wilson)")
    ax.set_ylim(-3, 103)
    ax.legend(fontsize=7, loc="lower left")
    return png_bytes(fig)


def alpha_figure(s: NavigationSummary) -> bytes:
    """Safety (95% interval) against RMSE over safe runs, one marker per alpha rule."""
    vs = s.config["sweep_variances"]
    rules = list(dict.fromkeys(x.rule for x in s.cells if x.controller ==
                               s.config["sweep_controller"] and x.variance in vs))
    marks = "ovsD^P*X"
    fig, axes = plt.subplots(1, len(vs), figsize=(5.5 * len(vs), 4.2), squeeze=False)
    for ax, v in zip(axes[0], vs, strict=True):
        for x in (x for x in s.cells if x.controller == s.config["sweep_controller"]
                  and x.variance == v):
            i = rules.index(x.rule)
            _errorbar(ax, [x.rmse], [x], color=plt.cm.tab10(i + 2), marker=marks[i % 8],
                      label=f"{NAMES[x.controller]} {x.rule}")
        b = s.cell("bas_mppi", v)
        if b is not None:
            _errorbar(ax, [b.rmse], [b], color=COLORS["bas_mppi"], marker="s",
                      label=NAMES["bas_mppi"])
        ax.set_xlabel("RMSE over safe realisations [m]")
        ax.set_ylabel("safety [%] (95% Wilson)")
        ax.set_ylim(-3, 103)
        ax.set_title(f"alpha trade-off at variance {v:g}", fontsize=9)
        ax.legend(fontsize=7, loc="lower right")
    return png_bytes(fig)

"""Plotting helpers (matplotlib): a scene, closed-loop paths, a step's samples, and safety
against a swept parameter.

Every helper takes an optional ``ax`` (a new figure's axes when None, through
``matplotlib.pyplot``) and returns the axes it drew on. Planar plots label their axes in
metres and keep an equal aspect; rates are drawn in percent. Each helper widens the axes'
limits to all the data it drew (and keeps what was already there), so nothing is clipped;
helpers stack on the same axes (a scene, then paths, then samples). Artists carry a ``gid``
naming what they show ("obstacle", "start", "goal", "path", "crash", "sample", "sample-crashed",
"nominal", "nominal-crashed", "rate", "interval"), for tests and later styling. matplotlib is
imported on first use, so ``import workbench`` stays fast.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from workbench.problem.obstacles import Circle, scene_circles
from workbench.validation import as_array, fail, flag
from workbench.validation import real as real_number

CRASH = "red"  # crashed samples and crash markers
_PAD = 0.03  # share of the data's span added on each side


def _axes(ax):
    if ax is not None:
        return ax
    import matplotlib.pyplot as plt

    return plt.subplots()[1]


def _circle_array(obj) -> tuple[np.ndarray, Any, Any]:
    """(circles (n, 3), start, goal) of a scene-like object (see :func:`scene`)."""
    start = goal = None
    if obj is None:
        return np.zeros((0, 3)), None, None
    if hasattr(obj, "plant") and hasattr(obj, "scene"):  # a NavigationSetup
        obj = obj.scene
    if callable(getattr(obj, "obstacles", None)):  # NavigationScene, CircleScene
        start, goal = getattr(obj, "start", None), getattr(obj, "goal", None)
        obj = obj.obstacles()
    elif hasattr(obj, "scene_value") and hasattr(obj, "obstacles"):  # a Model
        obj = obj.scene_value if getattr(obj, "scene_capacity", 0) else obj.obstacles
    if isinstance(obj, Circle):
        obj = (obj,)
    try:  # numbers only: a flat scene vector or (n, 3) rows
        a = np.array(obj, dtype=float)
    except (TypeError, ValueError):
        a = None
    if a is not None and a.ndim == 1:
        v = as_array("scene", a, (None,))
        if v.size % 3:
            raise fail("scene", v, "a flat scene vector has 3 entries (x, y, radius) per slot")
        circles = list(scene_circles(v))  # inert slots (radius 0) left out
    else:
        circles = []
        for i, c in enumerate(obj):
            if isinstance(c, Circle):
                circles.append(c)
            else:
                xyr = as_array(f"scene[{i}]", c, (3,))
                circles.append(Circle((xyr[0], xyr[1]), xyr[2]))
    arr = np.array([(*c.center, c.radius) for c in circles], dtype=float).reshape(-1, 3)
    return arr, start, goal


def _fit(ax, x, y, fresh: bool, log_x: bool = False) -> None:
    """Widen the limits to the finite points (x, y) (all of them, with a small pad; the pad
    of a logarithmic x axis is a share of its decades); on fresh axes set them to exactly
    that."""
    x, y = np.asarray(x, float).ravel(), np.asarray(y, float).ravel()
    ok = np.isfinite(x) & np.isfinite(y) & ((x > 0) if log_x else True)
    if not ok.any():
        return
    x, y = x[ok], y[ok]
    for v, log, get, put in ((x, log_x, ax.get_xlim, ax.set_xlim),
                             (y, False, ax.get_ylim, ax.set_ylim)):
        v = np.log10(v) if log else v
        lo, hi = float(v.min()), float(v.max())
        pad = _PAD * (hi - lo) if hi > lo else max(0.5, 0.05 * abs(lo))
        lo, hi = lo - pad, hi + pad
        if log:
            lo, hi = 10.0**lo, 10.0**hi
        if not fresh:
            a, b = get()
            lo, hi = min(lo, a), max(hi, b)
        put(lo, hi)


def _planar(ax) -> None:
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal", adjustable="box")


def _fresh(ax) -> bool:
    return not ax.has_data()


def scene(ax=None, circles_or_scene=None, *, start=None, goal=None, bounds=None,
          color: str = "0.75"):
    """Draw obstacles as filled discs, with start (square) and goal (cross) markers.

    ``circles_or_scene``: circles (:class:`~workbench.problem.Circle` objects, (x, y, radius)
    triples or an (n, 3) array), a flat scene vector (unused slots, radius 0, are skipped), a
    scene (:class:`~workbench.scenarios.scenes.NavigationScene` or ``CircleScene``: its start
    and goal are drawn unless given), a navigation set-up (its scene) or a model (its scene).
    ``start``, ``goal``: positions (the first two entries of a state are taken). ``bounds``:
    (x_min, x_max, y_min, y_max) in metres that the view must include (the workspace)."""
    return _draw_scene(ax, circles_or_scene, start=start, goal=goal, bounds=bounds,
                       color=color)


def _draw_scene(ax, circles_or_scene, *, start=None, goal=None, bounds=None,
                color: str = "0.75"):
    ax = _axes(ax)
    fresh = _fresh(ax)
    from matplotlib.patches import Circle as Disc

    circles, s0, g0 = _circle_array(circles_or_scene)
    start = s0 if start is None else start
    goal = g0 if goal is None else goal
    xs, ys = [], []
    for cx, cy, r in circles:
        ax.add_patch(Disc((cx, cy), r, facecolor=color, edgecolor="0.45", lw=0.6, zorder=0,
                          gid="obstacle"))
        xs += [cx - r, cx + r]
        ys += [cy - r, cy + r]
    for name, p, marker, col in (("start", start, "s", "tab:blue"),
                                 ("goal", goal, "X", "tab:green")):
        if p is None:
            continue
        p = np.asarray(p, dtype=float).ravel()
        if p.size < 2 or not np.all(np.isfinite(p[:2])):
            raise fail(name, p, "need a finite position (x, y)")
        ax.plot([p[0]], [p[1]], marker, color=col, ms=8, zorder=5, gid=name, label=name)
        xs.append(p[0])
        ys.append(p[1])
    if bounds is not None:
        b = as_array("bounds", bounds, (4,))
        if b[0] >= b[1] or b[2] >= b[3]:
            raise fail("bounds", b, "need (x_min, x_max, y_min, y_max) with min < max")
        xs += [b[0], b[1]]
        ys += [b[2], b[3]]
    _fit(ax, xs, ys, fresh)
    _planar(ax)
    return ax


def _episodes(items) -> list[tuple[np.ndarray, bool, int | None]]:
    """(states, crashed, crash index) of an episode, an array or a sequence of them."""
    if hasattr(items, "X") or (isinstance(items, np.ndarray) and items.ndim == 2):
        items = [items]
    out = []
    for i, e in enumerate(items):
        if hasattr(e, "X"):
            X = np.asarray(e.X, dtype=float)
            crashed = bool(getattr(e, "crashed", False))
            k = getattr(e, "crash_step", None)
            out.append((X, crashed, (len(X) - 1) if crashed and k is None else k))
        else:
            X = np.asarray(e, dtype=float)
            if X.ndim != 2 or X.shape[1] < 2:
                raise fail(f"paths[{i}]", X.shape, "need an Episode or states (n, >= 2)")
            out.append((X, False, None))
    return out


def paths(ax=None, episodes_or_arrays=(), scene=None, *, position: tuple[int, int] = (0, 1),
          color: str = "tab:blue", label: str | None = None, alpha: float = 0.6,
          lw: float = 1.0):
    """Draw closed-loop paths: :class:`~workbench.sim.Episode` objects (their states ``X``) or
    state arrays (n, nx), one or a sequence; a crashed episode ends in a red cross at its crash
    state. ``scene``: drawn first with :func:`scene` when given. ``position``: the state
    indices of x and y; ``label``: legend entry (first path only)."""
    ax = _axes(ax)
    if scene is not None:
        _draw_scene(ax, scene)
    fresh = _fresh(ax)
    xs, ys = [], []
    i, j = position
    for n, (X, crashed, k) in enumerate(_episodes(episodes_or_arrays)):
        ax.plot(X[:, i], X[:, j], color=color, alpha=alpha, lw=lw, gid="path",
                label=label if n == 0 else None)
        xs.append(X[:, i])
        ys.append(X[:, j])
        if crashed:
            k = len(X) - 1 if k is None or k >= len(X) else k
            ax.plot([X[k, i]], [X[k, j]], "x", color=CRASH, ms=8, mew=2, zorder=6, gid="crash")
    if xs:
        _fit(ax, np.concatenate(xs), np.concatenate(ys), fresh)
    _planar(ax)
    return ax


def samples(ax=None, info_or_samples=None, scene=None, *, real: bool = True,
            nominal: bool = True, cmap: str = "viridis", dynamic_range: float = 1e6,
            colorbar: bool = True, lw: float = 0.8):
    """Draw a step's kept samples (:class:`~workbench.sampling.samples.SampleTrajectories`, or
    a step info carrying one as ``samples``): real samples as solid lines, nominal ones dashed,
    coloured by their update weight on a log scale (``cmap``; weights below the largest kept
    one / ``dynamic_range`` share the lowest colour), crashed samples in red underneath, the
    heaviest on top.
    ``scene``: obstacles to draw first (default: the step's own scene; ``()`` for none).
    ``colorbar``: add a colour bar of weight / largest kept weight."""
    rec = getattr(info_or_samples, "samples", info_or_samples)
    if rec is None or not hasattr(rec, "real"):
        raise fail("info_or_samples", type(info_or_samples).__name__,
                   "need a SampleTrajectories or a step info with samples: switch recording "
                   "on with ctrl.record_samples(k) before the step")
    flag("real", real)
    flag("nominal", nominal)
    dr = real_number("dynamic_range", dynamic_range, 1.0, strict=True)
    if rec.position is None:
        raise fail("samples.position", None, "the model has no planar position to draw")
    if len(rec.position) != 2:
        raise fail("samples.position", rec.position, "this plot draws a planar position (2 "
                   "state indices); the model's position has 3: project it yourself from "
                   "samples.real")
    ax = _axes(ax)
    sc = rec.scene if scene is None else scene
    if sc is not None and np.size(sc):
        _draw_scene(ax, sc)
    fresh = _fresh(ax)
    from matplotlib import colormaps
    from matplotlib.colors import LogNorm

    i, j = rec.position
    w = np.asarray(rec.weights, dtype=float)
    top = float(w.max()) if w.size and w.max() > 0 else 1.0
    norm = LogNorm(vmin=1.0 / dr, vmax=1.0, clip=True)
    colors = colormaps[cmap]
    xs, ys = [], []
    sets = []
    if real:
        sets.append((rec.real, rec.crashed, "-", "sample"))
    if nominal and rec.nominal is not None:
        sets.append((rec.nominal, rec.crashed_nominal, "--", "nominal"))
    for X, crashed, ls, gid in sets:
        crashed = np.asarray(crashed, dtype=bool)
        # crashed first (underneath), then the others by weight, the heaviest on top
        order = np.lexsort((w, ~crashed))
        for n in order:
            bad = bool(crashed[n])
            col = CRASH if bad else colors(norm(max(w[n] / top, 1.0 / dr)))
            ax.plot(X[n, :, i], X[n, :, j], ls, color=col, lw=lw, alpha=0.6 if bad else 0.9,
                    zorder=2, gid=f"{gid}-crashed" if bad else gid)
        xs.append(X[:, :, i])
        ys.append(X[:, :, j])
    if xs:
        _fit(ax, np.concatenate([a.ravel() for a in xs]),
             np.concatenate([a.ravel() for a in ys]), fresh)
    _planar(ax)
    if colorbar and sets:
        from matplotlib.cm import ScalarMappable

        sm = ScalarMappable(norm=norm, cmap=colors)
        ax.figure.colorbar(sm, ax=ax, label="weight / largest kept weight (crashed: red)")
    return ax


def safety_sweep(ax=None, values=(), rates=(), low=None, high=None, *,
                 label: str | None = None, xlabel: str = "swept parameter",
                 color: str | None = None, log_x: bool = False):
    """Safety rate (fractions in [0, 1], drawn in %) against a swept parameter ``values``, with
    the interval [``low``, ``high``] (e.g. Wilson 95 %) as a band. ``xlabel`` should carry the
    parameter's unit; ``label`` is the legend entry; ``log_x`` a logarithmic x axis."""
    x = as_array("values", values, (None,))
    r = as_array("rates", rates, (x.size,))
    band = []
    for name, v in (("low", low), ("high", high)):
        if v is not None:
            band.append(as_array(name, v, (x.size,)))
    if (low is None) != (high is None):
        raise fail("low" if low is None else "high", None, "give both interval ends or neither")
    for name, v in (("rates", r), *zip(("low", "high"), band, strict=False)):
        if np.any(v < 0) or np.any(v > 1):
            raise fail(name, v, "rates are fractions in [0, 1] (they are drawn in %)")
    if band and (np.any(band[0] > r) or np.any(band[1] < r)):
        raise fail("low", band[0], "need low <= rates <= high")
    flag("log_x", log_x)
    if log_x and np.any(x <= 0):
        raise fail("values", x, "a logarithmic x axis needs values > 0")
    ax = _axes(ax)
    fresh = _fresh(ax)
    order = np.argsort(x, kind="stable")
    (line,) = ax.plot(x[order], 100 * r[order], "o-", color=color, label=label, gid="rate")
    ys = [100 * r]
    if band:
        lo, hi = 100 * band[0], 100 * band[1]
        ax.fill_between(x[order], lo[order], hi[order], color=line.get_color(), alpha=0.2,
                        lw=0, gid="interval")
        ys += [lo, hi]
    if log_x:
        ax.set_xscale("log")
    _fit(ax, np.concatenate([x] * len(ys)), np.concatenate(ys), fresh, log_x=log_x)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("safety rate [%]")
    ax.grid(alpha=0.3)
    if label is not None:
        ax.legend()
    return ax


__all__ = ["CRASH", "paths", "safety_sweep", "samples", "scene"]

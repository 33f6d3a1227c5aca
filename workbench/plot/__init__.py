"""Plotting helpers (matplotlib) for any model: a scene with the model's constraints,
closed-loop paths, a step's samples, the model's body at chosen states, and safety against a
swept parameter.

**Projection.** The helpers that draw states (:func:`scene`, :func:`constraints`,
:func:`paths`, :func:`samples`) draw two or three of them, named by ``states`` (indices or the
model's state names, e.g. ``states=("q1", "q2")``). The default is the model's ``position``;
a model without one is refused until ``states`` names what to draw. Three states draw on 3-D
axes (mplot3d) with an equal-ish box. The axes are labelled "name [unit]" from the model's
``state_names`` and ``state_units`` (the bare name when the unit is unknown); data given
without a model are planar positions, "x [m]" and "y [m]". Two states that share a unit keep
an equal aspect. A projection that came from ``states`` or a model is remembered on the axes:
later helpers on the same axes use it unless given their own.

**Constraints.** A model's obstacles are drawn as shapes when the projection is its planar
position: discs, moving discs with a velocity arrow, half-planes, capsules, a signed-distance
grid's zero level set (:mod:`workbench.plot.obstacles`); spheres and the obstacles of 3-D
scenes are drawn through the level set below (their section in the plane drawn, or their
surfaces in 3-D). Every other margin of its h(x) is drawn as the zero level set
min_i h_i(x) = 0 in the projection (gid "constraint"; the unsafe side shaded lightly, gid
"unsafe"; in 3-D a surface coloured by the active margin), computed on a grid over the view
with the states not drawn fixed at a reference state: ``reference``, else the start (scene:
``start`` when it is a full state, or a set-up's ``x0``), the first state of the first path
(paths) or the step's start (samples). When h depends on states not drawn, their reference
values are written in a corner of the axes (gid "reference").

Every helper takes an optional ``ax`` (a new figure's axes when None, through
``matplotlib.pyplot``) and returns the axes it drew on. Each widens the axes' limits to all the
data it drew (and keeps what was already there), so helpers stack (a scene, then paths, then
samples); the level set covers the view at the time it is drawn. Rates are drawn in percent.
Artists carry a ``gid`` naming what they show ("obstacle", "moving-obstacle", "velocity",
"half-plane", "half-plane-boundary", "capsule", "grid-boundary", "grid-unsafe", "constraint",
"unsafe", "start", "goal", "path", "crash", "sample", "sample-crashed", "nominal",
"nominal-crashed", "body", "rate", "interval"). matplotlib is imported on first use, so
``import workbench`` stays fast.

A model without a position, drawn in the plane of two of its states::

    ax = plot.scene(None, arm, states=("q1", "q2"), bounds=(-3.2, 3.2, -3.2, 3.2))
    plot.paths(ax, episode)               # the same projection, remembered on ax
    plot.bodies(workspace_ax, episode, draw_arm, steps=5)
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from workbench.plot import obstacles as shapes
from workbench.problem.models import Model
from workbench.problem.obstacles import Circle, scene_circles
from workbench.problem.scene_kinds import Capsule, HalfSpace, MovingCircle, Sphere
from workbench.problem.sdf_grid import SignedDistanceGrid
from workbench.validation import as_array, fail, flag, integer
from workbench.validation import real as real_number

CRASH = "red"  # crashed samples and crash markers
CONSTRAINT = "0.3"  # the zero level set of h and its unsafe side
_PAD = 0.03  # share of the data's span added on each side
_PLANAR = ("x [m]", "y [m]", "z [m]")  # labels of data drawn without a model
_REMEMBERED = "_workbench_projection"  # the attribute of the axes holding their projection
_GRID = {2: 201, 3: 36}  # default grid points per axis of the level set
_MAX_GRID = {2: 2000, 3: 160}
_KINDS = (MovingCircle, HalfSpace, Capsule, Sphere)


@dataclass(frozen=True)
class _Projection:
    """Which states are drawn (2 or 3 indices), their axis labels, and whether the axes keep
    an equal aspect (the states share a unit)."""

    index: tuple[int, ...]
    labels: tuple[str, ...]
    equal: bool

    @property
    def dims(self) -> int:
        return len(self.index)


def _labels(model: Model, index: Sequence[int]) -> tuple[tuple[str, ...], bool]:
    """Axis labels "name [unit]" (the bare name without a unit) and whether the units agree."""
    units = model.state_units
    out, seen = [], set()
    for i in index:
        unit = units[i] if units is not None and i < len(units) else ""
        name = model.state_names[i] if i < len(model.state_names) else f"x{i}"
        out.append(f"{name} [{unit}]" if unit else name)
        seen.add(unit)
    return tuple(out), len(seen) == 1 and "" not in seen


def _projection(ax, states, model: Model | None, default: Sequence[int] | None = None,
                field: str = "states") -> _Projection:
    """The projection to draw: ``states`` (indices or the model's state names), else the
    one remembered on ``ax``, else the model's position (a model without one is refused),
    else ``default``, else (0, 1) with planar labels."""
    if states is None:
        known = getattr(ax, _REMEMBERED, None) if ax is not None else None
        if isinstance(known, _Projection):
            if model is None or max(known.index) >= model.nx:
                return known
            return _Projection(known.index, *_labels(model, known.index))
        if model is not None:
            if model.position is None:
                names = model.state_names
                raise fail(field, None, f"model {model.name!r} has no position to draw by "
                           f"default: name 2 or 3 of its states {names} (or their indices), "
                           f"e.g. {field}=({names[0]!r}, {names[min(1, len(names) - 1)]!r})")
            return _Projection(tuple(model.position), *_labels(model, model.position))
        index = tuple(int(i) for i in (default if default is not None else (0, 1)))
        return _Projection(index, _PLANAR[:len(index)], True)
    if isinstance(states, str) or not isinstance(states, tuple | list) or len(states) not in (
            2, 3):
        raise fail(field, states, "must be 2 or 3 states to draw: indices or state names")
    chosen: list[int] = []
    for s in states:
        if isinstance(s, str):
            if model is None:
                raise fail(field, states, "state names need the model: pass model=... (or "
                           "give state indices)")
            if s not in model.state_names:
                raise fail(field, states, f"{s!r} is not a state of model {model.name!r}; "
                           f"its states are {model.state_names}")
            chosen.append(model.state_names.index(s))
        elif isinstance(s, int | np.integer) and not isinstance(s, bool | np.bool_) and 0 <= s \
                and (model is None or s < model.nx):
            chosen.append(int(s))
        else:
            top = f" in [0, {model.nx - 1}]" if model is not None else " >= 0"
            raise fail(field, states, f"each entry must be a state name or an index{top}")
    if len(set(chosen)) != len(chosen):
        raise fail(field, states, "the states drawn must be distinct")
    if model is None:
        return _Projection(tuple(chosen), _PLANAR[:len(chosen)], True)
    return _Projection(tuple(chosen), *_labels(model, chosen))


def _model_of(obj) -> Model | None:
    """The model behind a scene-like object: a Model, or a navigation set-up's plant."""
    if isinstance(obj, Model):
        return obj
    plant = getattr(obj, "plant", None)
    return plant if isinstance(plant, Model) and hasattr(obj, "scene") else None


def _remember(ax, proj: _Projection) -> None:
    setattr(ax, _REMEMBERED, proj)


def _axes(ax, dims: int = 2):
    """``ax``, or new axes (3-D for ``dims`` 3); refuses axes of the wrong kind."""
    if ax is None:
        import matplotlib.pyplot as plt

        fig = plt.figure()
        return fig.add_subplot(projection="3d") if dims == 3 else fig.add_subplot()
    spatial = getattr(ax, "name", "") == "3d"
    if spatial != (dims == 3):
        raise fail("ax", f"{getattr(ax, 'name', type(ax).__name__)} axes",
                   f"drawing {dims} states needs "
                   + ("3-D axes (fig.add_subplot(projection='3d'))" if dims == 3 else
                      "planar axes") + ", or ax=None for new ones")
    return ax


def _scene_objects(obj, model: Model | None) -> tuple[list, Any, Any]:
    """(obstacles, start, goal) of a scene-like object (see :func:`scene`): circles, and the
    other kinds of a scene layout (unused slots left out)."""
    start = goal = None
    if obj is None:
        return [], None, None
    layout = model.scene_layout if model is not None else None
    if hasattr(obj, "plant") and hasattr(obj, "scene"):  # a NavigationSetup
        obj = obj.scene
    if callable(getattr(obj, "obstacles", None)):  # NavigationScene, CircleScene
        start, goal = getattr(obj, "start", None), getattr(obj, "goal", None)
        obj = obj.obstacles()
    elif hasattr(obj, "scene_value") and hasattr(obj, "obstacles"):  # a Model
        if obj.scene_layout is not None:
            return obj.scene_layout.objects(obj.scene_value), None, None
        obj = obj.scene_value if getattr(obj, "scene_capacity", 0) else obj.obstacles
    if isinstance(obj, Circle | SignedDistanceGrid) or isinstance(obj, _KINDS):
        obj = (obj,)
    if isinstance(obj, np.ndarray) and obj.ndim == 1 and layout is not None:
        return layout.objects(layout.vector(obj)), None, None
    try:  # numbers only: a flat scene vector or (n, 3) rows
        a = np.array(obj, dtype=float)
    except (TypeError, ValueError):
        a = None
    if a is not None and a.ndim == 1:
        v = as_array("scene", a, (None,))
        if v.size % 3:
            raise fail("scene", v, "a flat scene vector has 3 entries (x, y, radius) per slot")
        return list(scene_circles(v)), start, goal  # inert slots (radius 0) left out
    out: list = []
    for i, c in enumerate(obj):
        if isinstance(c, Circle | SignedDistanceGrid) or isinstance(c, _KINDS):
            out.append(c)
        else:
            xyr = as_array(f"scene[{i}]", c, (3,))
            out.append(Circle((xyr[0], xyr[1]), xyr[2]))
    return out, start, goal


def _limits(ax, dims: int) -> list[tuple[Any, Any]]:
    pairs = [(ax.get_xlim, ax.set_xlim), (ax.get_ylim, ax.set_ylim)]
    if dims == 3:
        pairs.append((ax.get_zlim, ax.set_zlim))
    return pairs


def _fit(ax, cols, fresh: bool, log_x: bool = False) -> None:
    """Widen the limits to the finite points (one array per axis: all of them, with a small
    pad; the pad of a logarithmic x axis is a share of its decades); on fresh axes set them to
    exactly that."""
    cols = [np.asarray(c, float).ravel() for c in cols]
    ok = np.logical_and.reduce([np.isfinite(c) for c in cols])
    if log_x:
        ok &= cols[0] > 0
    if not ok.any():
        return
    for n, (v, (get, put)) in enumerate(zip(cols, _limits(ax, len(cols)), strict=True)):
        log = log_x and n == 0
        v = np.log10(v[ok]) if log else v[ok]
        lo, hi = float(v.min()), float(v.max())
        pad = _PAD * (hi - lo) if hi > lo else max(0.5, 0.05 * abs(lo))
        lo, hi = lo - pad, hi + pad
        if log:
            lo, hi = 10.0**lo, 10.0**hi
        if not fresh:
            a, b = get()
            lo, hi = min(lo, a), max(hi, b)
        put(lo, hi)


def _frame(ax, proj: _Projection) -> None:
    """Axis labels of the projection; an equal aspect (3-D: an equal-ish box, no side below
    a quarter of the longest) when the states share a unit."""
    pad = {"labelpad": 8} if proj.dims == 3 else {}  # clear of the 3-D tick labels
    ax.set_xlabel(proj.labels[0], **pad)
    ax.set_ylabel(proj.labels[1], **pad)
    if proj.dims == 3:
        ax.set_zlabel(proj.labels[2])
        if proj.equal:
            spans = np.array([abs(b - a) for a, b in (g() for g, _ in _limits(ax, 3))])
            top = float(spans.max()) or 1.0
            ax.set_box_aspect(tuple(np.maximum(spans, top / 4) / top), zoom=0.88)
    elif proj.equal:
        ax.set_aspect("equal", adjustable="box")


def _fresh(ax) -> bool:
    return not ax.has_data()


def _point(name: str, p, proj: _Projection, model: Model | None) -> np.ndarray:
    """The drawn coordinates of a marker: a state (its projected entries) or the coordinates
    themselves."""
    a = np.asarray(p, dtype=float).ravel()
    if model is not None and a.size in (model.n_physical, model.nx):
        out = a[list(proj.index)] if max(proj.index) < a.size else a[:0]
    elif a.size == proj.dims:
        out = a
    elif model is None and a.size > max(proj.index):
        out = a[list(proj.index)]
    else:
        out = a[:0]
    if out.size != proj.dims:
        what = f"a state of model {model.name!r}" if model is not None else "a state"
        raise fail(name, a, f"need {what} or the {proj.dims} drawn coordinates")
    if not np.all(np.isfinite(out)):
        raise fail(name, a, "need finite coordinates")
    return out


def _plot(ax, pts: np.ndarray, *args, **kw):
    """``ax.plot`` of points (n, 2 or 3)."""
    return ax.plot(*(pts[:, d] for d in range(pts.shape[1])), *args, **kw)


def scene(ax=None, circles_or_scene=None, *, start=None, goal=None, bounds=None,
          color: str = "0.75", model: Model | None = None, states=None, reference=None,
          constraints: bool = True):
    """Draw obstacles and a model's constraints, with start (square) and goal (cross) markers.

    ``circles_or_scene``: circles (:class:`~workbench.problem.Circle` objects, (x, y, radius)
    triples or an (n, 3) array), obstacles of any planar kind (half-planes, capsules, moving
    circles, a signed-distance grid), a flat scene vector (of the model's scene layout, or of
    circle slots; unused slots are skipped), a
    scene (:class:`~workbench.scenarios.scenes.NavigationScene` or ``CircleScene``: its start
    and goal are drawn unless given), a navigation set-up (its scene and plant) or a model
    (its scene, and its constraints). ``model``: the model whose names, units and h(x) are
    drawn (default: the model given as the scene). ``states``: the projection (see the module
    docstring). ``start``, ``goal``: states, or the drawn coordinates. ``bounds``: (min, max)
    per drawn state, (x_min, x_max, y_min, y_max[, z_min, z_max]), that the view must include.
    ``reference``: the state fixing the states not drawn in the level set (default: ``start``
    when it is a full state, else a set-up's start state ``x0``). ``constraints``: draw the
    level set of the model's margins."""
    model = model if model is not None else _model_of(circles_or_scene)
    proj = _projection(ax, states, model)
    ax = _axes(ax, proj.dims)
    if states is not None or model is not None:
        _remember(ax, proj)
    flag("constraints", constraints)
    _draw_scene(ax, proj, circles_or_scene, model=model, start=start, goal=goal,
                bounds=bounds, color=color, reference=reference, constraints=constraints)
    return ax


def _discs_drawable(proj: _Projection, model: Model | None) -> bool:
    """Circles are planar positions: drawable when the projection is the model's position."""
    if proj.dims != 2:
        return False
    return model is None or (model.position is not None
                             and tuple(model.position) == proj.index)


def _draw_scene(ax, proj: _Projection, circles_or_scene, *, model: Model | None = None,
                start=None, goal=None, bounds=None, color: str = "0.75", reference=None,
                constraints: bool = True, extra: np.ndarray | None = None,
                h_scene=None) -> None:
    """The scene, the markers, ``extra`` points (n, dims) the caller draws next fitted into
    the view, then the level set of the model's margins over it."""
    fresh = _fresh(ax)
    discs = _discs_drawable(proj, model)
    flat = isinstance(circles_or_scene, np.ndarray) and circles_or_scene.ndim == 1
    if (model is not None and flat and not model.scene_capacity
            and model.scene_layout is None):
        objs: list = []  # a scene vector that holds no circles
        s0 = g0 = None
    else:
        objs, s0, g0 = _scene_objects(circles_or_scene, model)
    spatial = model is not None and model.scene_layout is not None and \
        model.scene_layout.dim == 3
    if objs and (not discs or spatial):
        if model is None:
            raise fail("scene", objs, f"obstacles are planar positions; the projection draws "
                       f"{proj.dims} states: draw them on planar axes")
        objs = []  # drawn through the model's level set instead
    if model is None:
        shapes.check_planar("scene", objs)
    start = s0 if start is None else start
    goal = g0 if goal is None else goal
    pts: list[np.ndarray] = shapes.draw_bounded(ax, objs, color)
    marks = []
    for name, p, marker, col in (("start", start, "s", "tab:blue"),
                                 ("goal", goal, "X", "tab:green")):
        if p is None:
            continue
        q = _point(name, p, proj, model)
        marks.append((name, q, marker, col))
        pts.append(q[None, :])
    if bounds is not None:
        b = as_array("bounds", bounds, (2 * proj.dims,))
        if np.any(b[0::2] >= b[1::2]):
            names = ", ".join(f"{a}_min, {a}_max" for a in "xyz"[:proj.dims])
            raise fail("bounds", b, f"need ({names}) with min < max")
        pts.append(b.reshape(proj.dims, 2).T)
    if extra is not None and extra.size:
        pts.append(extra)
    if pts:
        allp = np.concatenate(pts)
        _fit(ax, [allp[:, d] for d in range(proj.dims)], fresh)
    _frame(ax, proj)
    shapes.draw_half_planes(ax, objs, color)
    if model is not None and constraints:
        ref = reference
        if ref is None and start is not None and np.size(start) in (model.n_physical,
                                                                     model.nx):
            ref = start
        if ref is None and isinstance(getattr(circles_or_scene, "x0", None), np.ndarray):
            ref = circles_or_scene.x0  # a navigation set-up's start state
        skip = 0
        if discs and not spatial:
            skip = (model.scene_layout.n_margins if model.scene_layout is not None
                    else model.scene_capacity or len(model.obstacles))
        _level_set(ax, proj, model, ref, h_scene, skip=skip)
    for name, q, marker, col in marks:  # on top of the level set
        _plot(ax, q[None, :], marker, color=col, ms=8, zorder=5, gid=name, label=name)


def _reference(model: Model, reference, drawn: Sequence[int],
               first: int) -> tuple[np.ndarray, list[int]]:
    """The physical reference state of the level set and the states not drawn that the
    margins from ``first`` on depend on (refused without a reference when there are some)."""
    n = model.n_physical
    h = model.h[first:]
    hidden = [i for i in range(n) if i not in drawn and ca.depends_on(h, model.x[i])]
    if reference is None:
        if hidden:
            names = tuple(model.state_names[i] for i in hidden)
            raise fail("reference", None, f"the margins of model {model.name!r} depend on "
                       f"{names}, which are not drawn: give a state ({n} or {model.nx} "
                       "entries) that fixes them")
        return np.zeros(n), hidden
    ref = np.asarray(reference, dtype=float).ravel()
    if ref.size not in (n, model.nx):
        raise fail("reference", ref, f"need a state of model {model.name!r}: {n} or "
                   f"{model.nx} entries")
    ref = as_array("reference", ref[:n], (n,))
    return ref, hidden


def _margins(model: Model, pts: np.ndarray, h_scene, first: int) -> np.ndarray:
    """The margins from ``first`` on at physical states ``pts`` (m, n_physical): (m, nh')."""
    sv = model.scene_vector(h_scene if h_scene is not None
                            and np.size(h_scene) == model.n_scene else None)
    f = model.margins_function.map(len(pts))
    return np.asarray(f(pts.T, sv), dtype=float).T.reshape(len(pts), -1)[:, first:]


def _grid_states(ref: np.ndarray, proj: _Projection, axes: list[np.ndarray]) -> np.ndarray:
    """Physical states (m, n) on the grid of ``axes`` (one array per drawn state, ij order),
    the other entries from ``ref``."""
    mesh = np.meshgrid(*axes, indexing="ij")
    pts = np.repeat(ref[None, :], mesh[0].size, axis=0)
    for i, g in zip(proj.index, mesh, strict=True):
        if i < pts.shape[1]:  # states past the physical ones do not enter h
            pts[:, i] = g.ravel()
    return pts


def _level_set(ax, proj: _Projection, model: Model, reference, h_scene, *, skip: int = 0,
               resolution: int | None = None, color: str = CONSTRAINT) -> None:
    """Draw min_i h_i = 0 (margins from ``skip`` on) over the view; see the module docstring."""
    if model.nh <= skip:
        return
    ref, hidden = _reference(model, reference, proj.index, skip)
    n = _GRID[proj.dims] if resolution is None else integer(
        "resolution", resolution, 8, _MAX_GRID[proj.dims])
    axes = [np.linspace(float(get()[0]), float(get()[1]), n) for get, _ in _limits(ax, proj.dims)]
    pts = _grid_states(ref, proj, axes)
    h = _margins(model, pts, h_scene, skip)
    H = np.min(h, axis=1).reshape((n,) * proj.dims)
    if proj.dims == 2:
        _contour(ax, axes, H, color)
    else:
        _surface(ax, proj, model, ref, h_scene, skip, axes, H)
    if hidden:
        units = model.state_units or ("",) * model.nx
        text = "h = 0 at " + ", ".join(
            f"{model.state_names[i]} = {ref[i]:.3g} {units[i]}".rstrip() for i in hidden)
        put = ax.text2D if proj.dims == 3 else ax.text
        put(0.01, 0.01, text, transform=ax.transAxes, fontsize=8, color="0.2", va="bottom",
            zorder=7, gid="reference", bbox={"fc": "white", "ec": "none", "alpha": 0.7})


def _contour(ax, axes: list[np.ndarray], H: np.ndarray, color: str) -> None:
    """The zero contour of H (ij grid) and its negative side, shaded; nothing where H has no
    sign change (all unsafe: all shaded)."""
    X, Y = np.meshgrid(*axes, indexing="ij")
    Hm = np.ma.masked_invalid(H)
    lo, hi = Hm.min(), Hm.max()
    if np.ma.is_masked(lo) or not lo < 0:
        return
    fill = ax.contourf(X, Y, Hm, levels=[float(lo), 0.0], colors=[color], alpha=0.18,
                       zorder=0.5)
    fill.set_gid("unsafe")
    if hi > 0:
        line = ax.contour(X, Y, Hm, levels=[0.0], colors=[color], linewidths=1.3,
                          zorder=1)
        line.set_gid("constraint")


# a cube's corners (ij offsets) and its split into six tetrahedra around the diagonal 0-6
_CUBE = np.array([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1),
                  (0, 1, 1)])
_TETS = np.array([(0, 1, 2, 6), (0, 2, 3, 6), (0, 3, 7, 6), (0, 7, 4, 6), (0, 4, 5, 6),
                  (0, 5, 1, 6)])


def _triangles(axes: list[np.ndarray], H: np.ndarray) -> np.ndarray:
    """Triangles (m, 3, 3) of the surface H = 0 on the ij grid ``axes`` (marching
    tetrahedra: linear interpolation along the edges where H changes sign)."""
    H = np.where(np.isnan(H), np.inf, H)
    shape = np.array(H.shape) - 1
    base = np.stack(np.meshgrid(*(np.arange(s) for s in shape), indexing="ij"), -1)
    corners = base.reshape(-1, 1, 3) + _CUBE[None]  # (cubes, 8, 3)
    vals = H[corners[..., 0], corners[..., 1], corners[..., 2]]
    neg = vals < 0
    mixed = neg.any(1) & ~neg.all(1)
    corners, vals = corners[mixed][:, _TETS].reshape(-1, 4, 3), vals[mixed][:, _TETS]
    vals = vals.reshape(-1, 4)
    inside = vals < 0
    k = inside.sum(1)
    keep = (k > 0) & (k < 4)
    corners, vals, inside, k = corners[keep], vals[keep], inside[keep], k[keep]
    order = np.argsort(~inside, axis=1, kind="stable")  # the inside corners first
    vals = np.take_along_axis(vals, order, 1)
    corners = np.take_along_axis(corners, order[..., None], 1)
    P = np.stack([axes[d][corners[..., d]] for d in range(3)], -1)  # (tets, 4, 3)

    def edge(rows, a, b):
        va, vb = vals[rows, a], vals[rows, b]
        t = (va / (va - vb))[:, None]
        return P[rows, a] + t * (P[rows, b] - P[rows, a])

    one, three, two = k == 1, k == 3, k == 2
    tris = [np.stack([edge(one, 0, 1), edge(one, 0, 2), edge(one, 0, 3)], 1),
            np.stack([edge(three, 3, 0), edge(three, 3, 1), edge(three, 3, 2)], 1)]
    q = [edge(two, 0, 2), edge(two, 0, 3), edge(two, 1, 3), edge(two, 1, 2)]
    tris += [np.stack([q[0], q[1], q[2]], 1), np.stack([q[0], q[2], q[3]], 1)]
    return np.concatenate(tris)


def _surface(ax, proj: _Projection, model: Model, ref: np.ndarray, h_scene, skip: int,
             axes: list[np.ndarray], H: np.ndarray) -> None:
    """The surface min_i h_i = 0 in 3-D: translucent triangles coloured by the margin that
    is smallest there, lit by their normals."""
    from matplotlib import colormaps
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # type: ignore[import-untyped]

    tris = _triangles(axes, H)
    if not len(tris):
        return
    centres = tris.mean(axis=1)
    states = np.repeat(ref[None, :], len(centres), axis=0)
    for d, i in enumerate(proj.index):
        if i < states.shape[1]:
            states[:, i] = centres[:, d]
    active = np.argmin(_margins(model, states, h_scene, skip), axis=1)
    spans = np.array([a[-1] - a[0] for a in axes])
    scaled = tris / np.where(spans > 0, spans, 1.0)  # normals in the box's proportions
    normal = np.cross(scaled[:, 1] - scaled[:, 0], scaled[:, 2] - scaled[:, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    light = np.abs(normal @ (np.array([0.3, -0.4, 0.87]) / np.linalg.norm([0.3, -0.4, 0.87])))
    base = np.array(colormaps["tab10"](active % 10))[:, :3]
    rgba = np.c_[base * (0.55 + 0.45 * light[:, None]), np.full(len(tris), 0.35)]
    ax.add_collection3d(Poly3DCollection(tris, facecolors=rgba, edgecolors="none",
                                         gid="constraint", zorder=0))


def constraints(ax=None, model: Model | None = None, *, states=None, reference=None,
                scene=None, bounds=None, resolution: int | None = None,
                color: str = CONSTRAINT):
    """Draw the zero level set min_i h_i(x) = 0 of every margin of ``model`` in the
    projection (see the module docstring), over the current view widened to ``bounds``
    ((min, max) per drawn state), on a grid of ``resolution`` points per drawn state (default
    201 in 2-D, 36 in 3-D). ``reference``: the state fixing the states not drawn; needed when
    the margins depend on them. ``scene``: the scene input of h (default: the model's)."""
    if not isinstance(model, Model):
        raise fail("model", type(model).__name__, "need a Model whose margins h(x) to draw")
    proj = _projection(ax, states, model)
    ax = _axes(ax, proj.dims)
    _remember(ax, proj)
    if bounds is None and _fresh(ax):
        raise fail("bounds", None, "the axes show nothing yet: give (min, max) per drawn "
                   "state for the grid, or draw data first")
    h_scene = None if scene is None else model.scene_vector(scene)
    _draw_scene(ax, proj, None, model=model, bounds=bounds, constraints=False)
    _level_set(ax, proj, model, reference, h_scene, resolution=resolution, color=color)
    return ax


def _episodes(items, proj: _Projection) -> list[tuple[np.ndarray, bool, int | None]]:
    """(states, crashed, crash index) of an episode, an array or a sequence of them."""
    if hasattr(items, "X") or (isinstance(items, np.ndarray) and items.ndim == 2):
        items = [items]
    out = []
    for i, e in enumerate(items):
        X = np.asarray(e.X if hasattr(e, "X") else e, dtype=float)
        if X.ndim != 2 or X.shape[1] <= max(proj.index):
            raise fail(f"paths[{i}]", X.shape, f"need an Episode or states (n, nx) with the "
                       f"drawn states {proj.index}")
        if hasattr(e, "X"):
            crashed = bool(getattr(e, "crashed", False))
            k = getattr(e, "crash_step", None)
            out.append((X, crashed, (len(X) - 1) if crashed and k is None else k))
        else:
            out.append((X, False, None))
    return out


def paths(ax=None, episodes_or_arrays=(), scene=None, *, states=None,
          model: Model | None = None, reference=None, color: str = "tab:blue",
          label: str | None = None, alpha: float = 0.6, lw: float = 1.0, position=None):
    """Draw closed-loop paths: :class:`~workbench.sim.Episode` objects (their states ``X``) or
    state arrays (n, nx), one or a sequence; a crashed episode ends in a red cross at its crash
    state. ``scene``: drawn first with :func:`scene` when given (a model there is also
    ``model``), its level set over the view including the paths, with the first path's first
    state as the default ``reference``. ``states``: the projection (``position`` is its older
    name); ``model``: names and units for it. ``label``: legend entry (first path only)."""
    if position is not None:
        if states is not None:
            raise fail("position", position, "give states or position (its older name), "
                       "not both")
        states = position
    model = model if model is not None else _model_of(scene)
    proj = _projection(ax, states, model)
    ax = _axes(ax, proj.dims)
    if states is not None or model is not None:
        _remember(ax, proj)
    runs = _episodes(episodes_or_arrays, proj)
    cols = list(proj.index)
    pts = (np.concatenate([X[:, cols] for X, _, _ in runs]) if runs
           else np.zeros((0, proj.dims)))
    if scene is not None:
        ref = reference if reference is not None or not runs else runs[0][0][0]
        _draw_scene(ax, proj, scene, model=model, reference=ref, extra=pts)
    elif len(pts):
        _fit(ax, [pts[:, d] for d in range(proj.dims)], _fresh(ax))
    for n, (X, crashed, k) in enumerate(runs):
        _plot(ax, X[:, cols], color=color, alpha=alpha, lw=lw, gid="path",
              label=label if n == 0 else None)
        if crashed:
            k = len(X) - 1 if k is None or k >= len(X) else k
            _plot(ax, X[k:k + 1, cols], "x", color=CRASH, ms=8, mew=2, zorder=6, gid="crash")
    _frame(ax, proj)
    return ax


def samples(ax=None, info_or_samples=None, scene=None, *, states=None,
            model: Model | None = None, reference=None, real: bool = True,
            nominal: bool = True, cmap: str = "viridis", dynamic_range: float = 1e6,
            colorbar: bool = True, lw: float = 0.8):
    """Draw a step's kept samples (:class:`~workbench.sampling.samples.SampleTrajectories`, or
    a step info carrying one as ``samples``): real samples as solid lines, nominal ones dashed,
    coloured by their update weight on a log scale (``cmap``; weights below the largest kept
    one / ``dynamic_range`` share the lowest colour), crashed samples in red underneath, the
    heaviest on top.
    ``states``: the projection (default: the samples' position); ``model``: names, units and
    the constraints drawn with the scene (its level set with the step's start as the default
    ``reference``). ``scene``: obstacles to draw first (default: the step's own scene; ``()``
    for none). ``colorbar``: add a colour bar of weight / largest kept weight."""
    rec = getattr(info_or_samples, "samples", info_or_samples)
    if rec is None or not hasattr(rec, "real"):
        raise fail("info_or_samples", type(info_or_samples).__name__,
                   "need a SampleTrajectories or a step info with samples: switch recording "
                   "on with ctrl.record_samples(k) before the step")
    flag("real", real)
    flag("nominal", nominal)
    dr = real_number("dynamic_range", dynamic_range, 1.0, strict=True)
    model = model if model is not None else _model_of(scene)
    if states is None and model is None and rec.position is None and not isinstance(
            getattr(ax, _REMEMBERED, None), _Projection):
        raise fail("states", None, "the samples' model has no position to draw by default: "
                   "name 2 or 3 states to draw (indices, or names with model=...)")
    proj = _projection(ax, states, model, default=rec.position)
    if max(proj.index) >= rec.real.shape[2]:
        raise fail("states", states if states is not None else proj.index,
                   f"the samples have {rec.real.shape[2]} states")
    ax = _axes(ax, proj.dims)
    if states is not None or model is not None:
        _remember(ax, proj)
    sets = []
    if real:
        sets.append((rec.real, rec.crashed, "-", "sample"))
    if nominal and rec.nominal is not None:
        sets.append((rec.nominal, rec.crashed_nominal, "--", "nominal"))
    cols = list(proj.index)
    pts = (np.concatenate([X[:, :, cols].reshape(-1, proj.dims) for X, *_ in sets]) if sets
           else np.zeros((0, proj.dims)))
    sc = rec.scene if scene is None else scene
    if (sc is not None and np.size(sc)) or (model is not None and scene is None):
        ref = rec.real[0, 0] if reference is None else reference
        _draw_scene(ax, proj, sc if sc is not None and np.size(sc) else None, model=model,
                    reference=ref, extra=pts, h_scene=rec.scene)
    elif len(pts):
        _fit(ax, [pts[:, d] for d in range(proj.dims)], _fresh(ax))
    from matplotlib import colormaps
    from matplotlib.colors import LogNorm

    w = np.asarray(rec.weights, dtype=float)
    top = float(w.max()) if w.size and w.max() > 0 else 1.0
    norm = LogNorm(vmin=1.0 / dr, vmax=1.0, clip=True)
    colors = colormaps[cmap]
    for X, crashed, ls, gid in sets:
        crashed = np.asarray(crashed, dtype=bool)
        # crashed first (underneath), then the others by weight, the heaviest on top
        order = np.lexsort((w, ~crashed))
        for n in order:
            bad = bool(crashed[n])
            col = CRASH if bad else colors(norm(max(w[n] / top, 1.0 / dr)))
            _plot(ax, X[n][:, cols], ls, color=col, lw=lw, alpha=0.6 if bad else 0.9,
                  zorder=2, gid=f"{gid}-crashed" if bad else gid)
    _frame(ax, proj)
    if colorbar and sets:
        from matplotlib.cm import ScalarMappable

        sm = ScalarMappable(norm=norm, cmap=colors)
        room = {"shrink": 0.7, "pad": 0.12} if proj.dims == 3 else {}  # clear of the z label
        ax.figure.colorbar(sm, ax=ax, label="weight / largest kept weight (crashed: red)",
                           **room)
    return ax


def _artists(value, field: str) -> list:
    """The matplotlib artists a body hook returned (one, or nested lists of them)."""
    from matplotlib.artist import Artist

    if isinstance(value, Artist):
        return [value]
    if isinstance(value, list | tuple):
        return [a for v in value for a in _artists(v, field)]
    raise fail(field, type(value).__name__, "must return the matplotlib artists it drew "
               "(an artist or a list of them, e.g. what ax.plot returns)")


def _artist_points(artist) -> np.ndarray | None:
    """Data coordinates of a line or a patch (None for other artists)."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    if hasattr(artist, "get_data_3d"):
        return np.column_stack(artist.get_data_3d()).astype(float)
    if isinstance(artist, Line2D):
        return np.asarray(artist.get_xydata(), dtype=float)
    if isinstance(artist, Patch):
        return np.asarray(artist.get_path().transformed(artist.get_patch_transform()).vertices,
                          dtype=float)
    return None


def bodies(ax=None, episode_or_states=None, draw: Callable[..., Any] | None = None, *,
           steps: int | Sequence[int] = 5, fade: bool = True):
    """Draw a model's body at chosen states with the user's hook ``draw(ax, x)``, which draws
    the body at the state ``x`` on ``ax`` (in any coordinates: a workspace, the projection)
    and returns its artists; they get the gid "body". ``episode_or_states``: an Episode, states
    (n, nx) or one state (nx,). ``steps``: how many states, evenly spaced from the first to the
    last, or their indices. ``fade``: earlier states drawn fainter (alpha from 0.3 to 1). The
    view widens to the lines and patches returned; planar axes keep an equal aspect; the
    axes' labels are left as they are."""
    if not callable(draw):
        raise fail("draw", type(draw).__name__, "must be a callable draw(ax, x) that draws the "
                   "body at the state x and returns its artists")
    flag("fade", fade)
    src = getattr(episode_or_states, "X", episode_or_states)
    X = np.asarray(src, dtype=float) if src is not None else np.zeros((0, 0))
    if X.ndim == 1 and X.size:
        X = X[None, :]
    if X.ndim != 2 or not len(X):
        raise fail("episode_or_states", getattr(X, "shape", X), "need an Episode, states "
                   "(n, nx) or one state (nx,)")
    n = len(X)
    if isinstance(steps, Sequence | np.ndarray) and not isinstance(steps, str):
        try:
            idx = np.array([integer("steps", s, -n, n - 1) for s in steps], dtype=int) % n
        except ValueError as exc:
            raise fail("steps", steps, f"must be a count >= 1 or state indices in [{-n}, "
                       f"{n - 1}]") from exc
        if not idx.size:
            raise fail("steps", steps, "name at least one state")
    else:
        count = integer("steps", steps, 1)
        idx = np.unique(np.round(np.linspace(0, n - 1, min(count, n))).astype(int))
    ax = _axes(ax, 3 if getattr(ax, "name", "") == "3d" else 2)
    fresh = _fresh(ax)
    pts = []
    for m, k in enumerate(idx):
        drawn = _artists(draw(ax, X[k].copy()), "draw")
        share = 0.3 + 0.7 * m / (len(idx) - 1) if fade and len(idx) > 1 else 1.0
        for a in drawn:
            a.set_gid("body")
            if fade:
                a.set_alpha(share * (a.get_alpha() if a.get_alpha() is not None else 1.0))
            p = _artist_points(a)
            if p is not None and p.size:
                pts.append(p)
    if pts:
        allp = np.concatenate([p[:, :2] if getattr(ax, "name", "") != "3d" else p
                               for p in pts])
        _fit(ax, [allp[:, d] for d in range(allp.shape[1])], fresh)
    if getattr(ax, "name", "") != "3d":
        ax.set_aspect("equal", adjustable="box")
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
    _fit(ax, [np.concatenate([x] * len(ys)), np.concatenate(ys)], fresh, log_x=log_x)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("safety rate [%]")
    ax.grid(alpha=0.3)
    if label is not None:
        ax.legend()
    return ax


__all__ = ["CONSTRAINT", "CRASH", "bodies", "constraints", "paths", "safety_sweep", "samples",
           "scene"]

"""Drawing a planar scene's obstacles, one shape per kind (assumptions §3.4).

Circles are discs (gid "obstacle"); moving circles are discs at their present centre (gid
"moving-obstacle") with an arrow to where the centre is one second later (gid "velocity",
none at rest); capsules are stadiums (gid "capsule"); a signed-distance grid is the zero level
set of its bilinear interpolation over its nodes (gid "grid-boundary") with the inside shaded
lightly (gid "grid-unsafe"); a half-plane is its unsafe side shaded over the view (gid
"half-plane") and its boundary line, clipped to the axes (gid "half-plane-boundary"). Spheres
and the half-spaces and capsules of 3-D scenes are not planar: a model's level set draws their
section (see :mod:`workbench.plot`).
"""

from __future__ import annotations

import numpy as np

from workbench.problem.obstacles import Circle
from workbench.problem.scene_kinds import Capsule, HalfSpace, MovingCircle, Sphere
from workbench.problem.sdf_grid import SignedDistanceGrid
from workbench.validation import fail

PLANAR_KINDS = (Circle, MovingCircle, HalfSpace, Capsule, SignedDistanceGrid)
_EDGE = {"edgecolor": "0.45", "lw": 0.6}
_ARC = 25  # points per end cap of a stadium (odd: its tip is one)


def check_planar(field: str, objects) -> None:
    """Refuse an obstacle that has no planar shape (3-D kinds)."""
    for i, obj in enumerate(objects):
        if isinstance(obj, Sphere) or (isinstance(obj, HalfSpace | Capsule)
                                       and len(obj.normal if isinstance(obj, HalfSpace)
                                               else obj.a) != 2):
            raise fail(f"{field}[{i}]", obj, "is a 3-D obstacle; draw its section in a plane "
                       "through its model's margins: pass model=... (a model built with this "
                       "scene) and the states to draw")


def draw_bounded(ax, objects, color: str) -> list[np.ndarray]:
    """Draw every obstacle but the half-planes; the points (n, 2) the view must hold: the
    shapes drawn, and the point of each half-plane's boundary nearest the middle of the
    shapes (of the origin without any)."""
    from matplotlib.patches import Circle as Disc
    from matplotlib.patches import FancyArrowPatch, Polygon

    pts: list[np.ndarray] = []
    for obj in objects:
        if isinstance(obj, Circle | MovingCircle):
            c, r = np.array(obj.center), obj.radius
            moving = isinstance(obj, MovingCircle)
            ax.add_patch(Disc(tuple(c), r, facecolor=color, zorder=0,
                              gid="moving-obstacle" if moving else "obstacle", **_EDGE))
            pts.append(np.array([c - r, c + r]))
            if isinstance(obj, MovingCircle) and any(obj.velocity):
                tip = c + np.array(obj.velocity)
                ax.add_patch(FancyArrowPatch(tuple(c), tuple(tip), arrowstyle="-|>",
                                             mutation_scale=10, shrinkA=0, shrinkB=0,
                                             color="0.3", lw=0.8, zorder=1,
                                             gid="velocity"))
                pts.append(tip[None, :])
        elif isinstance(obj, Capsule):
            outline = stadium(np.array(obj.a), np.array(obj.b), obj.radius)
            ax.add_patch(Polygon(outline, closed=True, facecolor=color, zorder=0, gid="capsule",
                                 **_EDGE))
            pts.append(outline)
        elif isinstance(obj, SignedDistanceGrid):
            pts.append(_grid(ax, obj, color))
    if pts:
        allp = np.concatenate(pts)
        mid = 0.5 * (allp.min(axis=0) + allp.max(axis=0))
    else:
        mid = np.zeros(2)
    for obj in objects:
        if isinstance(obj, HalfSpace):
            n = np.array(obj.normal)
            pts.append((mid - (n @ mid - obj.offset) * n)[None, :])
    return pts


def stadium(a: np.ndarray, b: np.ndarray, r: float) -> np.ndarray:
    """The outline (n, 2) of the points within r of the segment a-b."""
    ang = np.arctan2(*(b - a)[::-1])
    t = np.linspace(-np.pi / 2, np.pi / 2, _ARC)
    cap_b = b + r * np.column_stack([np.cos(ang + t), np.sin(ang + t)])
    cap_a = a + r * np.column_stack([np.cos(ang + np.pi + t), np.sin(ang + np.pi + t)])
    return np.vstack([cap_b, cap_a])


def _grid(ax, g: SignedDistanceGrid, color: str) -> np.ndarray:
    x0, x1, y0, y1 = g.extent()
    nx, ny = g.shape
    X, Y = np.meshgrid(np.linspace(x0, x1, nx), np.linspace(y0, y1, ny), indexing="ij")
    V = g.values
    lo, hi = float(V.min()), float(V.max())
    if lo < 0.0:
        shade = ax.contourf(X, Y, V, levels=[lo - 1.0, 0.0], colors=[color], alpha=0.5,
                            zorder=0)
        shade.set_gid("grid-unsafe")
    if lo < 0.0 < hi:
        line = ax.contour(X, Y, V, levels=[0.0], colors=["0.45"], linewidths=0.8, zorder=1)
        line.set_gid("grid-boundary")
    return np.array([[x0, y0], [x1, y1]])


def draw_half_planes(ax, objects, color: str) -> None:
    """Each half-plane's unsafe side n.p < b shaded over the current view, and its boundary
    line (clipped to the axes by matplotlib, however they change later)."""
    from matplotlib.patches import Polygon

    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    view = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    for obj in objects:
        if not isinstance(obj, HalfSpace):
            continue
        n, b = np.array(obj.normal), obj.offset
        unsafe = clip(view, -n, -b)
        if len(unsafe) >= 3:
            ax.add_patch(Polygon(unsafe, closed=True, facecolor=color, alpha=0.5, lw=0,
                                 zorder=0, gid="half-plane"))
        p0 = b * n  # the boundary's point nearest the origin
        ax.axline(tuple(p0), tuple(p0 + np.array([-n[1], n[0]])), color="0.45", lw=0.8,
                  zorder=1, gid="half-plane-boundary")


def clip(polygon: np.ndarray, n: np.ndarray, b: float) -> np.ndarray:
    """The part of a convex polygon (m, 2) where n.p >= b (one Sutherland-Hodgman pass)."""
    out = []
    s = polygon @ n - b
    for i in range(len(polygon)):
        j = (i + 1) % len(polygon)
        if s[i] >= 0:
            out.append(polygon[i])
        if (s[i] >= 0) != (s[j] >= 0):
            out.append(polygon[i] + s[i] / (s[i] - s[j]) * (polygon[j] - polygon[i]))
    return np.array(out).reshape(-1, 2)

"""The kinds of run-time obstacle a scene holds, one registry (assumptions §3.4).

Each kind is a fixed-width slot of numbers in the scene input: its margin h (h >= 0 is safe) as
a CasADi expression of a position and the slot, the same margin in plain NumPy (the twins'
oracle, vectorised over positions and slots), the unused (inert) slot, the check of a slot and
its translation (the float32 local frame). A :class:`~workbench.problem.scene_layout.SceneLayout`
lists how many slots of each kind a model holds; the scene vector is the kinds' blocks in
registration order (circles first, so a circle-only scene is the circle scene of before).

=============  =====  ====================================  =====================================
kind           dims   slot                                  margin (squared / signed_distance)
=============  =====  ====================================  =====================================
circles        2      x, y, r                               |p-c|^2 - r^2 / |p-c| - r
spheres        3      x, y, z, r                            |p-c|^2 - r^2 / |p-c| - r
halfspaces     2, 3   n (unit normal), b                    n.p - b (both forms)
capsules       2, 3   a, b (segment ends), r                d^2 - r^2 / d - r, d = dist(p, ab)
moving         2      x, y, r, vx, vy                       a circle at c + v t (t = 0: now)
grid           2      ox, oy, res, values (nx ny)           bilinear signed distance (both forms)
=============  =====  ====================================  =====================================

``inflation`` (a robot radius) is added to r, to b (half-spaces) and subtracted from the grid's
distance. Margins of moving circles at time t are those of circles at c + v t; t = 0 in the
model's own margins (the scene is the present), the controllers' rollouts shift them to each
step's time (:func:`predicted_scene`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import casadi as ca
import numpy as np

from workbench.problem.obstacles import Circle
from workbench.registry import Registry
from workbench.validation import as_array, fail, real

FAR = 1e8  # coordinate of unused slots: margins there are about 1e16 (squared) or 1e8
FORMS = ("squared", "signed_distance")


@dataclass(frozen=True)
class Sphere:
    """A ball obstacle in 3-D: centre (3,) in metres, radius > 0."""

    center: tuple[float, float, float]
    radius: float

    def __post_init__(self) -> None:
        c = as_array("Sphere.center", self.center, (3,))
        object.__setattr__(self, "center", tuple(float(v) for v in c))
        object.__setattr__(self, "radius", real("Sphere.radius", self.radius, 0.0, strict=True))


def _coordinates(field: str, value, what: str = "2 or 3 entries") -> np.ndarray:
    """A finite 2-D or 3-D vector, refused naming ``field`` otherwise."""
    v = as_array(field, value, (None,))
    if v.size not in (2, 3):
        raise fail(field, value, f"needs {what}")
    return v


@dataclass(frozen=True)
class HalfSpace:
    """The safe side n.p >= offset of a wall, floor or ceiling (2-D: a half-plane). ``normal``
    (2 or 3 entries, not zero) is scaled to unit length (and ``offset`` with it), so the margin
    n.p - offset is the signed distance to the boundary."""

    normal: tuple[float, ...]
    offset: float

    def __post_init__(self) -> None:
        n = _coordinates("HalfSpace.normal", self.normal, "2 (a half-plane) or 3 entries")
        norm = float(np.linalg.norm(n))
        if not norm > 0:
            raise fail("HalfSpace.normal", self.normal, "must not be zero")
        b = real("HalfSpace.offset", self.offset)
        object.__setattr__(self, "normal", tuple(float(v) for v in n / norm))
        object.__setattr__(self, "offset", b / norm)

    @classmethod
    def through(cls, point, normal) -> HalfSpace:
        """The half-space whose boundary passes through ``point``, safe side along ``normal``."""
        n = as_array("HalfSpace.normal", normal, (None,))
        p = as_array("HalfSpace.point", point, (n.size,))
        return cls(tuple(n), float(n @ p))


@dataclass(frozen=True)
class Capsule:
    """A segment a-b with a radius > 0 (a corridor wall, a pillar, a link), in 2-D or 3-D;
    a and b must differ (a zero-length capsule is a circle or sphere)."""

    a: tuple[float, ...]
    b: tuple[float, ...]
    radius: float

    def __post_init__(self) -> None:
        a = _coordinates("Capsule.a", self.a)
        b = as_array("Capsule.b", self.b, (a.size,))
        if not np.any(a != b):
            raise fail("Capsule.b", self.b, "must differ from Capsule.a (a capsule of length "
                       "0 is a circle or sphere: use that kind)")
        object.__setattr__(self, "a", tuple(float(v) for v in a))
        object.__setattr__(self, "b", tuple(float(v) for v in b))
        object.__setattr__(self, "radius", real("Capsule.radius", self.radius, 0.0, strict=True))


@dataclass(frozen=True)
class MovingCircle:
    """A disc moving at constant velocity (m/s) from its present centre; the controllers
    predict it over their horizon, the plant moves it as the scene of each step says."""

    center: tuple[float, float]
    radius: float
    velocity: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        c = as_array("MovingCircle.center", self.center, (2,))
        v = as_array("MovingCircle.velocity", self.velocity, (2,))
        object.__setattr__(self, "center", (float(c[0]), float(c[1])))
        object.__setattr__(self, "velocity", (float(v[0]), float(v[1])))
        object.__setattr__(self, "radius",
                           real("MovingCircle.radius", self.radius, 0.0, strict=True))


# ---------------------------------------------------------------------------------- margins


def _dist_form(d2, r, form: str, sqrt):
    return d2 - r * r if form == "squared" else sqrt(d2) - r


def _ball_sx(p, s, form, infl, d):
    d2 = sum((p[i] - s[i]) ** 2 for i in range(d))
    return _dist_form(d2, s[d] + infl if infl else s[d], form, ca.sqrt)


def _ball_np(P, S, form, infl, d):
    diff = P[:, None, :d] - S[None, :, :d]
    d2 = np.sum(diff * diff, axis=2)
    return _dist_form(d2, S[None, :, d] + infl, form, np.sqrt)


def _half_sx(p, s, form, infl, d):
    h = sum(s[i] * p[i] for i in range(d)) - s[d]
    return h - infl if infl else h


def _half_np(P, S, form, infl, d):
    return P[:, :d] @ S[:, :d].T - S[None, :, d] - infl


def _capsule_sx(p, s, form, infl, d):
    a, b = [s[i] for i in range(d)], [s[d + i] for i in range(d)]
    ab = [b[i] - a[i] for i in range(d)]
    ap = [p[i] - a[i] for i in range(d)]
    t = sum(ap[i] * ab[i] for i in range(d)) / sum(ab[i] * ab[i] for i in range(d))
    t = ca.fmin(ca.fmax(t, 0), 1)
    d2 = sum((ap[i] - t * ab[i]) ** 2 for i in range(d))
    r = s[2 * d]
    return _dist_form(d2, r + infl if infl else r, form, ca.sqrt)


def _capsule_np(P, S, form, infl, d):
    a, ab = S[None, :, :d], S[None, :, d:2 * d] - S[None, :, :d]
    ap = P[:, None, :d] - a
    t = np.clip(np.sum(ap * ab, axis=2) / np.sum(ab * ab, axis=2), 0.0, 1.0)
    diff = ap - t[..., None] * ab
    return _dist_form(np.sum(diff * diff, axis=2), S[None, :, 2 * d] + infl, form, np.sqrt)


# --------------------------------------------------------------------------- slot checking


def _ball_ok(S, d):
    r, c = S[:, d], S[:, :d]
    return (r > 0) | ((r == 0) & np.all(c == FAR, axis=1))


def _half_ok(S, d):
    n = S[:, :d]
    return np.abs(np.sqrt(np.sum(n * n, axis=1)) - 1.0) <= 1e-9


def _capsule_ok(S, d):
    a, b, r = S[:, :d], S[:, d:2 * d], S[:, 2 * d]
    unused = np.all(S[:, :2 * d] == np.array(_capsule_inert(d)[:2 * d]), axis=1)
    return ((r > 0) & np.any(a != b, axis=1)) | ((r == 0) & unused)


def _capsule_inert(d):
    # b - a = 16 along x: exact in float32 too (its spacing at 1e8 is 8), so the float32
    # kernels' projection onto the unused segment stays finite
    return (FAR,) * d + (FAR + 16.0,) + (FAR,) * (d - 1) + (0.0,)


def _moving_ok(S, d):
    return _ball_ok(S[:, :3], 2) & ((S[:, 2] > 0) | np.all(S[:, 3:] == 0, axis=1))


def _shift_points(S, o, cols):
    out = S.copy()
    for c0 in cols:
        out[:, c0:c0 + o.size] -= o
    return out


def _half_shift(S, o):
    out = S.copy()
    d = o.size
    out[:, d] -= S[:, :d] @ o
    return out


@dataclass(frozen=True)
class SceneKind:
    """One kind of scene slot. ``width(d)``: numbers per slot at position dimension d;
    ``sx(p, slot, form, inflation, d)``: its margin as a CasADi expression;
    ``numpy(P (N, d), S (m, width), form, inflation, d)``: the margins (N, m), written apart
    from ``sx``; ``inert(d)``: the unused slot; ``valid(S, d)``: which rows (m,) are a slot of
    this kind or unused; ``translate(S, o)``: the slots seen from origin o (positions minus
    o); ``objects``: the class(es) a user passes; ``to_row(obj)`` its slot."""

    name: str
    dims: tuple[int, ...]
    width: Callable[[int], int]
    sx: Callable
    numpy: Callable
    inert: Callable[[int], tuple[float, ...]]
    valid: Callable
    translate: Callable
    objects: tuple[type, ...]
    to_row: Callable
    rule: str  # what a valid slot is, for messages


SCENE_KINDS: Registry[SceneKind] = Registry("scene kind", SceneKind, "scene kind",
                                            "register_scene_kind(kind)", "SceneKind.name")


def _circle_row(c):
    return (*c.center, c.radius)


SCENE_KINDS.register(SceneKind(
    "circles", (2,), lambda d: 3, _ball_sx, _ball_np, lambda d: (FAR, FAR, 0.0), _ball_ok,
    lambda S, o: _shift_points(S, o, (0,)), (Circle,), _circle_row,
    "a circle (x, y, r) with r > 0, or unused: exactly (1e8, 1e8, 0)"))
SCENE_KINDS.register(SceneKind(
    "moving", (2,), lambda d: 5, lambda p, s, f, i, d: _ball_sx(p, s, f, i, 2),
    lambda P, S, f, i, d: _ball_np(P, S, f, i, 2), lambda d: (FAR, FAR, 0.0, 0.0, 0.0),
    _moving_ok, lambda S, o: _shift_points(S, o, (0,)), (MovingCircle,),
    lambda c: (*c.center, c.radius, *c.velocity),
    "a moving circle (x, y, r, vx, vy) with r > 0, or unused: exactly (1e8, 1e8, 0, 0, 0)"))
SCENE_KINDS.register(SceneKind(
    "halfspaces", (2, 3), lambda d: d + 1, _half_sx, _half_np,
    lambda d: (0.0,) * (d - 1) + (1.0, -FAR), _half_ok, _half_shift, (HalfSpace,),
    lambda h: (*h.normal, h.offset),
    "a half-space (n, b) with |n| = 1; unused: (0, .., 1, -1e8)"))
SCENE_KINDS.register(SceneKind(
    "capsules", (2, 3), lambda d: 2 * d + 1, _capsule_sx, _capsule_np, _capsule_inert,
    _capsule_ok, lambda S, o: _shift_points(S, o, (0, o.size)), (Capsule,),
    lambda c: (*c.a, *c.b, c.radius),
    "a capsule (a, b, r) with a != b and r > 0; unused: a = (1e8, ..), b = (1e8 + 16, 1e8, ..), "
    "r = 0"))
SCENE_KINDS.register(SceneKind(
    "spheres", (3,), lambda d: 4, _ball_sx, _ball_np, lambda d: (FAR, FAR, FAR, 0.0), _ball_ok,
    lambda S, o: _shift_points(S, o, (0,)), (Sphere,), _circle_row,
    "a sphere (x, y, z, r) with r > 0, or unused: exactly (1e8, 1e8, 1e8, 0)"))


def register_scene_kind(kind: SceneKind) -> SceneKind:
    """Add a user kind of scene slot (its blocks come after the built-in kinds')."""
    return SCENE_KINDS.register(kind)

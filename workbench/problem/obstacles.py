"""Circular obstacles and their safety margins h_i(p) (h >= 0 is safe), assumptions §3.1."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import casadi as ca
import numpy as np

from workbench.validation import as_array, fail, one_of, real

HForm = Literal["squared", "signed_distance"]
H_FORMS: tuple[str, ...] = ("squared", "signed_distance")


@dataclass(frozen=True)
class Circle:
    """A disc obstacle: centre (2,) in metres, radius > 0 in metres."""

    center: tuple[float, float]
    radius: float

    def __post_init__(self) -> None:
        c = as_array("Circle.center", self.center, (2,))
        object.__setattr__(self, "center", (float(c[0]), float(c[1])))
        object.__setattr__(self, "radius", real("Circle.radius", self.radius, 0.0, strict=True))


def circle_margins(
    p, circles: tuple[Circle, ...], h_form: HForm = "squared", inflation: float = 0.0
):
    """Margins h_i for a 2-vector position ``p`` (CasADi or NumPy), one per circle.

    squared: ||p - c||^2 - (r + inflation)^2 ; signed_distance: ||p - c|| - (r + inflation).
    """
    one_of("h_form", h_form, H_FORMS)
    real("inflation", inflation, 0.0)
    out = []
    for c in circles:
        r = c.radius + inflation
        d2 = (p[0] - c.center[0]) ** 2 + (p[1] - c.center[1]) ** 2
        out.append(d2 - r**2 if h_form == "squared" else ca.sqrt(d2) - r)
    if isinstance(p, ca.SX | ca.MX | ca.DM):
        return ca.vertcat(*out) if out else ca.SX(0, 1)
    return np.array([float(v) for v in out])


def circles_from_arrays(centers, radii) -> tuple[Circle, ...]:
    """Circles from an (n,2) array of centres and an (n,) array of radii."""
    c = as_array("centers", centers, (None, 2))
    r = as_array("radii", radii, (c.shape[0],))
    if np.any(r <= 0):
        raise fail("radii", r, "every radius must be > 0")
    return tuple(Circle(center=(float(a), float(b)), radius=float(rr))
                 for (a, b), rr in zip(c, r, strict=False))


# Run-time scenes: circles as kernel inputs (3 numbers per slot: centre x, centre y, radius).
# An unused slot is inert: exactly INERT_SLOT, centre (INERT_CENTER, INERT_CENTER), radius 0.
# Its margin is then about 2e16 (squared form) or 1.4e8 (signed distance), so its inverse
# barrier term is below 1e-8 and it never registers a crash anywhere a model can reach. Radius 0
# anywhere else would be a point obstacle at that centre (the margin expressions do not skip
# it), so a scene vector refuses it: every slot is a circle of radius > 0 or INERT_SLOT.
INERT_CENTER = 1e8
SLOT = 3
INERT_SLOT = (INERT_CENTER, INERT_CENTER, 0.0)
SCENE_FORMS = ("a sequence of Circle or (x, y, radius) triples, an (n, 3) array of such rows, "
               "or a flat NumPy scene vector of 3 x scene_capacity entries")


def scene_symbol(capacity: int) -> ca.SX:
    """The scene input of a model with ``capacity`` circle slots: (3 capacity,) SX symbol."""
    return ca.SX.sym("scene", SLOT * int(capacity))


def slot_margins(p, scene: ca.SX, h_form: HForm = "squared", inflation: float = 0.0) -> ca.SX:
    """Margins h_i of a position ``p`` against the circle slots of a scene symbol (one per
    slot), the same expressions as :func:`circle_margins` with the circles as inputs."""
    one_of("h_form", h_form, H_FORMS)
    real("inflation", inflation, 0.0)
    out = []
    for i in range(scene.numel() // SLOT):
        cx, cy, r = scene[SLOT * i], scene[SLOT * i + 1], scene[SLOT * i + 2]
        if inflation:
            r = r + inflation
        d2 = (p[0] - cx) ** 2 + (p[1] - cy) ** 2
        out.append(d2 - r**2 if h_form == "squared" else ca.sqrt(d2) - r)
    return ca.vertcat(*out) if out else ca.SX(0, 1)


def slots_valid(v: np.ndarray) -> bool:
    """Whether every slot of a finite flat scene vector is a circle (radius > 0) or exactly
    :data:`INERT_SLOT` (a fast check, no message)."""
    r, cx, cy = v[2::SLOT], v[0::SLOT], v[1::SLOT]
    return bool(((r > 0) | ((r == 0) & (cx == INERT_CENTER) & (cy == INERT_CENTER))).all())


def check_slots(field: str, v: np.ndarray) -> None:
    """Refuse a finite flat scene vector with a slot that is neither a circle (radius > 0) nor
    the unused slot :data:`INERT_SLOT`, naming the first such slot."""
    if slots_valid(v):
        return
    s = v.reshape(-1, SLOT)
    r, cx, cy = s[:, 2], s[:, 0], s[:, 1]
    i = int(np.flatnonzero(~((r > 0) | ((r == 0) & (cx == INERT_CENTER)
                                         & (cy == INERT_CENTER))))[0])
    what = ("a negative radius" if r[i] < 0 else
            f"radius 0 at centre ({cx[i]:g}, {cy[i]:g}) would be a point obstacle there")
    raise fail(f"{field}[{SLOT * i}:{SLOT * i + SLOT}] (slot {i})", s[i],
               f"{what}; every slot must be a circle with radius > 0 or an unused slot, "
               f"exactly ({INERT_CENTER:g}, {INERT_CENTER:g}, 0) (INERT_SLOT; scene_vector "
               "fills the unused slots when given fewer circles than slots)")


def _triple(field: str, c) -> Circle:
    if isinstance(c, Circle):
        return c
    if isinstance(c, str | bytes) or np.shape(c) != (SLOT,):
        raise fail(field, c, "expected a Circle or an (x, y, radius) triple")
    x, y, r = as_array(field, c, (SLOT,))
    if not r > 0:
        raise fail(field, c, "the radius (third entry) must be > 0; leave unused slots out "
                   "(scene_vector fills them)")
    return Circle(center=(x, y), radius=r)


def _as_circles(scene) -> tuple[Circle, ...]:
    if scene is None:
        raise fail("scene", None, f"no scene given; expected {SCENE_FORMS}")
    if isinstance(scene, Circle):
        raise fail("scene", scene, "one Circle is not a scene: give a sequence of circles, "
                   "e.g. [circle]")
    if isinstance(scene, np.ndarray):
        if scene.ndim != 2 or scene.shape[1] != SLOT:
            raise fail("scene", f"an array of shape {scene.shape}", "an array scene has "
                       "shape (n, 3), one row (x, y, radius) per circle (or is a flat scene "
                       "vector)")
        return tuple(_triple(f"scene[{i}]", row) for i, row in enumerate(scene))
    if isinstance(scene, str | bytes | dict) or not hasattr(scene, "__iter__"):
        raise fail("scene", scene, f"expected {SCENE_FORMS}")
    return tuple(_triple(f"scene[{i}]", c) for i, c in enumerate(scene))


def scene_vector(scene, capacity: int) -> np.ndarray:
    """The flat scene input (3 capacity,) of a set of circles: a sequence of
    :class:`Circle` or ``(x, y, radius)`` triples (radius > 0), or an (n, 3) array, with
    n <= capacity; the remaining slots are inert (:data:`INERT_SLOT`). A flat NumPy array of
    the right size is validated (finite; each slot a circle or :data:`INERT_SLOT`) and
    copied. Anything else is a ValueError naming the value."""
    if isinstance(scene, np.ndarray) and scene.ndim == 1:
        v = as_array("scene", scene, (SLOT * capacity,))
        check_slots("scene", v)
        return v.copy()
    circles = _as_circles(scene)
    if len(circles) > capacity:
        raise fail("scene", f"{len(circles)} circles",
                   f"this model was built with room for at most {capacity} (scene_capacity)")
    v = np.tile(INERT_SLOT, capacity)
    for i, c in enumerate(circles):
        v[SLOT * i: SLOT * i + SLOT] = (*c.center, c.radius)
    return v


def scene_circles(vector) -> tuple[Circle, ...]:
    """The circles of a flat scene vector (inert slots, radius 0, left out)."""
    v = np.asarray(vector, dtype=float).reshape(-1, SLOT)
    return tuple(Circle(center=(a, b), radius=r) for a, b, r in v if r > 0)

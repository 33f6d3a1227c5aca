"""Circular obstacles and their safety margins h_i(p) (h >= 0 is safe), SPEC 3.1."""

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

"""The study's map as config: the generated map of a seed, or the user's own list of circles."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np

from workbench.problem.obstacles import Circle
from workbench.scenarios.scenes import CircleScene, NavigationScene
from workbench.validation import fail


@dataclass(frozen=True)
class MapSpec:
    """Start, goal and map. ``circles`` empty: the paper's map generator (assumptions §3.2)
    with ``seed``; otherwise ((cx, cy, r), ...) is the map. ``u_limit``: control box [P: 5]."""

    start: tuple[float, float] = (0.5, 0.5)
    goal: tuple[float, float] = (9.5, 9.5)
    seed: int = 7
    circles: tuple[tuple[float, float, float], ...] = ()
    u_limit: float = 5.0

    def __post_init__(self) -> None:
        for name in ("start", "goal"):
            p = getattr(self, name)
            a = np.asarray(p, dtype=float) if not isinstance(p, str) else np.zeros(0)
            if a.shape != (2,) or not np.all(np.isfinite(a)):
                raise fail(f"scene.{name}", p, "must be two finite numbers (x, y) [m]")
            object.__setattr__(self, name, (float(a[0]), float(a[1])))
        circles = []
        for i, c in enumerate(self.circles):
            a = np.asarray(c, dtype=float)
            if a.shape != (3,) or not np.all(np.isfinite(a)) or a[2] <= 0:
                raise fail(f"scene.circles[{i}]", c, "must be (cx, cy, r) with r > 0")
            circles.append((float(a[0]), float(a[1]), float(a[2])))
        object.__setattr__(self, "circles", tuple(circles))
        if not (np.isfinite(self.u_limit) and self.u_limit > 0):
            raise fail("scene.u_limit", self.u_limit, "must be a finite number > 0")

    def scene(self) -> NavigationScene | CircleScene:
        if self.circles:
            return CircleScene(self.circles, self.start, self.goal, u_limit=self.u_limit)
        return NavigationScene(start=self.start, goal=self.goal, seed=self.seed,
                               u_limit=self.u_limit)

    def obstacles(self) -> tuple[Circle, ...]:
        return _obstacles(self)

    def check(self) -> None:
        """Start and goal must lie outside every obstacle (h > 0)."""
        try:
            obstacles = self.obstacles()
        except ValueError as exc:
            # the scene itself rejects a start or goal inside an obstacle: name that field
            field = next((f"scene.{n}" for n in ("start", "goal")
                          if f"Scene.{n} =" in str(exc)), "scene.seed")
            raise fail(field, getattr(self, field.split(".")[1]), str(exc)) from exc
        for name in ("start", "goal"):
            p = np.array(getattr(self, name))
            for i, o in enumerate(obstacles):
                if np.sum((p - np.array(o.center)) ** 2) - o.radius ** 2 <= 0:
                    raise fail(f"scene.{name}", getattr(self, name),
                               f"lies inside obstacle {i} (centre {o.center}, radius "
                               f"{o.radius:g})")

    def circle_array(self) -> np.ndarray:
        """The map as an (n, 3) array of (cx, cy, r)."""
        return np.array([(*o.center, o.radius) for o in self.obstacles()])


@cache
def _obstacles(spec: MapSpec) -> tuple[Circle, ...]:
    return spec.scene().obstacles()  # the generator rejection-samples in Python: once

"""Scenes of the paper's studies, with every assumed value marked [A] (SPEC 3.3)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from workbench.obstacles import Circle


@dataclass(frozen=True)
class TrackingScene:
    """SPEC 3.3: one obstacle on a straight, unsafe reference from start to target."""

    start: tuple[float, ...] = (-5.0, 0.0, 0.0, 0.0)  # [A]
    target: tuple[float, ...] = (5.0, 0.0, 0.0, 0.0)  # [A]
    obstacle: Circle = field(default_factory=lambda: Circle((0.0, 0.1), 1.5))  # [A]
    horizon: int = 150  # [A] N, DBaS-code DI example
    dt: float = 0.02  # [A]
    u_limit: float = 15.0  # [P]

    def reference(self) -> np.ndarray:
        """Straight line start -> target at constant speed over the horizon, (T+1, 4)."""
        T = self.horizon
        s = np.linspace(0.0, 1.0, T + 1)[:, None]
        p0, p1 = np.array(self.start[:2]), np.array(self.target[:2])
        v = (p1 - p0) / (T * self.dt)
        return np.hstack([p0 + s * (p1 - p0), np.broadcast_to(v, (T + 1, 2))])

    def assumed_values(self) -> dict[str, object]:
        return {"start": self.start, "target": self.target,
                "obstacle_center": self.obstacle.center, "obstacle_radius": self.obstacle.radius,
                "horizon": self.horizon, "dt": self.dt}


@dataclass(frozen=True)
class NavigationScene:
    """SPEC 3.2 [A]: 30 circles in [0,10]^2 with a central vertical corridor, fixed seed."""

    start: tuple[float, float] = (0.5, 0.5)
    goal: tuple[float, float] = (9.5, 9.5)
    n_obstacles: int = 30
    gate_radius: float = 1.0
    corridor_width: float = 0.8
    radius_range: tuple[float, float] = (0.3, 0.9)
    center_range: tuple[float, float] = (1.0, 9.0)
    endpoint_clearance: float = 0.75
    edge_gap: float = 0.4
    seed: int = 7
    dt: float = 0.02
    u_limit: float = 5.0  # [P]

    def obstacles(self) -> tuple[Circle, ...]:
        """The map: two gate circles, then rejection-sampled circles (deterministic in seed)."""
        off = self.gate_radius + self.corridor_width / 2
        circles = [Circle((5.0 - off, 5.0), self.gate_radius),
                   Circle((5.0 + off, 5.0), self.gate_radius)]
        rng = np.random.default_rng(self.seed)
        ends = (np.array(self.start), np.array(self.goal))
        for _ in range(100_000):
            if len(circles) == self.n_obstacles:
                break
            r = rng.uniform(*self.radius_range)
            c = rng.uniform(*self.center_range, size=2)
            if any(np.linalg.norm(c - e) - r < self.endpoint_clearance for e in ends):
                continue
            if any(np.linalg.norm(c - np.array(o.center)) - r - o.radius < self.edge_gap
                   for o in circles):
                continue
            circles.append(Circle((float(c[0]), float(c[1])), float(r)))
        if len(circles) < self.n_obstacles:
            raise ValueError(f"NavigationScene.seed = {self.seed} is invalid: could not place "
                             f"{self.n_obstacles} obstacles")
        return tuple(circles)

    def assumed_values(self) -> dict[str, object]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}

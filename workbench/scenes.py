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

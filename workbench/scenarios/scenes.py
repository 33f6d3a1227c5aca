"""Scenes of the paper's studies, with every assumed value marked [A] (assumptions §3.3)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from workbench.problem.obstacles import Circle
from workbench.problem.scene_layout import SceneLayout
from workbench.validation import as_array, fail, positive


@dataclass(frozen=True)
class TrackingScene:
    """assumptions §3.3: one obstacle on a straight, unsafe reference from start to target."""

    start: tuple[float, ...] = (-5.0, 0.0, 0.0, 0.0)  # [A]
    target: tuple[float, ...] = (5.0, 0.0, 0.0, 0.0)  # [A]
    obstacle: Circle = field(default_factory=lambda: Circle((0.0, 0.1), 1.5))  # [A]
    horizon: int = 150  # [A] N, DBaS-code DI example
    dt: float = 0.02  # [A]
    u_limit: float = 15.0  # [P]

    def __post_init__(self) -> None:
        for name in ("start", "target"):
            as_array(f"TrackingScene.{name}", getattr(self, name), (4,))
        if not isinstance(self.horizon, int | np.integer) or isinstance(self.horizon, bool) \
                or self.horizon < 1:
            raise fail("TrackingScene.horizon", self.horizon, "must be an integer >= 1")
        positive("TrackingScene.dt", self.dt)
        positive("TrackingScene.u_limit", self.u_limit)

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
    """assumptions §3.2 [A]: 30 circles in [0,10]^2 with a central vertical corridor, fixed seed.

    ``n_obstacles`` counts every circle, the two gate circles of the corridor included.
    """

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

    def __post_init__(self) -> None:
        for name in ("start", "goal"):
            as_array(f"NavigationScene.{name}", getattr(self, name), (2,))
        n = self.n_obstacles
        if not isinstance(n, int | np.integer) or isinstance(n, bool) or n < 2:
            raise fail("NavigationScene.n_obstacles", n,
                       "must be an integer >= 2 (it counts the two gate circles of the corridor)")
        if not isinstance(self.seed, int | np.integer) or isinstance(self.seed, bool) \
                or self.seed < 0:
            raise fail("NavigationScene.seed", self.seed, "must be an integer >= 0")
        for name in ("radius_range", "center_range"):
            lo, hi = as_array(f"NavigationScene.{name}", getattr(self, name), (2,))
            if not lo <= hi:
                raise fail(f"NavigationScene.{name}", getattr(self, name),
                           "must be (low, high) with low <= high")
        if self.radius_range[0] <= 0:
            raise fail("NavigationScene.radius_range", self.radius_range, "radii must be > 0")
        for name in ("gate_radius", "corridor_width", "dt", "u_limit"):
            positive(f"NavigationScene.{name}", getattr(self, name))
        for name in ("endpoint_clearance", "edge_gap"):
            positive(f"NavigationScene.{name}", getattr(self, name), allow_zero=True)
        self._check_endpoints(self._gates())

    def obstacles(self) -> tuple[Circle, ...]:
        """The map: two gate circles, then random circles (deterministic in seed).

        Circles are first rejection-sampled (radius and centre uniform) for up to ``_DRAWS``
        draws: every map this completes is unchanged from earlier versions, the default one
        included. Rejection sampling jams on dense maps (it failed for 11 of the first 20
        seeds): :meth:`_complete` then finishes the map on a grid of candidate centres. Only
        when no strategy fits even the smallest radius is the map infeasible, and the error
        says what (density, radius range, clearances).
        """
        circles = self._gates()
        rng = np.random.default_rng(self.seed)
        circles = self._sample(circles, rng)
        if len(circles) < self.n_obstacles:
            circles = self._complete(circles, rng)
        return tuple(circles)

    def _sample(self, circles: list[Circle], rng: np.random.Generator) -> list[Circle]:
        """Rejection sampling, all ``_DRAWS`` draws at once: draw i is a radius then a centre
        (the generator's doubles 3i, 3i + 1, 3i + 2, as one ``uniform`` call for the radius
        and one for the centre would take them); it is kept when it clears both endpoints and
        every circle kept before it. The same circles as drawing one at a time; the generator
        ends where that loop would when the map is not complete (the grid placement goes on
        from there)."""
        if len(circles) >= self.n_obstacles:
            return circles
        u = rng.random((_DRAWS, 3))
        (rlo, rhi), (clo, chi) = self.radius_range, self.center_range
        r = rlo + (rhi - rlo) * u[:, 0]
        c = clo + (chi - clo) * u[:, 1:]

        def dist(p) -> np.ndarray:
            d = c - np.asarray(p, dtype=float)
            return np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1])

        ok = np.ones(_DRAWS, dtype=bool)
        for e in (self.start, self.goal):
            ok &= ~(dist(e) - r < self.endpoint_clearance)
        for o in circles:
            ok &= ~(dist(o.center) - r - o.radius < self.edge_gap)
        out, i = list(circles), 0
        while len(out) < self.n_obstacles:
            rest = np.flatnonzero(ok[i:])
            if rest.size == 0:
                break
            i += int(rest[0])
            out.append(Circle((float(c[i, 0]), float(c[i, 1])), float(r[i])))
            ok[i + 1:] &= ~(dist(c[i])[i + 1:] - r[i + 1:] - r[i] < self.edge_gap)
            i += 1
        return out

    def _gates(self) -> list[Circle]:
        off = self.gate_radius + self.corridor_width / 2
        return [Circle((5.0 - off, 5.0), self.gate_radius),
                Circle((5.0 + off, 5.0), self.gate_radius)]

    def _check_endpoints(self, circles) -> None:
        """Start and goal outside the gate circles (the random circles keep
        endpoint_clearance from both by construction)."""
        for name in ("start", "goal"):
            p = np.array(getattr(self, name), dtype=float)
            for i, o in enumerate(circles):
                if np.linalg.norm(p - np.array(o.center)) <= o.radius:
                    raise fail(f"NavigationScene.{name}", getattr(self, name),
                               f"lies inside obstacle {i} (centre {o.center}, radius "
                               f"{o.radius:g}); start and goal must be in free space")

    def _infeasible(self, placed: int) -> str:
        lo, hi = self.center_range
        r0, r1 = self.radius_range
        cover = (self.n_obstacles - 2) * np.pi * ((r0 + r1) / 2 + self.edge_gap / 2) ** 2
        return (f"NavigationScene: placed at most {placed} of n_obstacles = {self.n_obstacles} "
                f"circles; no centre in center_range = {self.center_range} leaves room for the "
                f"smallest radius (radius_range[0] = {r0:g}) with edge_gap = {self.edge_gap:g} "
                f"to the other circles and endpoint_clearance = {self.endpoint_clearance:g} to "
                f"start and goal: the map is too dense (the random circles with half the gap "
                f"cover about {cover:.0f} m^2; the centre area is {(hi - lo) ** 2:.0f} m^2). "
                "Lower n_obstacles, the radius range or the gaps, or widen center_range")

    def _complete(self, circles: list[Circle], rng: np.random.Generator) -> list[Circle]:
        """Finish a map rejection sampling could not: first fill the gaps it left on the grid;
        if that jams, pack all random circles afresh, smallest first, each touching the
        circles already placed (drawn among the ``jitter`` tightest fits). Strategies are
        tried in order with the same generator, so the map stays deterministic in the seed."""
        most = 0
        for jitter in (None, 10, 100, 1):
            start = list(circles) if jitter is None else list(circles[:2])
            radii = None if jitter is None else np.sort(
                rng.uniform(*self.radius_range, self.n_obstacles - 2))
            try:
                return self._place_on_grid(start, rng, radii=radii, jitter=jitter)
            except _Jammed as exc:
                most = max(most, exc.args[0])
        raise ValueError(self._infeasible(most))

    def _place_on_grid(self, circles: list[Circle], rng: np.random.Generator, *,
                       radii: np.ndarray | None, jitter: int | None) -> list[Circle]:
        """Place circles until there are n_obstacles, on a grid of candidate centres.

        Each circle takes the next of ``radii`` (or a drawn radius) at a centre where it fits:
        any such centre (``jitter`` None), or one of the ``jitter`` tightest fits (touching the
        circles already placed: dense packing that leaves the open space for later circles).
        Without a centre for that radius the largest circle that still fits is used. Raises
        _Jammed(placed) when not even the smallest radius fits anywhere.
        """
        lo, hi = self.center_range
        g = np.arange(lo, hi + 1e-12, _GRID)
        G = np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1).reshape(-1, 2)
        room = np.full(G.shape[0], np.inf)  # largest radius each candidate centre allows
        for e in (self.start, self.goal):
            room = np.minimum(room, np.hypot(*(G - np.array(e)).T) - self.endpoint_clearance)

        def shrink(o: Circle) -> np.ndarray:
            return np.hypot(*(G - np.array(o.center)).T) - o.radius - self.edge_gap

        for o in circles:
            room = np.minimum(room, shrink(o))
        i = 0
        while len(circles) < self.n_obstacles:
            r = float(radii[i]) if radii is not None else float(rng.uniform(*self.radius_range))
            i += 1
            fits = np.flatnonzero(room >= r)
            if fits.size:
                if jitter is not None:
                    fits = fits[np.argsort(room[fits], kind="stable")[:jitter]]
                k = int(fits[rng.integers(fits.size)])
            else:
                k = int(np.argmax(room))
                r = float(room[k])
                if r < self.radius_range[0]:
                    raise _Jammed(len(circles))
            c = Circle((float(G[k, 0]), float(G[k, 1])), r)
            circles.append(c)
            room = np.minimum(room, shrink(c))
        return circles

    def assumed_values(self) -> dict[str, object]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


_DRAWS = 100_000  # rejection-sampling draws before the grid placement takes over
_GRID = 0.02  # grid spacing of candidate centres (m)


class _Jammed(Exception):
    """Grid placement found no room for the smallest radius (args: circles placed)."""


@dataclass(frozen=True)
class CircleScene:
    """A navigation scene of your own circles: ``navigation_setup(CircleScene(...))``.

    circles: :class:`~workbench.problem.obstacles.Circle` objects or ``(x, y, radius)``
    triples; start and goal positions (2,) in free space; dt and the control box as in
    :class:`NavigationScene`. ``CircleScene.from_circles(circles, start, goal)`` is the same.
    """

    circles: tuple[Circle, ...]
    start: tuple[float, float] = (0.5, 0.5)
    goal: tuple[float, float] = (9.5, 9.5)
    dt: float = 0.02
    u_limit: float = 5.0

    def __post_init__(self) -> None:
        if isinstance(self.circles, Circle) or not hasattr(self.circles, "__iter__"):
            raise fail("CircleScene.circles", self.circles, "must be a sequence of Circle or "
                       "(x, y, radius)")
        circles = []
        for i, c in enumerate(self.circles):
            if not isinstance(c, Circle):
                xyr = as_array(f"CircleScene.circles[{i}]", c, (3,))
                if not xyr[2] > 0:
                    raise fail(f"CircleScene.circles[{i}]", c, "the radius (third entry) "
                               "must be > 0")
                c = Circle((xyr[0], xyr[1]), xyr[2])
            circles.append(c)
        object.__setattr__(self, "circles", tuple(circles))
        for name in ("start", "goal"):
            p = as_array(f"CircleScene.{name}", getattr(self, name), (2,))
            object.__setattr__(self, name, (float(p[0]), float(p[1])))
            for i, o in enumerate(circles):
                d = float(np.linalg.norm(p - np.array(o.center)))
                if d <= o.radius:
                    where = "on the boundary of" if d == o.radius else "inside"
                    raise fail(f"CircleScene.{name}", getattr(self, name),
                               f"lies {where} circle {i} (centre {o.center}, radius "
                               f"{o.radius:g}); start and goal must be in free space")
        positive("CircleScene.dt", self.dt)
        positive("CircleScene.u_limit", self.u_limit)

    @classmethod
    def from_circles(cls, circles, start=(0.5, 0.5), goal=(9.5, 9.5), **kw) -> CircleScene:
        return cls(tuple(circles), start, goal, **kw)

    def obstacles(self) -> tuple[Circle, ...]:
        return self.circles

    def assumed_values(self) -> dict[str, object]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


@dataclass(frozen=True, eq=False)
class ObstacleScene:
    """A navigation scene of obstacles of any kind: ``navigation_setup(ObstacleScene(...))``
    builds the plant on a :class:`~workbench.problem.scene_layout.SceneLayout`.

    objects: :class:`Circle`, :class:`~workbench.problem.scene_kinds.HalfSpace`,
    :class:`~workbench.problem.scene_kinds.Capsule`,
    :class:`~workbench.problem.scene_kinds.MovingCircle` (at its time-0 position) and at most
    one :class:`~workbench.problem.sdf_grid.SignedDistanceGrid` (e.g. an occupancy map's,
    :mod:`workbench.scenarios.occupancy`); start and goal positions (2,); dt and the control
    box as in :class:`NavigationScene`. layout: the slots of the plant's scene input (default:
    exactly the given obstacles, :meth:`SceneLayout.fitting`); a larger one lets other scenes
    with up to that many obstacles (and a grid of the same shape) share compiled kernels.
    Start and goal are checked to be in free space when the plant is built.
    """

    objects: tuple
    start: tuple[float, float] = (0.5, 0.5)
    goal: tuple[float, float] = (9.5, 9.5)
    dt: float = 0.02
    u_limit: float = 5.0
    layout: SceneLayout | None = None

    def __post_init__(self) -> None:
        if isinstance(self.objects, str | bytes) or not hasattr(self.objects, "__iter__"):
            raise fail("ObstacleScene.objects", self.objects, "must be a sequence of obstacles")
        objects = tuple(self.objects)
        layout = self.layout
        if layout is None:
            layout = SceneLayout.fitting(objects, "ObstacleScene.objects")
        elif not isinstance(layout, SceneLayout):
            raise fail("ObstacleScene.layout", layout, "must be a SceneLayout or None")
        if layout.dim != 2:
            raise fail("ObstacleScene.layout", layout, "a navigation scene is planar (dim 2)")
        layout.vector(list(objects), "ObstacleScene.objects")  # refuses what does not fit
        object.__setattr__(self, "objects", objects)
        object.__setattr__(self, "layout", layout)
        for name in ("start", "goal"):
            p = as_array(f"ObstacleScene.{name}", getattr(self, name), (2,))
            object.__setattr__(self, name, (float(p[0]), float(p[1])))
        positive("ObstacleScene.dt", self.dt)
        positive("ObstacleScene.u_limit", self.u_limit)

    @property
    def scene_layout(self) -> SceneLayout:
        """The layout the plant is built with."""
        assert self.layout is not None
        return self.layout

    def obstacles(self) -> tuple:
        return self.objects

    def assumed_values(self) -> dict[str, object]:
        return {"start": self.start, "goal": self.goal, "dt": self.dt,
                "u_limit": self.u_limit, "layout": self.scene_layout,
                "objects": [repr(o) for o in self.objects]}

"""Map families drawn from a seed, moving obstacles and a difficulty measure per map.

All maps live in the box [0, 10]^2 with start (0.5, 0.5) and goal (9.5, 9.5) by default;
:func:`scaled` scales a map (or scene) afterwards. Three families of circles
(:data:`MAP_FAMILIES`):

- ``"spec"``: the paper's map family, :class:`~workbench.scenarios.scenes.NavigationScene`
  (two gate circles around a central corridor plus random circles), reused as is.
- ``"corridor"``: ``n_gates`` walls of overlapping circles cross the box perpendicular to the
  start-goal line, each with one gate of width ``corridor_width``, plus random circles.
- ``"occupancy"``: cellular-automaton occupancy grids made the way the BARN benchmark makes
  its maps (Perille, Truong, Xiao and Stone 2020, "Benchmarking Metric Ground Navigation",
  arXiv 2008.13315; their generator github.com/dperille/jackal-map-creation): each of the
  grid x grid cells is occupied with probability ``fill``, then ``smoothing`` synchronous
  automaton steps over the 8 neighbours make a cell with >= 5 occupied neighbours occupied and
  one with <= 1 free (others keep their state); maps whose start and goal are not linked are
  thrown away and drawn again (BARN's 300 maps: 30 x 30 cells, fill 0.15 to 0.30, 2 to 4
  steps; its script's default fill 0.27 and 4 steps are the defaults here). Differences:
  BARN fills its top and bottom rows (its corridor walls) and counts the outside there as
  occupied, here the outside counts as free (the box bounds the map); BARN checks the link
  with obstacles inflated by its robot, here the cells near start and goal are cleared
  (endpoint_clearance), the free cells must link start and goal (4-connected flood fill, as
  BARN) and the circles must leave a passage at least min_gap wide. The grid becomes circles
  by :func:`cover_cells` (conservative: every occupied cell is covered, no circle reaches
  more than (sqrt 2 - 1) / 2 cell sizes beyond the occupied cells).

and two families whose obstacles are shapes other than circles (:data:`LAYOUT_FAMILIES`; their
:meth:`GeneratedMap.scene` is an :class:`~workbench.scenarios.scenes.ObstacleScene` on the
family's :meth:`GeneratedMap.layout`, the same for every seed, so one compiled set of kernels
serves every map of the family; no moving obstacles):

- ``"corridor_capsules"``: the ``"corridor"`` family's maps (the same walls, gates and random
  circles for the same knobs and seed), each wall's two sides given as capsules (the segment
  through the centres of that side's circles, their radius) instead of chains of circles: the
  capsules hold the circles, the gates keep their width and the walls lose their scallops.
  A side of a single circle stays a circle. The difficulty is that of the circle walls.
- ``"occupancy_grid"``: the ``"occupancy"`` family's cells (the same cells for the same knobs
  and seed), the obstacles given as the signed-distance grid of the cells
  (:meth:`~workbench.scenarios.occupancy.OccupancyMap.signed_distance`, nodes at the cell
  centres) instead of covering circles: the plant's scene input is one grid of ``grid`` x
  ``grid`` nodes. Its difficulty is that of the covering circles (as the occupancy family's).

``generate(MapFamily(...), seed)`` is deterministic in (family, seed) and returns a
:class:`GeneratedMap` with its :class:`MapDifficulty`. The box is where maps live and what
the difficulty measure treats as the boundary; the navigation plant itself does not keep the
robot inside it (a controller may leave the box, e.g. around the end of a corridor wall).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from workbench.problem.obstacles import Circle
from workbench.problem.scene_kinds import Capsule, HalfSpace, MovingCircle
from workbench.problem.scene_layout import SceneLayout
from workbench.problem.sdf_grid import SignedDistanceGrid
from workbench.scenarios.occupancy import OccupancyMap
from workbench.scenarios.scenes import CircleScene, NavigationScene, ObstacleScene
from workbench.validation import as_array, fail, flag, integer, real

MAP_FAMILIES: tuple[str, ...] = ("spec", "corridor", "occupancy")
LAYOUT_FAMILIES: tuple[str, ...] = ("corridor_capsules", "occupancy_grid")  # not circles
FAMILIES: tuple[str, ...] = MAP_FAMILIES + LAYOUT_FAMILIES
BOX: tuple[tuple[float, float], tuple[float, float]] = ((0.0, 10.0), (0.0, 10.0))
# n_obstacles when unset: spec counts every circle (gates included, as NavigationScene);
# corridor counts the random circles besides the walls; occupancy has none
DEFAULT_OBSTACLES = {"spec": 30, "corridor": 5, "corridor_capsules": 5}
CENTER_RANGE = (1.0, 9.0)  # centres of random and moving circles (as NavigationScene)
WALL_SPACING = 1.5  # wall circles' centre spacing in radii: overlap, thinnest part 1.32 radii
WALL_JITTER = 0.15  # walls sit at (i + U(-j, j)) / (n_gates + 1) of the start-goal line
MAX_DRAWS = 20_000  # rejection-sampling draws for random and moving circles
MAX_MAPS = 60  # occupancy grids drawn before giving up on a connected one
MAX_CIRCLES = 1000  # n_obstacles (and moving) of one map: each circle is a scene slot
MAX_GRID = 100  # occupancy cells per side: cover_cells needs (occupied cells)^2 bits
MAX_NODES = 2**20  # grid nodes of one difficulty evaluation: resolution 0.01 on [0, 10]^2 fits
_CHUNK = 2**22  # float64 entries of one block of cover_cells' pairwise distances (32 MB)


@dataclass(frozen=True)
class MapFamily:
    """A map family and its knobs (lengths in m, in the box [0, 10]^2).

    family: one of :data:`MAP_FAMILIES` or :data:`LAYOUT_FAMILIES`. n_obstacles: spec: every
    circle, the two gate circles included (default 30); corridor: random circles besides the
    walls (default 5, also corridor_capsules); occupancy and occupancy_grid: must stay unset
    (:attr:`obstacle_count` resolves the default). radius_range:
    radii of random and moving circles (corridor walls use the upper end). min_gap: smallest
    edge-to-edge gap between a random or moving circle and any other circle (wall circles
    overlap each other by design); for occupancy maps, the narrowest passage the start-goal
    connection must keep (BARN checks connectivity in the robot's configuration space).
    corridor_width: the spec gate's width and the corridor gates' width (random circles keep
    at least this gap to wall circles). n_gates: corridor walls, one gate each. fill, grid,
    smoothing: occupancy initial fill fraction, cells per side and cellular-automaton
    iterations. start, goal: inside the box. endpoint_clearance: every circle's edge keeps
    this distance from start and goal. moving, speed: number of moving circles and their
    speed (m/s) (see :func:`generate`; none on the :data:`LAYOUT_FAMILIES` maps). predict:
    True tells the controllers the moving circles' velocities, which they predict over their
    horizon (:meth:`GeneratedMap.velocity_scene`); unset or False: they see the circles where
    they are now (the maps themselves are the same).

    Counts are integers (never ``bool``) with upper limits: n_obstacles and moving <=
    :data:`MAX_CIRCLES`, n_gates <= 20, grid in [4, :data:`MAX_GRID`], smoothing <= 100.
    """

    family: str = "spec"
    n_obstacles: int | None = None
    radius_range: tuple[float, float] = (0.3, 0.9)
    min_gap: float = 0.4
    corridor_width: float = 0.8
    n_gates: int = 2
    fill: float = 0.27
    grid: int = 20
    smoothing: int = 4
    start: tuple[float, float] = (0.5, 0.5)
    goal: tuple[float, float] = (9.5, 9.5)
    endpoint_clearance: float = 0.75
    moving: int = 0
    speed: float = 0.5
    predict: bool | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.family, str) or self.family not in FAMILIES:
            raise fail("map.family", self.family,
                       f"unknown map family; allowed values are {FAMILIES}")
        n = self.n_obstacles
        if n is not None and self.family in ("occupancy", "occupancy_grid"):
            raise fail("map.n_obstacles", n, f"the {self.family} family has no obstacle "
                       "count (fill, grid and smoothing shape its maps); leave it unset")
        if n is not None:
            low = 2 if self.family == "spec" else 0
            what = " (it counts the two gate circles)" if low else ""
            try:
                integer("map.n_obstacles", n, low, MAX_CIRCLES)
            except ValueError as exc:
                raise fail("map.n_obstacles", n, f"must be an integer in [{low}, {MAX_CIRCLES}]"
                           f"{what}") from exc
        lo, hi = as_array("map.radius_range", self.radius_range, (2,))
        if not 0 < lo <= hi:
            raise fail("map.radius_range", self.radius_range,
                       "must be (low, high) with 0 < low <= high")
        object.__setattr__(self, "radius_range", (float(lo), float(hi)))
        real("map.min_gap", self.min_gap, 0.0)
        real("map.corridor_width", self.corridor_width, 0.0, strict=True)
        integer("map.n_gates", self.n_gates, 0, 20)
        real("map.fill", self.fill, 0.0, maximum=1.0)
        integer("map.grid", self.grid, 4, MAX_GRID)
        integer("map.smoothing", self.smoothing, 0, 100)
        for name in ("start", "goal"):
            p = as_array(f"map.{name}", getattr(self, name), (2,))
            if not np.all((p > BOX[0][0]) & (p < BOX[0][1])):
                raise fail(f"map.{name}", getattr(self, name),
                           f"must lie strictly inside the box [{BOX[0][0]:g}, {BOX[0][1]:g}]^2")
            object.__setattr__(self, name, (float(p[0]), float(p[1])))
        if np.hypot(self.goal[0] - self.start[0], self.goal[1] - self.start[1]) < 1e-9:
            raise fail("map.goal", self.goal, "must differ from map.start")
        real("map.endpoint_clearance", self.endpoint_clearance, 0.0)
        integer("map.moving", self.moving, 0, MAX_CIRCLES)
        if self.moving and self.family in LAYOUT_FAMILIES:
            raise fail("map.moving", self.moving, f"the {self.family} family has no moving "
                       "obstacles; use 0 (or the occupancy family, whose map is circles)")
        real("map.speed", self.speed, 0.0)
        if self.predict is not None:
            flag("map.predict", self.predict)
            if self.predict and not self.moving:
                raise fail("map.predict", self.predict, "predicts moving circles: set "
                           "map.moving > 0, or leave predict out")

    @property
    def obstacle_count(self) -> int:
        """n_obstacles, or the family's default when unset (0 for occupancy)."""
        if self.n_obstacles is not None:
            return int(self.n_obstacles)
        return DEFAULT_OBSTACLES.get(self.family, 0)


@dataclass(frozen=True)
class MapDifficulty:
    """Difficulty of a map for a point robot going from start to goal.

    bottleneck: the largest c such that some collision-free path keeps clearance >= c all the
    way (the widest path; clearance = distance to the nearest circle edge, capped by the
    distance to the box edge), on a grid (:func:`difficulty`); 0.0 when there is no path.
    path_length: length of the shortest path that keeps that clearance (m; inf without a
    path). straight_clearance: smallest clearance on the straight start-goal segment (< 0:
    the segment cuts a circle). n_circles: number of circles. coverage: fraction of the box
    covered by circles.
    """

    bottleneck: float
    path_length: float
    straight_clearance: float
    n_circles: int
    coverage: float

    def as_dict(self) -> dict[str, float]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


def _circle_array(circles) -> np.ndarray:
    out = []
    for i, c in enumerate(circles):
        if isinstance(c, Circle):
            out.append((*c.center, c.radius))
        else:
            out.append(tuple(as_array(f"circles[{i}]", c, (3,))))
    return np.array(out, dtype=float).reshape(-1, 3)


def _circle_distance(X: np.ndarray, Y: np.ndarray, C: np.ndarray) -> np.ndarray:
    """Distance of the points (X, Y) to the nearest circle edge (inf without circles)."""
    d = np.full(np.broadcast_shapes(X.shape, Y.shape), np.inf)
    for cx, cy, r in C:
        np.minimum(d, np.hypot(X - cx, Y - cy) - r, out=d)
    return d


# 16-neighbourhood (half of it; the graph is undirected): steps and the nodes a knight step
# passes between (both must be free)
_STEPS = ((1, 0, ()), (0, 1, ()), (1, 1, ()), (1, -1, ()),
          (1, 2, ((0, 1), (1, 1))), (2, 1, ((1, 0), (1, 1))),
          (1, -2, ((0, -1), (1, -1))), (2, -1, ((1, 0), (1, -1))))


def _shift(mask: np.ndarray, di: int, dj: int) -> np.ndarray:
    """mask[i + di, j + dj] aligned with (i, j) (False outside)."""
    out = np.zeros_like(mask)
    n, m = mask.shape
    out[max(0, -di):n - max(0, di), max(0, -dj):m - max(0, dj)] = \
        mask[max(0, di):n - max(0, -di), max(0, dj):m - max(0, -dj)]
    return out


def _shortest(free: np.ndarray, hx: float, hy: float, s: tuple[int, int],
              g: tuple[int, int]) -> float:
    """Shortest path length between grid nodes s and g through free nodes (16-neighbour)."""
    n, m = free.shape
    idx = np.arange(n * m).reshape(n, m)
    rows, cols, w = [], [], []
    for di, dj, between in _STEPS:
        ok = free & _shift(free, di, dj)
        for bi, bj in between:
            ok &= _shift(free, bi, bj)
        a = idx[ok]
        rows.append(a)
        cols.append(a + di * m + dj)
        w.append(np.full(a.size, np.hypot(di * hx, dj * hy)))
    graph = coo_matrix((np.concatenate(w), (np.concatenate(rows), np.concatenate(cols))),
                       shape=(n * m, n * m)).tocsr()
    dist = dijkstra(graph, directed=False, indices=idx[s], limit=np.inf)
    return float(dist[idx[g]])


def difficulty(circles, start, goal, *, resolution: float = 0.05,
               box=BOX) -> MapDifficulty:
    """The :class:`MapDifficulty` of circles (Circle or (x, y, r)) between start and goal.

    Clearance is evaluated on the nodes of a grid of spacing ``resolution`` over ``box``
    ((x_lo, x_hi), (y_lo, y_hi)); start and goal are snapped to their nearest nodes (the
    snapping distances are added to the length). The bottleneck is exact on the nodes: the
    largest clearance c whose set {clearance >= c} links start and goal (8-connected); since
    clearance is 1-Lipschitz, the straight steps between nodes keep it within
    resolution / sqrt(2). path_length: the shortest 16-neighbour path in that set (exact along
    the lattice directions 0, 26.6, 45, 63.4, ... degrees, at most 2.7 % long in between).
    Without a path (or with start or goal inside a circle) the bottleneck is 0.0 and the
    length inf. straight_clearance is exact; coverage is the covered fraction of the grid's
    cell centres. The grid has at most :data:`MAX_NODES` nodes (resolution 0.01 on the box
    [0, 10]^2).
    """
    res = real("difficulty.resolution", resolution, 0.0, strict=True)
    b = as_array("difficulty.box", box, (2, 2))
    if not np.all(b[:, 1] > b[:, 0]):
        raise fail("difficulty.box", box, "must be ((x_lo, x_hi), (y_lo, y_hi)) with lo < hi")
    with np.errstate(over="ignore"):
        nodes = np.prod([max(1.0, np.rint((hi - lo) / res)) + 1 for lo, hi in b])
    if not nodes <= MAX_NODES:
        raise fail("difficulty.resolution", resolution,
                   f"gives a grid of {nodes:.4g} nodes over the box {b.tolist()}, above the "
                   f"limit {MAX_NODES}; use a coarser resolution")
    p0 = as_array("difficulty.start", start, (2,))
    p1 = as_array("difficulty.goal", goal, (2,))
    C = _circle_array(circles)
    nx, ny = (max(1, round((hi - lo) / res)) for lo, hi in b)
    xs, ys = np.linspace(b[0, 0], b[0, 1], nx + 1), np.linspace(b[1, 0], b[1, 1], ny + 1)
    hx, hy = xs[1] - xs[0], ys[1] - ys[0]
    X, Y = xs[:, None], ys[None, :]
    edge = np.minimum(np.minimum(X - b[0, 0], b[0, 1] - X), np.minimum(Y - b[1, 0], b[1, 1] - Y))
    clear = np.minimum(_circle_distance(X, Y, C), edge)

    def node(p):
        i = int(np.clip(np.rint((p[0] - b[0, 0]) / hx), 0, nx))
        j = int(np.clip(np.rint((p[1] - b[1, 0]) / hy), 0, ny))
        return (i, j), float(np.hypot(p[0] - xs[i], p[1] - ys[j]))

    (s, ds), (g, dg) = node(p0), node(p1)

    def box_clear(p):
        return float(min(p[0] - b[0, 0], b[0, 1] - p[0], p[1] - b[1, 0], b[1, 1] - p[1]))

    ends = min(box_clear(p0), box_clear(p1), float(_circle_distance(p0[0], p0[1], C)),
               float(_circle_distance(p1[0], p1[1], C)))
    eight = np.ones((3, 3), dtype=bool)

    def linked(t: float) -> bool:
        lab, _ = ndimage.label(clear >= t, structure=eight)
        return lab[s] != 0 and lab[s] == lab[g]

    bottleneck, length = 0.0, np.inf
    top = min(clear[s], clear[g])
    if ends > 0 and top > 0:
        levels = np.unique(clear[(clear > 0) & (clear <= top)])
        lo, hi = 0, levels.size - 1  # find the largest level that links s and g
        if levels.size and linked(levels[0]):
            while lo < hi:
                mid = (lo + hi + 1) // 2
                lo, hi = (mid, hi) if linked(levels[mid]) else (lo, mid - 1)
            bottleneck = float(min(levels[lo], ends))  # off-node start or goal: their own
            length = _shortest(clear >= bottleneck, hx, hy, s, g) + ds + dg
    # straight segment: circles exactly (point-segment distance); the box edge distance is
    # concave along the segment, so its minimum is at an end
    d = p1 - p0
    straight = min(box_clear(p0), box_clear(p1))
    if C.shape[0]:
        t = np.clip(((C[:, :2] - p0) @ d) / (d @ d if d @ d > 0 else 1.0), 0.0, 1.0)
        near = p0 + t[:, None] * d
        straight = min(straight, float(np.min(np.hypot(*(near - C[:, :2]).T) - C[:, 2])))
    cx, cy = (xs[:-1] + xs[1:]) / 2, (ys[:-1] + ys[1:]) / 2
    coverage = float(np.mean(_circle_distance(cx[:, None], cy[None, :], C) < 0))
    return MapDifficulty(bottleneck=bottleneck, path_length=float(length),
                         straight_clearance=float(straight), n_circles=int(C.shape[0]),
                         coverage=coverage)


@dataclass(frozen=True)
class GeneratedMap:
    """One map of a family: circles (at time 0), start, goal, the moving circles as
    (index, (vx, vy)) and the difficulty of the map at time 0.

    walls: for corridor maps, the circle indices of each wall in order along it (the gate
    lies between two consecutive ones). cells, cell_size: for occupancy maps, the occupied
    cells (i along x, j along y; cell (i, j) is [i, i + 1] x [j, j + 1] times cell_size from
    the box corner), which the circles cover. box: the box moving circles bounce in. grid:
    for occupancy_grid maps, the signed-distance grid of the cells (``circles`` is then
    empty; the difficulty is the covering circles'). capsules: for corridor_capsules maps,
    the walls' sides in order (``circles`` then holds the random circles and any side of a
    single circle; ``walls`` is empty). After :func:`scaled`, ``family`` and ``seed`` still
    describe the unscaled map.
    """

    family: MapFamily
    seed: int
    circles: tuple[Circle, ...]
    start: tuple[float, float]
    goal: tuple[float, float]
    moving: tuple[tuple[int, tuple[float, float]], ...]
    difficulty: MapDifficulty
    walls: tuple[tuple[int, ...], ...] = ()
    cells: tuple[tuple[int, int], ...] = ()
    cell_size: float = 0.0
    box: tuple[tuple[float, float], tuple[float, float]] = BOX
    grid: SignedDistanceGrid | None = None
    capsules: tuple[Capsule, ...] = ()

    @property
    def n_static(self) -> int:
        """Number of circles that never move."""
        return len(self.circles) - len(self.moving)

    def scene(self, dt: float = 0.02, u_limit: float = 5.0,
              circle_slots: int | None = None) -> CircleScene | ObstacleScene:
        """The map at time 0 as a :class:`CircleScene` (for ``navigation_setup``); a
        :data:`LAYOUT_FAMILIES` map as an :class:`ObstacleScene` on its :meth:`layout`; a map
        whose family predicts its moving circles as an :class:`ObstacleScene` of
        :meth:`velocity_scene_at` (0) with ``circle_slots`` circle slots (default: its static
        circles) and a moving slot per moving circle."""
        if self.family.predict:
            slots = self.n_static if circle_slots is None else integer(
                "scene.circle_slots", circle_slots, self.n_static)
            told = SceneLayout.of(circles=slots, moving=len(self.moving))
            return ObstacleScene(self.velocity_scene_at(0, dt), self.start, self.goal, dt=dt,
                                 u_limit=u_limit, layout=told)
        layout = self.layout()
        if layout is not None:
            objects = (*self.capsules, *self.circles) + (() if self.grid is None
                                                          else (self.grid,))
            return ObstacleScene(objects, self.start, self.goal, dt=dt, u_limit=u_limit,
                                 layout=layout)
        return CircleScene(self.circles, self.start, self.goal, dt=dt, u_limit=u_limit)

    def layout(self) -> SceneLayout | None:
        """The scene layout of a :data:`LAYOUT_FAMILIES` map (None for circle maps), the same
        for every map of its family: corridor_capsules: a capsule per wall side and room for
        the random circles plus a circle per side; occupancy_grid: the grid's shape."""
        fam = self.family
        if fam.family == "corridor_capsules":
            return SceneLayout.of(capsules=2 * fam.n_gates,
                                  circles=fam.obstacle_count + 2 * fam.n_gates)
        if fam.family == "occupancy_grid":
            return SceneLayout.of(grid=(fam.grid, fam.grid))
        return None

    def scene_at(self, k: int, dt: float) -> tuple[Circle, ...]:
        """The circles at step k (time k dt): each moving circle translates at its velocity
        and bounces off the box edges (elastically, its edge touching the edge); moving
        circles pass through other circles. k = 0 gives ``circles``."""
        k = integer("scene_at.k", k, 0)
        dt = real("scene_at.dt", dt, 0.0, strict=True)
        if k == 0 or not self.moving:
            return self.circles
        out = list(self.circles)
        for i, v in self.moving:
            c = self.circles[i]
            x, y = (_bounce(c.center[a], v[a] * k * dt, self.box[a], c.radius) for a in range(2))
            out[i] = Circle((x, y), c.radius)
        return tuple(out)

    def moving_scene(self, dt: float) -> Callable[[int], tuple[Circle, ...]]:
        """``k -> scene_at(k, dt)``, for ``closed_loop(..., scene=...)``."""
        dt = real("moving_scene.dt", dt, 0.0, strict=True)
        return lambda k: self.scene_at(k, dt)

    def scene_layout(self) -> SceneLayout:
        """The slots of a model that is told how the circles move (:meth:`velocity_scene_at`):
        one circle slot per static circle, one moving slot per moving circle (a
        :data:`LAYOUT_FAMILIES` map, without moving circles: its :meth:`layout`)."""
        own = self.layout()
        if own is not None:
            return own
        return SceneLayout.of(circles=self.n_static, moving=len(self.moving))

    def velocity_scene_at(self, k: int, dt: float) -> tuple[Circle | MovingCircle, ...]:
        """The true scene at step k (time k dt) with the moving circles' velocities, for a
        model built with :meth:`scene_layout`: the static circles as :class:`Circle`, each
        moving circle as a :class:`MovingCircle` at its position of :meth:`scene_at` with its
        velocity at that time (a component's sign flips at each bounce; 0 for an axis on which
        the circle fits the box exactly and stays put). A controller predicts it at c + v t."""
        k = integer("velocity_scene_at.k", k, 0)
        dt = real("velocity_scene_at.dt", dt, 0.0, strict=True)
        now = self.scene_at(k, dt)
        moving = dict(self.moving)
        out: list[Circle | MovingCircle] = [c for i, c in enumerate(now) if i not in moving]
        for i, v in self.moving:
            c0, c = self.circles[i], now[i]
            vx, vy = (v[a] * _bounce_sign(c0.center[a], v[a] * k * dt, self.box[a],
                                          c0.radius) for a in range(2))
            out.append(MovingCircle(c.center, c.radius, (vx, vy)))
        return tuple(out)

    def velocity_scene(self, dt: float) -> Callable[[int], tuple[Circle | MovingCircle, ...]]:
        """``k -> velocity_scene_at(k, dt)``, for ``closed_loop(..., scene=...)`` with a model
        built with :meth:`scene_layout` (the controller is told the velocities; the plant's
        crash check uses the circles' true positions)."""
        dt = real("velocity_scene.dt", dt, 0.0, strict=True)
        return lambda k: self.velocity_scene_at(k, dt)


def _bounce(x0: float, shift: float, span: tuple[float, float], r: float) -> float:
    """Coordinate x0 + shift reflected back into [lo + r, hi - r] (a triangle wave)."""
    lo, width = span[0] + r, span[1] - span[0] - 2 * r
    if width <= 0:
        return x0
    u = np.mod(x0 - lo + shift, 2 * width)
    return float(lo + (u if u <= width else 2 * width - u))


# ------------------------------------------------------------------------------ generators


def _bounce_sign(x0: float, shift: float, span: tuple[float, float], r: float) -> float:
    """The direction of travel (+1, -1) after moving ``shift`` from x0 on the triangle wave of
    :func:`_bounce` (0 when the span leaves no room, or for a circle that does not move): +1
    on its rising half, -1 on its falling half (a bounce point counts as after the bounce)."""
    lo, width = span[0] + r, span[1] - span[0] - 2 * r
    if width <= 0:
        return 0.0
    u = np.mod(x0 - lo + shift, 2 * width)
    return 1.0 if u < width else -1.0


def _gap_ok(C: np.ndarray, c: np.ndarray, r: float, gap: float | np.ndarray) -> bool:
    if not C.shape[0]:
        return True
    return bool(np.all(np.hypot(*(C[:, :2] - c).T) - C[:, 2] - r >= gap))


def _place(rng: np.random.Generator, fam: MapFamily, C: np.ndarray, n: int,
           gaps: np.ndarray, field: str, value: object, box=BOX) -> np.ndarray:
    """Rejection-sample n circles (radius and centre uniform) with edge gap >= ``gaps``
    (per existing circle; min_gap among new ones) and endpoint_clearance to start and goal."""
    ends = np.array([fam.start, fam.goal])
    new = np.zeros((0, 3))
    for _ in range(MAX_DRAWS):
        if new.shape[0] == n:
            break
        r = rng.uniform(*fam.radius_range)
        lo = max(CENTER_RANGE[0], box[0][0] + r)
        hi = min(CENTER_RANGE[1], box[0][1] - r)
        c = rng.uniform(lo, hi, size=2)
        if np.any(np.hypot(*(ends - c).T) - r < fam.endpoint_clearance):
            continue
        if not (_gap_ok(C, c, r, gaps) and _gap_ok(new, c, r, fam.min_gap)):
            continue
        new = np.vstack([new, (c[0], c[1], r)])
    if new.shape[0] < n:
        raise fail(field, value,
                   f"placed only {new.shape[0]} of {n} circles in {MAX_DRAWS} draws: too dense "
                   f"for radius_range = {fam.radius_range}, min_gap = {fam.min_gap:g} and "
                   f"endpoint_clearance = {fam.endpoint_clearance:g}; ask for fewer circles "
                   "or smaller radii or gaps")
    return new


def _spec(fam: MapFamily, seed: int) -> np.ndarray:
    try:
        scene = NavigationScene(start=fam.start, goal=fam.goal, n_obstacles=fam.obstacle_count,
                                corridor_width=fam.corridor_width,
                                radius_range=fam.radius_range,
                                endpoint_clearance=fam.endpoint_clearance,
                                edge_gap=fam.min_gap, seed=seed)
        circles = scene.obstacles()
    except ValueError as exc:
        text = str(exc)
        name = next((n for n in ("start", "goal") if f"NavigationScene.{n} =" in text), None)
        if name is not None:
            raise fail(f"map.{name}", getattr(fam, name), text) from exc
        raise fail("map.n_obstacles", fam.obstacle_count, text) from exc
    return _circle_array(circles)


def _clip_line(p: np.ndarray, d: np.ndarray, box=BOX) -> tuple[float, float]:
    """Parameters [s_lo, s_hi] of the line p + s d inside the box."""
    lo, hi = -np.inf, np.inf
    for a in range(2):
        if abs(d[a]) < 1e-12:
            continue
        s0, s1 = sorted(((box[a][0] - p[a]) / d[a], (box[a][1] - p[a]) / d[a]))
        lo, hi = max(lo, s0), min(hi, s1)
    return float(lo), float(hi)


def _corridor(fam: MapFamily, rng: np.random.Generator):
    """Walls: n_gates lines perpendicular to start -> goal at fractions
    (i + U(-0.15, 0.15)) / (n_gates + 1) of the way, clipped to the box and covered by circles
    of radius radius_range[1] with centres on the line at most 1.5 radii apart (the end ones
    on the box edge), except at one gate: its two flanking circles are corridor_width apart
    edge to edge, its centre uniform on the middle 80 % of the wall where there is room.
    Then n_obstacles random circles (min_gap to each other, max(min_gap, corridor_width) to
    wall circles, endpoint_clearance to start and goal)."""
    p0, p1 = np.array(fam.start), np.array(fam.goal)
    d = p1 - p0
    u = d / np.linalg.norm(d)
    normal = np.array([-u[1], u[0]])
    rw, w = fam.radius_range[1], fam.corridor_width
    walls, C = [], np.zeros((0, 3))
    prev = None
    for i in range(1, fam.n_gates + 1):
        t = (i + rng.uniform(-WALL_JITTER, WALL_JITTER)) / (fam.n_gates + 1)
        p = p0 + t * d
        s_lo, s_hi = _clip_line(p, normal)
        span = w + 2 * rw  # centre distance of the two circles flanking the gate
        g_lo, g_hi = s_lo + span / 2, s_hi - span / 2
        if g_lo > g_hi:
            raise fail("map.corridor_width", w, f"wall {i} is {s_hi - s_lo:.3g} m long: too "
                       f"short for a gate of this width between circles of radius {rw:g}")
        a = 0.1 * (s_hi - s_lo)  # keep gates off the box corners when there is room
        if g_lo + a <= g_hi - a:
            g_lo, g_hi = g_lo + a, g_hi - a
        gate = rng.uniform(g_lo, g_hi)
        a, b = gate - span / 2, gate + span / 2
        left = np.linspace(s_lo, a, int(np.ceil((a - s_lo) / (WALL_SPACING * rw))) + 1)
        right = np.linspace(b, s_hi, int(np.ceil((s_hi - b) / (WALL_SPACING * rw))) + 1)
        s = np.concatenate([left, right])
        centres = p + s[:, None] * normal
        wall = np.column_stack([centres, np.full(s.size, rw)])
        if prev is not None:
            sep = (t - prev) * np.linalg.norm(d) - 2 * rw
            if sep < w:
                raise fail("map.n_gates", fam.n_gates,
                           f"walls {i - 1} and {i} are only {sep:.3g} m apart (edge to edge), "
                           f"less than corridor_width = {w:g}: the start-goal distance "
                           f"{np.linalg.norm(d):.3g} m leaves no room for that many walls")
        prev = t
        walls.append(tuple(range(C.shape[0], C.shape[0] + s.size)))
        C = np.vstack([C, wall])
    _check_ends(fam, C, "wall circle", hint="walls are spread evenly between start and goal: "
                "lower map.n_gates or map.endpoint_clearance, or move start and goal apart")
    gaps = np.full(C.shape[0], max(fam.min_gap, w))
    n = fam.obstacle_count
    C = np.vstack([C, _place(rng, fam, C, n, gaps, "map.n_obstacles", n)])
    return C, tuple(walls)


def _check_ends(fam: MapFamily, C: np.ndarray, what: str, hint: str) -> None:
    for name in ("start", "goal"):
        p = np.array(getattr(fam, name))
        if not C.shape[0]:
            return
        gap = np.hypot(*(C[:, :2] - p).T) - C[:, 2]
        i = int(np.argmin(gap))
        if gap[i] < fam.endpoint_clearance or gap[i] <= 0:
            where = "lies inside" if gap[i] <= 0 else \
                f"lies within endpoint_clearance = {fam.endpoint_clearance:g} of"
            raise fail(f"map.{name}", getattr(fam, name),
                       f"{where} {what} {i} (centre ({C[i, 0]:.3g}, {C[i, 1]:.3g}), radius "
                       f"{C[i, 2]:.3g}); start and goal must be in free space; {hint}")


def automaton_step(occ: np.ndarray) -> np.ndarray:
    """One BARN smoothing step (synchronous, 8 neighbours, outside the grid counts as free):
    a cell with >= 5 occupied neighbours becomes occupied, with <= 1 becomes free, otherwise
    it keeps its state."""
    k = np.ones((3, 3), dtype=int)
    k[1, 1] = 0
    n = ndimage.convolve(occ.astype(int), k, mode="constant", cval=0)
    out = occ.copy()
    out[n >= 5] = True
    out[n <= 1] = False
    return out


def occupancy_grid(fam: MapFamily, rng: np.random.Generator) -> np.ndarray:
    """One draw of the occupancy grid (grid, grid) (bool; [i, j] = cell i along x, j along y):
    random fill, ``smoothing`` automaton steps, then the cells whose circumscribed circle
    comes within endpoint_clearance of start or goal are cleared."""
    G = fam.grid
    h = (BOX[0][1] - BOX[0][0]) / G
    occ = rng.random((G, G)) < fam.fill
    for _ in range(fam.smoothing):
        occ = automaton_step(occ)
    c = BOX[0][0] + (np.arange(G) + 0.5) * h
    for e in (fam.start, fam.goal):
        near = np.hypot(c[:, None] - e[0], c[None, :] - e[1]) - h / np.sqrt(2) \
            < fam.endpoint_clearance
        occ &= ~near
    return occ


def cover_cells(occ: np.ndarray, h: float, origin=(0.0, 0.0)) -> np.ndarray:
    """Circles (n, 3) covering every occupied cell (side h) of a grid, none reaching beyond
    the circumscribed circles of the occupied cells (so at most (sqrt 2 - 1) h / 2 outside
    the occupied cells).

    Candidates: for each occupied cell, the circle at its centre with radius the larger of
    h / sqrt(2) (its circumscribed circle) and the distance to the nearest free cell (outside
    the grid is free; that circle lies inside occupied cells). Greedy set cover (a cell counts
    as covered when its four corners are) picks candidates, most newly covered cells first.
    Memory: n^2 bits for n occupied cells plus blocks of :data:`_CHUNK` distances."""
    idx = np.argwhere(occ)
    if not idx.size:
        return np.zeros((0, 3))
    P = np.asarray(origin) + (idx + 0.5) * h
    pad = np.pad(occ, 1, constant_values=False)
    F = np.asarray(origin) + (np.argwhere(~pad) - 1 + 0.5) * h
    n = P.shape[0]
    R = np.empty(n)
    step = max(1, _CHUNK // max(F.shape[0], 1))
    for a in range(0, n, step):
        Pa = P[a:a + step]
        dx = np.maximum(np.abs(Pa[:, None, 0] - F[None, :, 0]) - h / 2, 0.0)
        dy = np.maximum(np.abs(Pa[:, None, 1] - F[None, :, 1]) - h / 2, 0.0)
        R[a:a + step] = np.maximum(np.hypot(dx, dy).min(axis=1), h / np.sqrt(2))
    corners = P[:, None, :] + h / 2 * np.array([[-1, -1], [-1, 1], [1, -1], [1, 1]])
    M = np.empty((n, n), dtype=bool)  # M[c, q]: candidate c covers cell q
    step = max(1, _CHUNK // (4 * n))
    for a in range(0, n, step):
        Pa = P[a:a + step]
        far = np.hypot(Pa[:, None, None, 0] - corners[None, :, :, 0],
                       Pa[:, None, None, 1] - corners[None, :, :, 1]).max(axis=2)
        M[a:a + step] = far <= R[a:a + step, None] + 1e-9 * h
    todo = np.ones(n, dtype=bool)
    gain = M.sum(axis=1)  # cells still to cover that each candidate covers
    chosen = []
    while todo.any():
        c = int(np.argmax(gain))
        chosen.append(c)
        new = todo & M[c]
        todo &= ~M[c]
        gain -= M[:, new].sum(axis=1)
    return np.column_stack([P[chosen], R[chosen]])


def _occupancy(fam: MapFamily, rng: np.random.Generator):
    h = (BOX[0][1] - BOX[0][0]) / fam.grid
    four = ndimage.generate_binary_structure(2, 1)

    def cell(p):
        return tuple(np.clip(((np.array(p) - BOX[0][0]) // h).astype(int), 0, fam.grid - 1))

    need = max(fam.min_gap / 2, 0.0)
    for _ in range(MAX_MAPS):
        occ = occupancy_grid(fam, rng)
        lab, _ = ndimage.label(~occ, structure=four)  # BARN: flood fill of the free cells
        if lab[cell(fam.start)] == 0 or lab[cell(fam.start)] != lab[cell(fam.goal)]:
            continue
        C = cover_cells(occ, h)
        d = difficulty(C, fam.start, fam.goal)
        if d.bottleneck > 0 and d.bottleneck >= need:
            return C, tuple(map(tuple, np.argwhere(occ).tolist())), d
    raise fail("map.fill", fam.fill,
               f"none of {MAX_MAPS} occupancy grids (grid = {fam.grid}, smoothing = "
               f"{fam.smoothing}) linked start and goal by a passage at least min_gap = "
               f"{fam.min_gap:g} m wide; lower fill or min_gap, or change smoothing")


def _movers(fam: MapFamily, rng: np.random.Generator, C: np.ndarray, free: list[int]):
    """Pick the moving circles: free-standing circles (``free``) drawn at random first, then
    extra circles placed like random ones; each gets speed ``fam.speed`` in a uniform
    direction. Returns the circles (extras appended) and ((index, velocity), ...)."""
    k = min(fam.moving, len(free))
    chosen = sorted(int(i) for i in rng.choice(free, size=k, replace=False)) if k else []
    extra = fam.moving - k
    if extra:
        M = _place(rng, fam, C, extra, np.full(C.shape[0], fam.min_gap), "map.moving",
                   fam.moving)
        chosen += list(range(C.shape[0], C.shape[0] + extra))
        C = np.vstack([C, M])
    angles = rng.uniform(0.0, 2 * np.pi, fam.moving)
    return C, tuple((i, (float(fam.speed * np.cos(a)), float(fam.speed * np.sin(a))))
                    for i, a in zip(chosen, angles, strict=True))


def generate(family: MapFamily, seed: int) -> GeneratedMap:
    """The map of ``family`` for ``seed`` (deterministic): the circles from
    ``np.random.default_rng(seed)`` (the spec family: ``NavigationScene(seed=seed, ...)``),
    then ``family.moving`` moving circles from a generator spawned from it (so the map at
    time 0 does not depend on ``moving`` beyond added circles): free-standing circles (spec:
    the random ones, not the gate pair; corridor: the random ones, not wall circles) drawn at
    random first; when more are asked for (always for occupancy) the rest are extra circles
    appended like random ones (radius in radius_range, min_gap to every circle,
    endpoint_clearance to start and goal). Each moves at speed ``family.speed`` in a uniform
    random direction. The difficulty is that of the map at time 0.

    A start or goal inside (or, for generated circles, within endpoint_clearance of) an
    obstacle raises ValueError naming map.start / map.goal; nothing is moved silently.
    Maps are cached (the same object for the same family and seed)."""
    if not isinstance(family, MapFamily):
        raise fail("map", family, "must be a MapFamily")
    return _generate(family, integer("map.seed", seed, 0))


@lru_cache(maxsize=256)
def _generate(family: MapFamily, seed: int) -> GeneratedMap:
    rng = np.random.default_rng(seed)
    walls: tuple[tuple[int, ...], ...] = ()
    cells: tuple[tuple[int, int], ...] = ()
    diff = None
    if family.family == "spec":
        C = _spec(family, seed)
    elif family.family in ("corridor", "corridor_capsules"):
        C, walls = _corridor(family, rng)
    else:
        C, cells, diff = _occupancy(family, rng)
    grid = None
    if family.family == "occupancy_grid":
        if not cells:
            raise fail("map.fill", family.fill, "drew a map without an occupied cell; the "
                       "occupancy_grid family needs one (raise fill)")
        h = (BOX[0][1] - BOX[0][0]) / family.grid
        occ = np.zeros((family.grid, family.grid), dtype=bool)
        occ[tuple(np.array(cells).T)] = True
        grid = OccupancyMap(occ, h, (BOX[0][0], BOX[1][0])).signed_distance()
    for name in ("start", "goal"):
        p = np.array(getattr(family, name))
        inside: np.ndarray | list[int] = []
        if C.shape[0]:
            inside = np.flatnonzero(np.hypot(*(C[:, :2] - p).T) <= C[:, 2])
        if len(inside):
            i = int(inside[0])
            raise fail(f"map.{name}", getattr(family, name),
                       f"lies inside obstacle {i} (centre ({C[i, 0]:.3g}, {C[i, 1]:.3g}), "
                       f"radius {C[i, 2]:.3g}); start and goal must be in free space")
    moving: tuple[tuple[int, tuple[float, float]], ...] = ()
    n = C.shape[0]
    if family.moving:
        free = {"spec": list(range(2, n)), "occupancy": []}.get(
            family.family, sorted(set(range(n)) - {i for w in walls for i in w}))
        C, moving = _movers(family, rng.spawn(1)[0], C, free)
    if diff is None or C.shape[0] > n:
        diff = difficulty(C, family.start, family.goal)
    circles = () if grid is not None else tuple(
        Circle((float(x), float(y)), float(r)) for x, y, r in C)
    capsules: tuple[Capsule, ...] = ()
    if family.family == "corridor_capsules":
        capsules, single = _wall_capsules(C, walls)
        on_walls = {i for w in walls for i in w}
        circles = tuple(circles[i] for i in single) + tuple(
            c for i, c in enumerate(circles) if i not in on_walls)
        walls = ()
    return GeneratedMap(family=family, seed=seed, circles=circles, start=family.start,
                        goal=family.goal, moving=moving, difficulty=diff, walls=walls,
                        cells=cells, cell_size=(BOX[0][1] - BOX[0][0]) / family.grid
                        if cells else 0.0, grid=grid, capsules=capsules)


def _wall_capsules(C: np.ndarray, walls) -> tuple[tuple[Capsule, ...], list[int]]:
    """Each wall's two sides (the circles before and after its gate, the widest gap between
    consecutive centres) as capsules through their first and last centres; the indices of
    sides of a single circle, which stay circles."""
    out, single = [], []
    for w in walls:
        idx = np.array(w)
        gap = np.hypot(*np.diff(C[idx, :2], axis=0).T)
        k = int(np.argmax(gap)) + 1
        for side in (idx[:k], idx[k:]):
            if side.size == 1:
                single.append(int(side[0]))
                continue
            a, b = C[side[0]], C[side[-1]]
            out.append(Capsule((float(a[0]), float(a[1])), (float(b[0]), float(b[1])),
                               float(a[2])))
    return tuple(out), single


def scaled(scene_or_map, factor: float):
    """A map or scene scaled by ``factor`` about the origin: circles (centres and radii),
    start, goal, and for a :class:`GeneratedMap` also velocities, box, grid (origin,
    resolution and distances) and the difficulty's lengths. GeneratedMap -> GeneratedMap;
    CircleScene or NavigationScene -> CircleScene, ObstacleScene -> ObstacleScene (every
    obstacle scaled, its layout kept; dt and u_limit unchanged); a sequence of circles ->
    tuple of circles."""
    f = real("scaled.factor", factor, 0.0, strict=True)

    def circ(cs) -> tuple[Circle, ...]:
        return tuple(Circle((x * f, y * f), r * f) for x, y, r in _circle_array(cs))

    def pt(p) -> tuple[float, float]:
        return (float(p[0]) * f, float(p[1]) * f)

    obj = scene_or_map
    if isinstance(obj, GeneratedMap):
        d = obj.difficulty
        diff = replace(d, bottleneck=d.bottleneck * f, path_length=d.path_length * f,
                       straight_clearance=d.straight_clearance * f)
        return replace(obj, circles=circ(obj.circles), start=pt(obj.start), goal=pt(obj.goal),
                       moving=tuple((i, pt(v)) for i, v in obj.moving), difficulty=diff,
                       cell_size=obj.cell_size * f, box=(pt(obj.box[0]), pt(obj.box[1])),
                       grid=None if obj.grid is None else _scaled_object(obj.grid, f),
                       capsules=tuple(_scaled_object(c, f) for c in obj.capsules))
    if isinstance(obj, ObstacleScene):
        return ObstacleScene(tuple(_scaled_object(o, f) for o in obj.objects), pt(obj.start),
                             pt(obj.goal), dt=obj.dt, u_limit=obj.u_limit,
                             layout=obj.scene_layout)
    if isinstance(obj, CircleScene | NavigationScene):
        return CircleScene(circ(obj.obstacles()), pt(obj.start), pt(obj.goal), dt=obj.dt,
                           u_limit=obj.u_limit)
    if isinstance(obj, Sequence) and not isinstance(obj, str):
        return circ(obj)
    raise fail("scaled.scene_or_map", type(obj).__name__,
               "must be a GeneratedMap, CircleScene, NavigationScene, ObstacleScene or a "
               "sequence of circles")


def _scaled_object(obj, f: float):
    """One obstacle of a scene scaled by ``f`` about the origin (a half-plane's normal kept)."""
    if isinstance(obj, SignedDistanceGrid):
        return SignedDistanceGrid(obj.values * f, (obj.origin[0] * f, obj.origin[1] * f),
                                  obj.resolution * f)
    if isinstance(obj, MovingCircle):
        (cx, cy), (vx, vy) = obj.center, obj.velocity
        return MovingCircle((cx * f, cy * f), obj.radius * f, (vx * f, vy * f))
    if isinstance(obj, HalfSpace):
        return HalfSpace(obj.normal, obj.offset * f)
    if isinstance(obj, Capsule):
        return Capsule(tuple(c * f for c in obj.a), tuple(c * f for c in obj.b), obj.radius * f)
    (x, y, r), = _circle_array([obj])
    return Circle((x * f, y * f), r * f)

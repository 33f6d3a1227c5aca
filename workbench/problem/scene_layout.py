"""How many run-time obstacles of each kind a model holds, and the scene vector of a scene.

A :class:`SceneLayout` fixes, when a model is built, the position dimension, the slots of each
kind of :data:`~workbench.problem.scene_kinds.SCENE_KINDS` and the shape of an optional
signed-distance grid. The scene input is the kinds' blocks in registration order, then the
grid; every compiled kernel and solver takes it as an input, so any scene that fits the layout
(other obstacles, moved ones, a new grid of the same shape) builds nothing. Unused slots are
inert. A scene is given as a sequence of obstacle objects (:class:`Circle`, :class:`Sphere`,
:class:`HalfSpace`, :class:`Capsule`, :class:`MovingCircle`, :class:`SignedDistanceGrid`, in
any order; ``(x, y, r)`` triples and (n, 3) arrays are circles) or as a flat scene vector.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

import workbench.problem.sdf_grid as sdf_grid
from workbench.problem.obstacles import Circle, HForm, slot_margins
from workbench.problem.scene_kinds import SCENE_KINDS, SceneKind
from workbench.problem.sdf_grid import SignedDistanceGrid
from workbench.validation import as_array, fail, integer

MAX_SLOTS = 10**4


@dataclass(frozen=True)
class Block:
    """One kind's slots in the scene vector: entries [start, start + count * width)."""

    kind: SceneKind
    count: int
    start: int
    width: int

    @property
    def stop(self) -> int:
        return self.start + self.count * self.width


@dataclass(frozen=True)
class SceneLayout:
    """``dim``: position dimension (2 or 3); ``slots``: (kind name, count) pairs (each kind at
    most once, count >= 1); ``grid``: (nx, ny) of a signed-distance grid or None (2-D only)."""

    dim: int = 2
    slots: tuple[tuple[str, int], ...] = ()
    grid: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        integer("SceneLayout.dim", self.dim, 2, 3)
        seen = set()
        norm = []
        for i, item in enumerate(self.slots):
            if not isinstance(item, tuple | list) or len(item) != 2:
                raise fail(f"SceneLayout.slots[{i}]", item, "expected (kind name, count)")
            name, count = item
            kind = SCENE_KINDS.named(name)
            if self.dim not in kind.dims:
                raise fail(f"SceneLayout.slots[{i}]", name,
                           f"a {name} slot needs a position of dimension {kind.dims}; "
                           f"this layout's is {self.dim}")
            if name in seen:
                raise fail(f"SceneLayout.slots[{i}]", name, "each kind at most once")
            seen.add(name)
            norm.append((name, integer(f"SceneLayout.slots[{i}] count", count, 1, MAX_SLOTS)))
        order = list(SCENE_KINDS)
        object.__setattr__(self, "slots", tuple(sorted(norm, key=lambda s: order.index(s[0]))))
        if self.grid is not None:
            if self.dim != 2:
                raise fail("SceneLayout.grid", self.grid, "a signed-distance grid is 2-D")
            g = tuple(integer("SceneLayout.grid", n, 2) for n in self.grid)
            if len(g) != 2 or g[0] * g[1] > sdf_grid.MAX_GRID_NODES:
                raise fail("SceneLayout.grid", self.grid, "(nx, ny), nx, ny >= 2, at most "
                           f"{sdf_grid.MAX_GRID_NODES} nodes")
            object.__setattr__(self, "grid", g)

    @classmethod
    def of(cls, dim: int = 2, grid: tuple[int, int] | None = None, **counts: int) -> SceneLayout:
        """``SceneLayout.of(circles=30, capsules=4, grid=(200, 200))``; zero counts left out."""
        return cls(dim, tuple((k, n) for k, n in counts.items() if n), grid)

    @classmethod
    def fitting(cls, scene, field: str = "scene") -> SceneLayout:
        """The smallest layout that holds the obstacles ``scene`` (a sequence, as
        :meth:`vector` takes): one slot per obstacle of each kind, the grid's shape; the
        position dimension of the obstacles (2 when none says)."""
        counts: dict[str, int] = {}
        grid: tuple[int, int] | None = None
        dims: set[int] = set()
        for i, obj in enumerate(_items(scene, field)):
            if isinstance(obj, SignedDistanceGrid):
                if grid is not None:
                    raise fail(f"{field}[{i}]", obj, "a scene holds at most one grid")
                grid, dims = obj.shape, dims | {2}
                continue
            kind = _kind_of(obj, f"{field}[{i}]")
            counts[kind.name] = counts.get(kind.name, 0) + 1
            d = _dim_of(obj)
            dims |= set() if d is None else {d}
        if len(dims) > 1:
            raise fail(field, sorted(dims), "obstacles of one scene share one position "
                       "dimension (2 or 3)")
        return cls.of(dims.pop() if dims else 2, grid, **counts)

    def blocks(self) -> list[Block]:
        out, start = [], 0
        for name, count in self.slots:
            kind = SCENE_KINDS[name]
            out.append(Block(kind, count, start, kind.width(self.dim)))
            start = out[-1].stop
        return out

    def count(self, name: str) -> int:
        return dict(self.slots).get(name, 0)

    @property
    def grid_start(self) -> int:
        b = self.blocks()
        return b[-1].stop if b else 0

    @property
    def size(self) -> int:
        g = self.grid
        return self.grid_start + (sdf_grid.HEADER + g[0] * g[1] if g else 0)

    @property
    def circles_only(self) -> bool:
        """Only circle slots: the scene vector of the circle scenes (scene_capacity)."""
        return self.grid is None and all(k == "circles" for k, _ in self.slots)

    @property
    def n_margins(self) -> int:
        return sum(n for _, n in self.slots) + (1 if self.grid else 0)

    # ------------------------------------------------------------------ margins

    def symbol(self) -> ca.SX:
        return ca.SX.sym("scene", self.size)

    def margins(self, p, scene: ca.SX, h_form: HForm = "squared", inflation: float = 0.0):
        """Margins of position ``p`` (dim SX entries), one per slot then the grid's."""
        out = []
        for b in self.blocks():
            if b.kind.name == "circles":
                out.append(slot_margins(p, scene[b.start:b.stop], h_form, inflation))
                continue
            for i in range(b.count):
                s = scene[b.start + i * b.width: b.start + (i + 1) * b.width]
                out.append(b.kind.sx(p, s, h_form, inflation, self.dim))
        if self.grid:
            out.append(sdf_grid.grid_sx(p, scene[self.grid_start:], self.grid, inflation))
        return ca.vertcat(*out) if out else ca.SX(0, 1)

    def numpy_margins(self, P, v, h_form: str = "squared", inflation: float = 0.0):
        """The same margins in NumPy at positions P (N, dim) for a scene vector v: (N, nh)."""
        P = np.atleast_2d(np.asarray(P, dtype=float))
        v = np.asarray(v, dtype=float)
        out = []
        for b in self.blocks():
            S = v[b.start:b.stop].reshape(b.count, b.width)
            out.append(b.kind.numpy(P, S, h_form, inflation, self.dim))
        if self.grid:
            out.append(sdf_grid.grid_numpy(P, v[self.grid_start:], self.grid,
                                           inflation)[:, None])
        return np.hstack(out) if out else np.zeros((P.shape[0], 0))

    # ------------------------------------------------------------------ values

    def inert(self) -> np.ndarray:
        """The scene with every slot unused (and an unused grid)."""
        parts = [np.tile(b.kind.inert(self.dim), b.count) for b in self.blocks()]
        if self.grid:
            parts.append(sdf_grid.inert_row(self.grid))
        return np.concatenate(parts) if parts else np.zeros(0)

    def valid(self, v: np.ndarray) -> bool:
        """Whether a finite flat vector of the right size is a scene of this layout (fast)."""
        for b in self.blocks():
            if not b.kind.valid(v[b.start:b.stop].reshape(b.count, b.width), self.dim).all():
                return False
        return not self.grid or v[self.grid_start + 2] > 0

    def check(self, field: str, v: np.ndarray) -> None:
        """Refuse a finite flat vector with an invalid slot, naming the first one."""
        for b in self.blocks():
            S = v[b.start:b.stop].reshape(b.count, b.width)
            ok = b.kind.valid(S, self.dim)
            if not ok.all():
                i = int(np.flatnonzero(~ok)[0])
                lo = b.start + i * b.width
                raise fail(f"{field}[{lo}:{lo + b.width}] ({b.kind.name} slot {i})", S[i],
                           f"every {b.kind.name} slot must be {b.kind.rule}")
        if self.grid:
            sdf_grid.check_row(field, v[self.grid_start:])

    def vector(self, scene, field: str = "scene") -> np.ndarray:
        """The flat scene vector of ``scene`` (see the module), validated; a flat vector of
        the layout's size is checked and copied."""
        if isinstance(scene, np.ndarray) and scene.ndim == 1:
            v = as_array(field, scene, (self.size,))
            self.check(field, v)
            return v.copy()
        items = _items(scene, field)
        v = self.inert()
        used = {b.kind.name: 0 for b in self.blocks()}
        blocks = {b.kind.name: b for b in self.blocks()}
        grid_seen = False
        for i, obj in enumerate(items):
            f = f"{field}[{i}]"
            if isinstance(obj, SignedDistanceGrid):
                if self.grid is None:
                    raise fail(f, "a SignedDistanceGrid", "this model has no grid "
                               "(SceneLayout.grid)")
                if obj.shape != self.grid or grid_seen:
                    raise fail(f, f"a grid of shape {obj.shape}", f"one grid of shape "
                               f"{self.grid} (the model's SceneLayout.grid)")
                v[self.grid_start:] = obj.row()
                grid_seen = True
                continue
            kind = _kind_of(obj, f)
            b = blocks.get(kind.name)
            dim = _dim_of(obj)
            if dim is not None and dim != self.dim:
                raise fail(f, obj, f"has {dim} coordinates; this scene's positions have "
                           f"{self.dim}")
            if b is None or used[kind.name] >= b.count:
                room = 0 if b is None else b.count
                raise fail(field, f"{used.get(kind.name, 0) + 1} or more {kind.name}",
                           f"this model was built with room for {room} "
                           f"(SceneLayout.slots)")
            lo = b.start + used[kind.name] * b.width
            v[lo:lo + b.width] = kind.to_row(obj)
            used[kind.name] += 1
        return v

    def translate(self, v: np.ndarray, origin: np.ndarray) -> np.ndarray:
        """The scene seen from ``origin`` (positions minus origin); unused slots kept."""
        out = np.array(v, dtype=float)
        o = np.asarray(origin, dtype=float)
        for b in self.blocks():
            S = out[b.start:b.stop].reshape(b.count, b.width)
            far = ~_in_use(b, S, self.dim)
            T = b.kind.translate(S, o)
            T[far] = S[far]
            out[b.start:b.stop] = T.ravel()
        if self.grid:
            out[self.grid_start:self.grid_start + 2] -= o
        return out

    def objects(self, v) -> list:
        """The obstacles of a scene vector (unused slots left out)."""
        v = np.asarray(v, dtype=float)
        out: list = []
        for b in self.blocks():
            S = v[b.start:b.stop].reshape(b.count, b.width)
            for row in S[_in_use(b, S, self.dim)]:
                out.append(_object(b.kind.name, row, self.dim))
        if self.grid:
            row = v[self.grid_start:]
            if not np.all(row[sdf_grid.HEADER:] == 1e8):
                out.append(SignedDistanceGrid.from_row(row, self.grid))
        return out

    @property
    def moves(self) -> bool:
        """Whether the layout has moving-circle slots (its scenes change over a horizon)."""
        return self.count("moving") > 0

    def predicted_sx(self, scene: ca.SX, t: ca.SX | float) -> ca.SX:
        """The scene symbol at time ``t`` (an SX scalar or a number) from now: each moving
        slot's centre replaced by c + v t (an unused slot has v = 0 and stays put); ``scene``
        itself when the layout has no moving slot."""
        b = next((b for b in self.blocks() if b.kind.name == "moving"), None)
        if b is None:
            return scene
        parts = [scene[:b.start]] if b.start else []
        for i in range(b.count):
            lo = b.start + i * b.width
            parts += [scene[lo:lo + 2] + t * scene[lo + 3:lo + 5], scene[lo + 2:lo + b.width]]
        if b.stop < self.size:
            parts.append(scene[b.stop:])
        return ca.vertcat(*parts)

    def predicted(self, v: np.ndarray, t: float) -> np.ndarray:
        """The scene at time ``t`` from now: moving circles at c + v t (the rest as is)."""
        b = next((b for b in self.blocks() if b.kind.name == "moving"), None)
        if b is None or t == 0:
            return v
        out = np.array(v, dtype=float)
        S = out[b.start:b.stop].reshape(b.count, b.width)
        S[:, :2] += t * S[:, 3:5]
        return out


def _in_use(b: Block, S: np.ndarray, dim: int) -> np.ndarray:
    return ~np.all(S == np.array(b.kind.inert(dim)), axis=1)


def _object(name: str, row: np.ndarray, dim: int):
    from workbench.problem.scene_kinds import Capsule, HalfSpace, MovingCircle, Sphere

    r = [float(x) for x in row]
    if name == "circles":
        return Circle((r[0], r[1]), r[2])
    if name == "moving":
        return MovingCircle((r[0], r[1]), r[2], (r[3], r[4]))
    if name == "spheres":
        return Sphere((r[0], r[1], r[2]), r[3])
    if name == "halfspaces":
        return HalfSpace(tuple(r[:dim]), r[dim])
    if name == "capsules":
        return Capsule(tuple(r[:dim]), tuple(r[dim:2 * dim]), r[2 * dim])
    return (name, tuple(r))


def _dim_of(obj) -> int | None:
    for attr in ("center", "normal", "a"):
        if hasattr(obj, attr):
            return len(getattr(obj, attr))
    return None


def _kind_of(obj, field: str) -> SceneKind:
    for kind in SCENE_KINDS.values():
        if kind.objects and isinstance(obj, kind.objects):
            return kind
    if isinstance(obj, str | bytes) or np.shape(obj) != (3,):
        names = ", ".join(c.__name__ for k in SCENE_KINDS.values() for c in k.objects)
        raise fail(field, obj, f"expected an obstacle ({names}, SignedDistanceGrid) or an "
                   "(x, y, radius) triple")
    r = as_array(field, obj, (3,))[2]
    if not r > 0:
        raise fail(field, obj, "the radius (third entry) must be > 0")
    return SCENE_KINDS["circles"]


def _items(scene, field: str) -> list:
    if scene is None:
        raise fail(field, None, "no scene given; expected a sequence of obstacles or a flat "
                   "scene vector")
    if isinstance(scene, np.ndarray):
        if scene.ndim != 2 or scene.shape[1] != 3:
            raise fail(field, f"an array of shape {scene.shape}", "an array scene has shape "
                       "(n, 3), one row (x, y, radius) per circle (or is a flat scene vector)")
        return [Circle((float(a), float(b)), float(r)) if r > 0 else (a, b, r)
                for a, b, r in scene]
    if isinstance(scene, str | bytes | dict) or not hasattr(scene, "__iter__"):
        raise fail(field, scene, "expected a sequence of obstacles or a flat scene vector")
    items = list(scene)
    return [Circle((float(o[0]), float(o[1])), float(o[2]))
            if not hasattr(o, "__dataclass_fields__") and np.shape(o) == (3,)
            and not isinstance(o, str | bytes) and np.all(np.isfinite(np.asarray(o, float)))
            and float(o[2]) > 0 else o for o in items]


def anchor_points(layout: SceneLayout, v) -> np.ndarray:
    """Points (m, dim) that place the used obstacles of a scene vector: centres, capsule ends,
    the point of each half-space's boundary nearest the origin, the grid's corners (unused
    slots left out)."""
    pts: list = []
    for obj in layout.objects(v):
        if isinstance(obj, SignedDistanceGrid):
            x0, x1, y0, y1 = obj.extent()
            pts += [(x0, y0), (x1, y1)]
        elif hasattr(obj, "center"):
            pts.append(obj.center)
        elif hasattr(obj, "normal"):
            pts.append(tuple(obj.offset * np.asarray(obj.normal)))
        elif hasattr(obj, "a"):
            pts += [obj.a, obj.b]
    return np.array(pts, dtype=float).reshape(-1, layout.dim)

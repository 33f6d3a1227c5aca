"""The float32 kernels' local frame: positions relative to the current state.

Float32 resolves about 7 significant digits, so a map far from the origin (a scene shifted by
1e5 m, or UTM coordinates near 4e6 m) leaves centimetres or metres of resolution where the
crash test needs micrometres. A float32 sampler therefore runs its rollouts in a frame whose
origin is the position of the batch's start state: it subtracts that position from the
position states of every start (real and nominal), from the goal's position in the cost
parameter and from the obstacles of the scene (circle centres; with a scene layout every
kind's positions, :meth:`~workbench.problem.scene_layout.SceneLayout.translate`). The
samples' costs, crash flags and controls do not change under that translation when the
problem is translation invariant, which :func:`local_frame` checks on the problem's own
functions (dynamics, margins, q, phi) before the frame is used.

The goal stays where it is: a goal beyond :data:`GOAL_LIMIT32` from the start leaves float32
too coarse to tell the samples' costs apart, and :func:`check_goal` refuses the batch.

A problem that is not translation invariant (obstacles compiled into the model, costs of
absolute positions, no declared position) runs float32 only where its coordinates are small:
:func:`check_coordinates` refuses start states and obstacles beyond :data:`COORDINATE_LIMIT32`.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from itertools import pairwise

import numpy as np

from workbench.problem.obstacles import SLOT
from workbench.problem.scene_layout import SceneLayout, anchor_points
from workbench.sampling.problem import SamplingProblem
from workbench.validation import fail

# Largest coordinate magnitude (m) a float32 sampler accepts without a local frame. The guard
# band is set from the float32 drift of the margins with positions up to ~20 m, with a factor
# 11 to spare; the drift grows with the coordinates' magnitude (their float32 spacing, 7.6e-6 m
# at 100 m), so 100 m keeps the band's assumption with a factor 2.
COORDINATE_LIMIT32 = 100.0

# Largest distance (m, per axis) from the start to the goal a float32 batch accepts. Costs of
# a far goal grow with its distance squared, and float32 resolves positions there only to its
# spacing (7.8e-3 m at 1e5 m, 1 m at 1e7 m). Measured on the navigation map (N 1024, T 100):
# the float32 applied control is float64's to 2e-7 (relative) with the goal up to 1e6 m away,
# and off by 1.4 at 1e7 m; 1e5 m leaves a factor 10.
GOAL_LIMIT32 = 1e5

_CARRY_STATES = ("x", "x_nom")  # carry fields holding a state, shifted with the frame
_SHIFT = 40.0  # m: shifts tried by the invariance check
_RTOL = 1e-9  # its relative tolerance per element, scaled by (1 + |shift|)^2


@dataclass(frozen=True)
class LocalFrame:
    """Which entries move with a translation of the position: state indices ``state``, the
    same axes' indices ``param`` in the cost parameter p (empty: p does not move) and whether
    the scene's obstacles move (circle centres: axes ``state[0]``, ``state[1]``; with a scene
    ``layout``, its translation along every axis of ``state``)."""

    state: tuple[int, ...]
    param: tuple[int, ...]
    scene: bool
    layout: SceneLayout | None = None
    # the state's position entries as a slice when they are adjacent (faster than a list)
    _sel: slice | list[int] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        st = self.state
        adjacent = all(b == a + 1 for a, b in pairwise(st))
        object.__setattr__(self, "_sel", slice(st[0], st[-1] + 1) if adjacent else list(st))

    def origin(self, carry: dict) -> np.ndarray:
        """The frame's origin: the position of the first start state of a batch."""
        x = np.asarray(carry["x"], dtype=float)
        return (x if x.ndim == 1 else x[0])[self._sel].copy()

    def carry(self, carry: dict, o: np.ndarray) -> dict:
        """The start states with the origin subtracted from their positions (copies)."""
        out = dict(carry)
        for name in _CARRY_STATES:
            if name in carry:
                x = np.array(carry[name], dtype=float)
                x[..., self._sel] -= o
                out[name] = x
        return out

    def consts(self, consts: dict[str, np.ndarray], o: np.ndarray) -> dict[str, np.ndarray]:
        """The kernel constants with the goal's position and the circle centres shifted."""
        out = dict(consts)
        if self.param:
            p = np.array(consts["p"], dtype=float)
            p[list(self.param)] -= o
            out["p"] = p
        if self.scene:
            out["scene"] = self.scene_at(consts["scene"], -o)
        return out

    def scene_at(self, scene: np.ndarray, shift: np.ndarray) -> np.ndarray:
        """The scene with its obstacles moved by ``shift`` (a copy)."""
        if self.layout is not None:
            return self.layout.translate(scene, -np.asarray(shift, dtype=float))
        s = np.array(scene, dtype=float).reshape(-1, SLOT)
        s[:, :2] += shift[:2]
        return s.reshape(-1)


class FrameConsts:
    """:meth:`LocalFrame.consts` into buffers reused from call to call (one set per calling
    thread and constants): a kernel then sees the same arrays as last time and skips checking
    them again, which keeps the frame's cost per batch to a few microseconds."""

    _KEEP = 8  # buffer sets kept (threads x constants)

    def __init__(self, frame: LocalFrame):
        self.frame = frame
        self._sets: dict[int, tuple] = {}

    def __call__(self, consts: dict[str, np.ndarray], o: np.ndarray) -> dict[str, np.ndarray]:
        """The constants with the origin ``o`` subtracted (valid until the next call from
        this thread)."""
        tid = threading.get_ident()
        got = self._sets.get(tid)
        p0, s0 = consts["p"], consts["scene"]
        if got is None or got[0] is not p0 or got[1] is not s0:
            if len(self._sets) >= self._KEEP:
                self._sets.pop(next(iter(self._sets)))
            out = self.frame.consts(consts, o)
            # (source, destination) views of the entries that move
            moves = []
            if self.frame.param:
                moves.append((p0[list(self.frame.param)], out["p"], list(self.frame.param)))
            circles = self.frame.scene and self.frame.layout is None
            self._sets[tid] = (p0, s0, out, moves,
                               (s0.reshape(-1, SLOT)[:, :2], out["scene"].reshape(-1, SLOT)[:, :2])
                               if circles else None)
            return out
        _, _, out, moves, scene = got
        for src, dst, idx in moves:
            dst[idx] = src - o
        if scene is not None:
            np.subtract(scene[0], o[:2], out=scene[1])
        elif self.frame.scene:
            out["scene"][:] = self.frame.scene_at(s0, -o)
        return out


def check_goal(frame: LocalFrame, consts: dict[str, np.ndarray]) -> None:
    """Refuse a float32 batch whose goal position (in the frame's translated constants) lies
    beyond :data:`GOAL_LIMIT32` from the start on some axis."""
    p = consts["p"]
    far = max((abs(float(p[i])) for i in frame.param), default=0.0)
    if far > GOAL_LIMIT32:
        raise fail("goal (position relative to the state)", far,
                   f"must be at most {GOAL_LIMIT32:g} m per axis for precision 'float32': "
                   "float32 resolves positions that far only to "
                   f"{float(np.spacing(np.float32(far))):.2g} m, too coarse to tell the "
                   "samples' costs apart; use precision 'float64' or a nearer waypoint")


def _close(a, b, shift: float) -> bool:
    a, b = np.asarray(a, dtype=float).ravel(), np.asarray(b, dtype=float).ravel()
    fin = np.isfinite(a) & np.isfinite(b)
    if not np.array_equal(fin, np.isfinite(a) | np.isfinite(b)):
        return False
    tol = _RTOL * (1.0 + shift) ** 2 * np.maximum(np.maximum(np.abs(a), np.abs(b)), 1.0)
    return bool(np.all(np.abs(a[fin] - b[fin]) <= tol[fin]))


def _invariant(sp: SamplingProblem, frame: LocalFrame, rng: np.random.Generator) -> bool:
    """Whether dynamics, margins and costs are unchanged (the next state moved by the shift)
    under random shifts of the frame's entries, at random states, controls and goals."""
    f, m = sp.functions(), sp.model
    scene = np.asarray(m.scene_value, dtype=float)
    idx = list(frame.state)
    for _ in range(4):
        x = rng.uniform(-5.0, 5.0, m.nx)
        u = rng.uniform(-1.0, 1.0, m.nu)
        p = rng.uniform(-5.0, 5.0, sp.n_p)
        d = rng.uniform(-_SHIFT, _SHIFT, len(idx))
        xs, ps, ss = x.copy(), p.copy(), scene.copy()
        xs[idx] += d
        if frame.param:
            ps[list(frame.param)] += d
        if frame.scene:
            ss = frame.scene_at(scene, d)
        nxt, nxt_s = np.asarray(f["dyn"](x, u, scene)), np.asarray(f["dyn"](xs, u, ss))
        nxt_s[idx] -= d[:, None]
        shift = float(np.max(np.abs(d)))
        if not (_close(nxt, nxt_s, shift) and _close(f["margins"](x, scene),
                                                     f["margins"](xs, ss), shift)
                and _close(f["q"](x, p), f["q"](xs, ps), shift)
                and _close(f["phi"](x, p), f["phi"](xs, ps), shift)):
            return False
    return True


def local_frame(sp: SamplingProblem) -> LocalFrame | None:
    """The problem's local frame, or None when it has none: the model declares no position,
    or dynamics, margins or costs change under a translation of the position (with the goal's
    position in p, which is tried when p has the state's size, and the scene's obstacles).
    Checked numerically at random points of a fixed seed (relative tolerance 1e-9)."""
    m = sp.model
    if m.position is None:
        return None
    layout = m.scene_layout
    if layout is not None and layout.dim != len(m.position):
        return None
    scene = m.scene_capacity > 0 or layout is not None
    tries = [LocalFrame(m.position, m.position, scene, layout)] if sp.n_p == m.nx else []
    tries.append(LocalFrame(m.position, (), scene, layout))
    for frame in tries:
        if _invariant(sp, frame, np.random.default_rng(20260)):
            return frame
    return None


def check_coordinates(sp: SamplingProblem, carry: dict, scene: np.ndarray | None) -> None:
    """Refuse a float32 batch of a problem without a local frame whose start positions (all
    physical states when the model declares no position) or obstacles (circle centres; the
    places of a layout's obstacles: centres, capsule ends, the boundary points of half-spaces
    nearest the origin, grid corners) exceed :data:`COORDINATE_LIMIT32` in magnitude: float32
    cannot resolve its crash decisions. ``scene`` None: the obstacles were checked before."""
    m = sp.model
    idx = list(m.position) if m.position is not None else list(range(m.n_physical))
    for name in _CARRY_STATES:
        if name in carry:
            x = np.asarray(carry[name], dtype=float)[..., idx]
            big = float(np.max(np.abs(x))) if x.size else 0.0
            if big > COORDINATE_LIMIT32:
                which = "position" if m.position is not None else "physical state"
                raise fail(f"{name} ({which} entries)", big, _limit_text(
                    f"at most {COORDINATE_LIMIT32:g} in magnitude"))
    if scene is None or not (m.scene_capacity or m.scene_layout is not None):
        return
    if m.scene_layout is not None:
        used = anchor_points(m.scene_layout, scene)
        what = "scene (obstacle positions)"
    else:
        s = np.asarray(scene, dtype=float).reshape(-1, SLOT)
        used = s[s[:, 2] > 0, :2]
        what = "scene (circle centres)"
    big = float(np.max(np.abs(used))) if used.size else 0.0
    if big > COORDINATE_LIMIT32:
        raise fail(what, big, _limit_text(
            f"at most {COORDINATE_LIMIT32:g} m from the origin"))


def _limit_text(allowed: str) -> str:
    return (f"must be {allowed} for precision 'float32': this problem is not translation "
            "invariant (obstacles compiled in, costs or margins of absolute positions, or no "
            "declared position), so its float32 kernels cannot run relative to the current "
            "state, and float32 cannot resolve crash decisions at this magnitude; use "
            "precision 'float64' or move the map near the origin")

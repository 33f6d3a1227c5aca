"""Closed-loop simulation on the true plant with the disturbance models of SPEC 2.3, in a
scene that may move: obstacles are checked against the scene of each step."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Literal, Protocol

import casadi as ca
import numpy as np

from workbench.codegen.fastcall import FastFunction
from workbench.problem.models import Model
from workbench.validation import fail, integer, one_of, real

DisturbanceModel = Literal["velocity_variance", "velocity_std", "white_noise", "kick"]
DISTURBANCE_MODELS: tuple[str, ...] = ("velocity_variance", "velocity_std", "white_noise", "kick")


# the built-in planar integrators (workbench.problem.models) and their physical state names:
# only for these does a Disturbance without named states pick the states itself
PLANAR_INTEGRATORS: dict[str, tuple[str, ...]] = {
    "double_integrator": ("px", "py", "vx", "vy"),
    "single_integrator": ("px", "py"),
}


def is_planar_integrator(plant: Model) -> bool:
    """Whether ``plant`` is a built-in planar double or single integrator (barrier-embedded or
    not): its name and its physical state names are the built-in ones."""
    base = plant.name.removesuffix("+bas")
    return PLANAR_INTEGRATORS.get(base) == tuple(plant.state_names[: plant.n_physical])


@dataclass(frozen=True)
class Disturbance:
    """Plant disturbance w on some states (SPEC 2.3): the velocities of the double integrator.

    velocity_variance (default): w = dt [0, 0, xi], xi ~ N(0, level I) (level = variance);
    velocity_std: level is the std, xi ~ N(0, level^2 I);
    white_noise: w = sqrt(dt) sqrt(level) xi01 on the disturbed states;
    kick: w = [0, 0, xi] without the dt factor, xi ~ N(0, level I).

    The disturbed states: ``states`` names them, by the plant's state names or by index
    (``Disturbance(1.0, states=("v",))``); ``velocity_index`` gives indices (the older
    spelling; give one of the two). Without either, :func:`closed_loop` takes them from the
    plant only for the built-in planar integrators (:func:`disturbed_states`: the velocities of
    the double integrator, the positions of the single integrator); any other plant with
    ``level > 0`` must name them (a ValueError lists its state names).
    """

    level: float = 0.0
    model: DisturbanceModel = "velocity_variance"
    velocity_index: tuple[int, ...] | None = None
    states: tuple[str | int, ...] | None = None

    def __post_init__(self) -> None:
        real("Disturbance.level", self.level, 0.0)
        one_of("Disturbance.model", self.model, DISTURBANCE_MODELS)
        if self.velocity_index is not None:
            idx = self.velocity_index
            allowed = ("must be a non-empty tuple of distinct state indices >= 0, or None "
                       "(take them from the plant)")
            if not isinstance(idx, tuple | list) or not idx:
                raise fail("Disturbance.velocity_index", idx, allowed)
            ints = tuple(integer("Disturbance.velocity_index", i, 0) for i in idx)
            if len(set(ints)) != len(ints):
                raise fail("Disturbance.velocity_index", idx, allowed)
            object.__setattr__(self, "velocity_index", ints)
        if self.states is not None:
            st = self.states
            allowed = ("must be a non-empty tuple of distinct state names (str) or indices "
                       "(int >= 0), e.g. states=(\"v\",) or states=(3,)")
            if isinstance(st, str | int) and not isinstance(st, bool):
                st = (st,)  # one state: Disturbance(1.0, states="v")
            if not isinstance(st, tuple | list) or not st:
                raise fail("Disturbance.states", self.states, allowed)
            st = tuple(s if isinstance(s, str) else integer("Disturbance.states", s, 0)
                       for s in st)
            if len(set(st)) != len(st):
                raise fail("Disturbance.states", self.states, allowed)
            if self.velocity_index is not None:
                raise fail("Disturbance.states", self.states,
                           "give either states or velocity_index, not both")
            object.__setattr__(self, "states", st)

    @property
    def named(self) -> tuple[str | int, ...] | None:
        """The disturbed states this disturbance names itself (``states`` or
        ``velocity_index``), None when it leaves them to the plant."""
        return self.states if self.states is not None else self.velocity_index

    def indices(self, plant: Model) -> tuple[int, ...]:
        """The disturbed states for ``plant``: the named ones (checked against the plant), the
        built-in planar integrators' own, or () for any other plant when ``level`` is 0 (nothing
        to disturb). Any other plant with ``level > 0`` must name them: ValueError."""
        if self.states is not None:
            return self._resolve(plant)
        if self.velocity_index is None:
            if is_planar_integrator(plant):
                return disturbed_states(plant)
            if self.level == 0:
                return ()
            raise fail("Disturbance.states", None,
                       f"{plant.name} is not a built-in planar integrator, so the disturbed "
                       f"states must be named: its states are {self._listing(plant)}; give "
                       f"e.g. Disturbance({self.level!r}, states=({plant.state_names[0]!r},)) "
                       "by name or states=(0,) by index")
        bad = [i for i in self.velocity_index if i >= plant.nx]
        if bad:
            raise fail("Disturbance.velocity_index", self.velocity_index,
                       f"index {bad[0]} is out of range for {plant.name} with {plant.nx} states")
        return self.velocity_index

    @staticmethod
    def _listing(plant: Model) -> str:
        return ", ".join(f"{i}: {n!r}" for i, n in enumerate(plant.state_names))

    def _resolve(self, plant: Model) -> tuple[int, ...]:
        out = []
        for s in self.states:
            if isinstance(s, str):
                if s not in plant.state_names:
                    raise fail("Disturbance.states", self.states,
                               f"{plant.name} has no state {s!r}; its states are "
                               f"{self._listing(plant)}")
                out.append(plant.state_names.index(s))
            elif s >= plant.nx:
                raise fail("Disturbance.states", self.states,
                           f"index {s} is out of range for {plant.name} with {plant.nx} states "
                           f"({self._listing(plant)})")
            else:
                out.append(s)
        if len(set(out)) != len(out):
            raise fail("Disturbance.states", self.states,
                       f"names the same state twice on {plant.name} ({self._listing(plant)})")
        return tuple(out)

    def sample(self, nx: int, dt: float, rng: np.random.Generator,
               index: tuple[int, ...] | None = None) -> np.ndarray:
        if index is None and self.states is not None:
            if not all(isinstance(s, int) for s in self.states):
                raise fail("Disturbance.states", self.states, "names need the plant: pass "
                           "index=disturbance.indices(plant)")
            index = self.states
        idx = list(index if index is not None else self.velocity_index or ())
        if not idx:
            raise fail("Disturbance.velocity_index", self.velocity_index,
                       "give the disturbed state indices (closed_loop takes them from the plant)")
        w = np.zeros(nx)
        xi = rng.standard_normal(len(idx))
        if self.model == "velocity_variance":
            w[idx] = dt * np.sqrt(self.level) * xi
        elif self.model == "velocity_std":
            w[idx] = dt * self.level * xi
        elif self.model == "white_noise":
            w[idx] = np.sqrt(dt) * np.sqrt(self.level) * xi
        else:
            w[idx] = np.sqrt(self.level) * xi
        return w


def disturbed_states(plant: Model) -> tuple[int, ...]:
    """The physical states a plant disturbance acts on: those the control drives directly.

    A guess, used by :meth:`Disturbance.indices` only for the built-in planar integrators
    (:func:`is_planar_integrator`); on other models it can miss (a kinematic bicycle's largest
    control gain is on the heading, not the speed): name the states there.

    A matched disturbance enters where the control enters. Per physical state i, the largest
    |dF_i/du| over seeded random states and controls; the states within a factor 2 of the
    largest are disturbed. Double integrator: the velocities (the position rows are 0 with
    Euler and dt^2/2 against dt with zero-order hold); single integrator: the positions.
    """
    n = plant.n_physical
    jac = ca.Function("dFdu", [plant.x, plant.u], [ca.jacobian(plant.x_next[:n], plant.u)])
    rng = np.random.default_rng(20261123)
    lo = np.where(np.isfinite(plant.u_min), plant.u_min, -1.0)
    hi = np.where(np.isfinite(plant.u_max), plant.u_max, 1.0)
    gain = np.zeros(n)
    for _ in range(8):
        J = np.abs(np.asarray(jac(rng.normal(0.0, 1.0, plant.nx), rng.uniform(lo, hi))))
        gain = np.maximum(gain, np.where(np.isfinite(J), J, 0.0).max(axis=1))
    if not gain.max() > 0:
        raise fail("plant", plant.name, "no state depends on u; give "
                   "Disturbance(states=...) to choose the disturbed states")
    return tuple(int(i) for i in np.flatnonzero(gain >= 0.5 * gain.max()))


class Controller(Protocol):
    def initial_state(self, x0: np.ndarray): ...

    def step(self, state, x: np.ndarray, rng: np.random.Generator): ...


@dataclass(frozen=True)
class Episode:
    """Per-step records of one closed-loop run. X (n+1, nx), U (n, nu).

    ``scene_time_s`` (n,): time spent handing each step's scene to the controller (zeros when
    the scene is static); ``scenes`` (n+1, n_scene): the scene of every state in X when the
    scene moves (empty otherwise)."""

    X: np.ndarray
    U: np.ndarray
    crashed: bool
    crash_step: int | None
    min_margin: float
    step_time_s: np.ndarray
    infos: tuple = field(default=(), repr=False)
    scene_time_s: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    scenes: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)), repr=False)


SceneInput = Callable[[int], object] | object


def scene_sequence(scenes: Sequence) -> Callable[[int], object]:
    """A moving scene for :func:`closed_loop` from a list of scenes, one per step (step k uses
    ``scenes[k]``; the last is held)."""
    items = list(scenes)
    if not items:
        raise fail("scenes", scenes, "need at least one scene")

    def at(k: int):
        return items[min(k, len(items) - 1)]

    return at


def closed_loop(controller, plant: Model, x0, steps: int, rng_controller: np.random.Generator,
                rng_plant: np.random.Generator, disturbance: Disturbance = Disturbance(),
                keep_infos: bool = True, scene: SceneInput = None) -> Episode:
    """Run ``controller`` on the plant x+ = F(x, u) + w for ``steps`` steps; stop at a crash
    (min_i h_i <= 0 on the true plant, in the scene of that time). w acts on
    ``disturbance.indices(plant)`` (none when that is empty: a plant of one's own without a
    disturbance).

    ``scene``: None (the plant's own obstacles), one scene (circles or a flat scene vector, see
    :meth:`~workbench.problem.Model.scene_vector`), or a callable ``k -> scene`` giving the
    scene at step k = 0..steps (:func:`scene_sequence` makes one from a list). Before step k
    the controller gets scene k through its ``set_scene`` (when it has one); the state after
    step k is checked against scene k + 1: obstacles move while the plant does.
    """
    integer("steps", steps, 1)
    x = np.asarray(x0, dtype=float)
    if x.shape != (plant.nx,) or not np.all(np.isfinite(x)):
        raise fail("x0", x0, f"must be {plant.nx} finite numbers")
    if scene is not None and not plant.n_scene:
        raise fail("scene", "given", f"the plant {plant.name} has no run-time scene (its "
                   "obstacles are baked in); build it with runtime obstacles")
    moving = callable(scene)
    static = None if scene is None or moving else plant.scene_vector(scene)

    def scene_at(k: int) -> np.ndarray:
        if not moving:
            return plant.scene_value if static is None else static
        try:
            return plant.scene_vector(scene(k))
        except ValueError as exc:
            raise fail(f"scene({k})", "returned", str(exc)) from exc

    f = FastFunction(ca.Function("plant", [plant.x, plant.u], [plant.x_next]))
    disturbed = disturbance.indices(plant)
    margins = plant.margins if plant.nh else None
    set_scene = getattr(controller, "set_scene", None)
    s = scene_at(0)
    if static is not None and set_scene is not None:
        set_scene(s)
    state = controller.initial_state(x)
    X, U, times, infos, stimes = [x.copy()], [], [], [], []
    scenes = [s] if moving else None
    crashed, crash_step = False, None
    min_h = float(np.min(margins(x, s))) if margins else np.inf
    if margins is not None and min_h <= 0:
        raise fail("x0", x0, f"starts inside an obstacle of the scene (min h = {min_h:.4g})")
    for k in range(steps):
        t0 = time.perf_counter()
        if moving and set_scene is not None:
            set_scene(s)
        t1 = time.perf_counter()
        state, u, info = controller.step(state, x, rng_controller)
        t2 = time.perf_counter()
        times.append(t2 - t1)
        stimes.append(t1 - t0)
        u = np.clip(u, plant.u_min, plant.u_max)
        x_model = f(x, u)[0]
        x = (x_model + disturbance.sample(plant.nx, plant.dt, rng_plant, disturbed)
             if disturbed else x_model.copy())
        s = scene_at(k + 1)
        X.append(x.copy())
        U.append(u)
        if moving:
            scenes.append(s)
        if keep_infos:
            infos.append(info)
        if margins is not None:
            h = float(np.min(margins(x, s)))
            min_h = min(min_h, h)
            if h <= 0:
                crashed, crash_step = True, k + 1
                break
    return Episode(X=np.array(X), U=np.array(U), crashed=crashed, crash_step=crash_step,
                   min_margin=min_h, step_time_s=np.array(times), infos=tuple(infos),
                   scene_time_s=np.array(stimes),
                   scenes=np.array(scenes) if moving else np.zeros((0, 0)))

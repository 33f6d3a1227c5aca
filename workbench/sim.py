"""Closed-loop simulation on the true plant under a plant disturbance (:class:`Disturbance`), in
a scene that may move: obstacles are checked against the scene of each step; optionally the
episode ends at the goal."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from numbers import Integral
from typing import Any, Literal, Protocol, runtime_checkable

import casadi as ca
import numpy as np

from workbench.codegen.fastcall import FastFunction
from workbench.problem.models import Model, margin_violation
from workbench.validation import MAX_STEPS, fail, integer, one_of, real

DisturbanceModel = Literal["velocity_variance", "velocity_std", "white_noise", "kick",
                           "impulse", "step", "uniform", "periodic"]
DISTURBANCE_MODELS: tuple[str, ...] = ("velocity_variance", "velocity_std", "white_noise", "kick",
                                       "impulse", "step", "uniform", "periodic")
# the deterministic signals may push either way: their level may be negative
_SIGNED = ("impulse", "step", "periodic")


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
    """Plant disturbance w_k added to some states after step k (x_{k+1} = F(x_k, u_k) + w_k).

    Four readings of one "variance" level of a Gaussian velocity disturbance (Table I of the
    SAIS paper; xi ~ N(0, I) on the disturbed states, drawn afresh every step):

    - velocity_variance (default): w = dt sqrt(level) xi (level = variance of the rate);
    - velocity_std: w = dt level xi (level = std of the rate);
    - white_noise: w = sqrt(dt) sqrt(level) xi (continuous-time white noise of intensity level:
      a Wiener increment per step);
    - kick: w = sqrt(level) xi (no dt: level is the variance of the per-step jump).

    The disturbance types of safe-control-gym (Yuan et al. 2022, arXiv:2109.06325;
    ``safe_control_gym/envs/disturbances.py``), re-implemented. They act there as forces on
    the dynamics, so here as rates: w = dt s_k on every disturbed state, s_k the signal of step
    k (an acceleration on the double integrator's velocities, a velocity on the single
    integrator's positions), the same scaling as velocity_variance:

    - impulse: s_k = level decay^|k - c| on the ``duration`` steps k = start_step ..
      start_step + duration - 1 (centre c = start_step + (duration - 1) / 2), 0 elsewhere
      (decay 1: a square pulse; decay < 1: a triangle-like peak). Its magnitude, step_offset,
      duration and decay_rate are level, start_step, duration and decay. For an odd duration
      this is safe-control-gym's pulse step for step; for an even one theirs is nonzero on
      ``duration - 1`` steps from start_step + 1, this one on exactly ``duration`` steps.
    - step: s_k = level for k >= start_step, 0 before (magnitude, step_offset).
    - uniform: s_k = level U(low, high), i.i.d. per step and state (their low/high; level
      scales, so the default is U(-level, level) and level 1 gives theirs exactly).
    - periodic: s_k = level sin(2 pi frequency k dt + phase) (their scale and frequency, time
      k dt in the plant's seconds, the same phase on every disturbed state). safe-control-gym
      draws a new phase U(-pi, pi) at every step, which makes its signal i.i.d. in time rather
      than periodic; here the phase is a fixed field (draw it per episode to randomise it).

    safe-control-gym's WhiteNoise (i.i.d. N(0, std^2) per step, a force) is the velocity_std
    reading with level = std (w = dt std xi), not the white_noise reading above; there is no
    separate model for it. Their random step_offset (step_offset=None) is left out: a study
    draws start_step from its own generator. impulse, step and periodic draw no random numbers
    and may have a negative level (a push the other way); the others need level >= 0.

    Fields other than level are read by some models only (start_step: impulse and step;
    duration, decay: impulse; low, high: uniform; frequency, phase: periodic); they are
    validated for every model and ignored by the others (a step has no duration: it lasts).
    start_step and duration are at most :data:`~workbench.validation.MAX_STEPS` (an episode's
    longest run).

    The disturbed states: ``states`` names them, by the plant's state names or by index
    (``Disturbance(1.0, states=("v",))``); ``velocity_index`` gives indices (the older
    spelling; give one of the two). Without either, :func:`closed_loop` takes them from the
    plant only for the built-in planar integrators (:func:`disturbed_states`: the velocities of
    the double integrator, the positions of the single integrator); any other plant with
    ``level != 0`` must name them (a ValueError lists its state names).
    """

    level: float = 0.0
    model: DisturbanceModel = "velocity_variance"
    velocity_index: tuple[int, ...] | None = None
    states: tuple[str | int, ...] | None = None
    start_step: int = 0
    duration: int = 1
    decay: float = 1.0
    low: float = -1.0
    high: float = 1.0
    frequency: float = 1.0
    phase: float = 0.0

    def __post_init__(self) -> None:
        one_of("Disturbance.model", self.model, DISTURBANCE_MODELS)
        if self.model in _SIGNED:
            real("Disturbance.level", self.level)
        else:
            real("Disturbance.level", self.level, 0.0)
        integer("Disturbance.start_step", self.start_step, 0, MAX_STEPS)
        integer("Disturbance.duration", self.duration, 1, MAX_STEPS)
        real("Disturbance.decay", self.decay, 0.0, strict=True, maximum=1.0)
        real("Disturbance.low", self.low)
        real("Disturbance.high", self.high)
        if self.high < self.low:
            raise fail("Disturbance.high", self.high,
                       f"must be >= Disturbance.low = {self.low!r}")
        real("Disturbance.frequency", self.frequency, 0.0, strict=True)
        real("Disturbance.phase", self.phase)
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
            if isinstance(st, str | Integral) and not isinstance(st, bool | np.bool_):
                st = (st,)  # one state: Disturbance(1.0, states="v")
            if isinstance(st, np.ndarray) and st.ndim == 1:
                st = tuple(st.tolist())
            if not isinstance(st, tuple | list) or not st:
                raise fail("Disturbance.states", self.states, allowed)
            if any(isinstance(s, str) and not s for s in st):
                raise fail("Disturbance.states", self.states, "a state name must not be empty; "
                           + allowed)
            st = tuple(s if isinstance(s, str) else integer("Disturbance.states", s, 0)
                       for s in st)
            if len(set(st)) != len(st):
                raise fail("Disturbance.states", self.states, allowed)
            if self.velocity_index is not None:
                raise fail("Disturbance.states", self.states,
                           "give either states or velocity_index, not both")
            object.__setattr__(self, "states", st)

    @property
    def label(self) -> str:
        """A short name for result tables: the model, its level and the fields it reads, e.g.
        ``velocity_variance(10)``, ``impulse(2, k=100..109)`` (first..last step of the
        pulse), ``step(-3, k>=50)``, ``uniform(1, [-1, 1])``, ``periodic(2, f=0.5)``; named
        states follow (``step(3, k>=0) on vx``)."""
        g = f"{self.level:g}"
        if self.model == "impulse":
            last = self.start_step + self.duration - 1
            g += f", k={self.start_step}..{last}"
            if self.decay != 1.0:
                g += f", decay={self.decay:g}"
        elif self.model == "step":
            g += f", k>={self.start_step}"
        elif self.model == "uniform":
            g += f", [{self.low:g}, {self.high:g}]"
        elif self.model == "periodic":
            g += f", f={self.frequency:g}" + (f", phase={self.phase:g}" if self.phase else "")
        text = f"{self.model}({g})"
        if self.named is not None:
            text += " on " + ",".join(str(s) for s in self.named)
        return text

    @property
    def named(self) -> tuple[str | int, ...] | None:
        """The disturbed states this disturbance names itself (``states`` or
        ``velocity_index``), None when it leaves them to the plant."""
        return self.states if self.states is not None else self.velocity_index

    def indices(self, plant: Model) -> tuple[int, ...]:
        """The disturbed states for ``plant``: the named ones (checked against the plant), the
        built-in planar integrators' own, or () for any other plant when ``level`` is 0 (nothing
        to disturb). Any other plant with ``level != 0`` must name them: ValueError."""
        if self.states is not None:
            return self._resolve(plant, self.states)
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

    def _resolve(self, plant: Model, states: tuple[str | int, ...]) -> tuple[int, ...]:
        out = []
        for s in states:
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
               index: tuple[int, ...] | None = None, k: int = 0) -> np.ndarray:
        """The disturbance w_k (nx,) of step k (the step from x_k to x_{k+1}, time k dt) on
        the states ``index`` (default: the named ones). The Gaussian readings draw
        ``rng.standard_normal(len(index))`` and uniform ``rng.uniform(low, high,
        len(index))`` once per call; impulse, step and periodic draw nothing."""
        name = "index" if index is not None else (
            "Disturbance.states" if self.states is not None else "Disturbance.velocity_index")
        if index is None and self.states is not None:
            if not all(isinstance(s, int) for s in self.states):
                raise fail("Disturbance.states", self.states, "names need the plant: pass "
                           "index=disturbance.indices(plant)")
            index = tuple(s for s in self.states if isinstance(s, int))  # all of them
        idx = list(index if index is not None else self.velocity_index or ())
        if not idx:
            raise fail("Disturbance.velocity_index", self.velocity_index,
                       "give the disturbed state indices (closed_loop takes them from the plant)")
        nx = integer("nx", nx, 1)
        real("dt", dt, 0.0, strict=True)
        for i in idx:
            ok = isinstance(i, Integral) and not isinstance(i, bool | np.bool_) and 0 <= i < nx
            if not ok:
                raise fail(name, str(tuple(idx)), f"entry {i!r} is not a state index in "
                           f"[0, {nx - 1}] (the state has nx = {nx} entries)")
        if len(set(idx)) != len(idx):
            raise fail(name, str(tuple(idx)), "names the same state twice")
        k = integer("k", k, 0)
        w = np.zeros(nx)
        model = self.model
        if model == "uniform":
            w[idx] = dt * self.level * rng.uniform(self.low, self.high, len(idx))
            return w
        if model in _SIGNED:
            w[idx] = dt * self._signal(k, dt)
            return w
        xi = rng.standard_normal(len(idx))
        if model == "velocity_variance":
            w[idx] = dt * np.sqrt(self.level) * xi
        elif model == "velocity_std":
            w[idx] = dt * self.level * xi
        elif model == "white_noise":
            w[idx] = np.sqrt(dt) * np.sqrt(self.level) * xi
        else:
            w[idx] = np.sqrt(self.level) * xi
        return w

    def _signal(self, k: int, dt: float) -> float:
        """The deterministic signal s_k of impulse, step and periodic."""
        if self.model == "step":
            return self.level if k >= self.start_step else 0.0
        if self.model == "impulse":
            if not self.start_step <= k < self.start_step + self.duration:
                return 0.0
            centre = self.start_step + (self.duration - 1) / 2
            return self.level * self.decay ** abs(k - centre)
        return self.level * float(np.sin(2 * np.pi * self.frequency * k * dt + self.phase))


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


@runtime_checkable
class StepInfo(Protocol):
    """What every controller's step reports: ``stats``, a
    :class:`~workbench.sampling.step_stats.StepStats` (samples, collision-free samples, ESS,
    and how often each safety mechanism acted)."""

    @property
    def stats(self) -> Any: ...


@runtime_checkable
class Controller(Protocol):
    """The step protocol every controller follows (all methods of the registry do, which a test
    checks): ``initial_state(x0)`` -> its state; ``step(state, x, rng)`` -> ``(state, u,
    info)`` with ``info`` a :class:`StepInfo`; ``set_scene(scene)``: the obstacles of the next
    steps (a scene vector or circles); ``record_samples(k, keep)``: keep ``k`` sample
    trajectories per step in the info (0: none).

    Optional: ``check_episode(episode)``, called by :func:`closed_loop` with the finished
    :class:`Episode` (the registered methods' warns when their safety mechanism never acted
    or acted on every step, see :mod:`workbench.scenarios.mechanism_health`)."""

    def initial_state(self, x0: np.ndarray | None = None) -> Any: ...

    def step(self, state: Any, x: np.ndarray,
             rng: np.random.Generator) -> tuple[Any, np.ndarray, StepInfo]: ...

    def set_scene(self, scene: Any) -> None: ...

    def record_samples(self, k: int = 64, keep: Any = "spread") -> None: ...


@dataclass(frozen=True)
class Episode:
    """Per-step records of one closed-loop run. X (n+1, nx), U (n, nu).

    ``step_time_s`` (n,): wall-clock time of each controller step (``time.perf_counter``);
    ``step_cpu_s`` (n,): the process's CPU time over the same call (``time.process_time``: all
    threads, the kernels' OpenMP team included; unaffected by other processes, see
    :mod:`workbench.study.latency`). ``scene_time_s`` (n,): time spent handing each step's
    scene to the controller (zeros when the scene is static); ``scenes`` (n+1, n_scene): the
    scene of every state in X when the scene moves (empty otherwise).
    ``reached_goal``/``goal_step``: with ``stop_at_goal``, whether and at which state
    X[goal_step] the episode reached the goal (it ends there)."""

    X: np.ndarray
    U: np.ndarray
    crashed: bool
    crash_step: int | None
    min_margin: float
    step_time_s: np.ndarray
    infos: tuple = field(default=(), repr=False)
    scene_time_s: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    scenes: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)), repr=False)
    reached_goal: bool = False
    goal_step: int | None = None
    step_cpu_s: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)


SceneInput = Callable[[int], object] | object


def scene_sequence(scenes: Sequence) -> Callable[[int], object]:
    """A moving scene for :func:`closed_loop` from a list of scenes, one per step (step k uses
    ``scenes[k]``; the last is held)."""
    if isinstance(scenes, str | bytes) or not hasattr(scenes, "__iter__"):
        raise fail("scenes", scenes, "must be a list of scenes, one per step")
    items = list(scenes)
    if not items:
        raise fail("scenes", scenes, "need at least one scene")

    def at(k: int):
        return items[min(k, len(items) - 1)]

    return at


def closed_loop(controller: Controller, plant: Model, x0, steps: int,
                rng_controller: np.random.Generator, rng_plant: np.random.Generator,
                disturbance: Disturbance = Disturbance(), keep_infos: bool = True,
                scene: SceneInput = None,
                stop_at_goal: float | None = None, goal=None,
                check_episode: bool = True,
                goal_distance: Callable[[np.ndarray], float] | None = None,
                period_s: float | None = None) -> Episode:
    """Run ``controller`` on the plant x+ = F(x, u) + w for ``steps`` steps; stop at a crash
    (min_i h_i <= 0 on the true plant, in the scene of that time). w acts on
    ``disturbance.indices(plant)`` (none when that is empty: a plant of one's own without a
    disturbance).

    ``scene``: None (the plant's own obstacles), one scene (circles or a flat scene vector, see
    :meth:`~workbench.problem.Model.scene_vector`), or a callable ``k -> scene`` giving the
    scene at step k = 0..steps (:func:`scene_sequence` makes one from a list); a callable must
    return a scene at every step (None, a bare Circle or a malformed scene is a ValueError
    naming the step). Before step k
    the controller gets scene k through its ``set_scene`` (when it has one); the state after
    step k is checked against scene k + 1: obstacles move while the plant does. Step k draws
    the disturbance of step k (``disturbance.sample(..., k=k)``).

    ``stop_at_goal``: a distance > 0; the episode ends after the first step whose state is
    within it (Euclidean, on ``plant.position``) of the goal position (``reached_goal``,
    ``goal_step``). ``goal``: a physical state or a position; default ``controller.goal``.
    A state that crashes is a crash, never a goal, even when within the distance.
    ``goal_distance``: with ``stop_at_goal``, ``x -> distance`` of a physical state to the goal,
    used instead of the Euclidean distance on ``plant.position`` (e.g.
    :meth:`~workbench.scenarios.navigation.NavigationSetup.goal_distance` for a plant without a
    position); ``goal`` is then not read.

    ``check_episode``: when the controller has a ``check_episode`` (see :class:`Controller`)
    and the infos are kept, hand it the episode before returning it (False: skip, e.g. in a
    study that checks all its episodes together).

    ``period_s``: run the loop at a fixed rate, as a controller on a robot does: each step
    starts one period after the last one started (the loop sleeps until then), or at once when
    the last one took longer, and the period then counts from there (no burst of steps makes
    up for a late one). None (the default): steps run back to back.
    """
    integer("steps", steps, 1)
    if period_s is not None:
        real("period_s", period_s, 0.0, strict=True)
    x = np.asarray(x0, dtype=float)
    if x.shape != (plant.nx,) or not np.all(np.isfinite(x)):
        raise fail("x0", x0, f"must be {plant.nx} finite numbers")
    if goal_distance is not None:
        if stop_at_goal is None or not callable(goal_distance):
            raise fail("goal_distance", goal_distance, "must be a function of the state, "
                       "given with stop_at_goal")
        if goal is not None:
            raise fail("goal", goal, "is not read with goal_distance (it measures the "
                       "distance itself); give one of them")
        real("stop_at_goal", stop_at_goal, 0.0, strict=True)
    goal_p = None if stop_at_goal is None or goal_distance is not None else _goal_position(
        plant, controller, stop_at_goal, goal)
    if stop_at_goal is None and goal is not None:
        raise fail("goal", goal, "is only read with stop_at_goal (give both, or neither)")
    reached, goal_step = False, None
    pos = list(plant.position) if goal_p is not None and plant.position is not None else []
    if scene is not None and not plant.n_scene:
        raise fail("scene", "given", f"the plant {plant.name} has no run-time scene (its "
                   "obstacles are baked in); build it with runtime obstacles")
    moving = callable(scene)
    static = None if scene is None or moving else plant.scene_vector(scene)

    def scene_at(k: int) -> np.ndarray:
        if not callable(scene):  # a static scene
            return plant.scene_value if static is None else static
        got = scene(k)
        if got is None:  # never the plant's own obstacles in place of the moving scene
            raise fail(f"scene({k})", None, "a moving scene must return the scene of every "
                       "step (circles or a scene vector); return plant.scene_value for the "
                       "plant's own obstacles")
        try:
            return plant.scene_vector(got)
        except ValueError as exc:  # name the step: scene(k)[i] = ... is invalid: ...
            text = str(exc)
            raise ValueError(f"scene({k}){text[5:]}" if text.startswith("scene")
                             else f"scene({k}): {text}") from exc

    f = FastFunction(ca.Function("plant", [plant.x, plant.u], [plant.x_next]))
    disturbed = disturbance.indices(plant)
    margins = plant.margins if plant.nh else None
    set_scene = getattr(controller, "set_scene", None)
    s = scene_at(0)
    min_h = _start_margin(plant, x0, x, s) if margins else np.inf  # before the controller
    if static is not None and set_scene is not None:
        set_scene(s)
    state = controller.initial_state(x)
    X, U, times, infos, stimes, cpu = [x.copy()], [], [], [], [], []
    scenes = [s] if moving else None
    crashed, crash_step = False, None
    tick = time.perf_counter()  # when the next step is due (with period_s)
    for k in range(steps):
        if period_s is not None:
            now = time.perf_counter()
            if now < tick:
                time.sleep(tick - now)
            tick = max(now, tick) + period_s
        t0 = time.perf_counter()
        if moving and set_scene is not None:
            set_scene(s)
        c1, t1 = time.process_time(), time.perf_counter()
        state, u, info = controller.step(state, x, rng_controller)
        t2, c2 = time.perf_counter(), time.process_time()
        times.append(t2 - t1)
        cpu.append(c2 - c1)
        stimes.append(t1 - t0)
        u = np.clip(u, plant.u_min, plant.u_max)
        x_model = f(x, u)[0]
        x = (x_model + disturbance.sample(plant.nx, plant.dt, rng_plant, disturbed, k)
             if disturbed else x_model.copy())
        s = scene_at(k + 1)
        X.append(x.copy())
        U.append(u)
        if scenes is not None:  # the scene moves
            scenes.append(s)
        if keep_infos:
            infos.append(info)
        if margins is not None:
            h = float(np.min(margins(x, s)))
            min_h = min(min_h, h)
            if h <= 0:
                crashed, crash_step = True, k + 1
                break
        if stop_at_goal is not None and (
                goal_distance(x[:plant.n_physical]) <= stop_at_goal if goal_distance is not None
                else goal_p is not None and np.linalg.norm(x[pos] - goal_p) <= stop_at_goal):
            reached, goal_step = True, k + 1
            break
    episode = Episode(X=np.array(X), U=np.array(U), crashed=crashed, crash_step=crash_step,
                      min_margin=min_h, step_time_s=np.array(times), infos=tuple(infos),
                      scene_time_s=np.array(stimes),
                      scenes=np.array(scenes) if moving else np.zeros((0, 0)),
                      reached_goal=reached, goal_step=goal_step, step_cpu_s=np.array(cpu))
    check = getattr(controller, "check_episode", None)
    if check_episode and keep_infos and callable(check):
        check(episode)
    return episode


def _start_margin(plant: Model, x0, x: np.ndarray, scene: np.ndarray) -> float:
    """min h at the start; a start on or inside an obstacle's boundary (min h <= 0, the
    episode's crash rule) is refused, naming x0 and the obstacle."""
    h = plant.margins(x, scene)
    where = margin_violation(plant, h)
    if where is None:
        return float(np.min(h))
    raise fail("x0", x0, f"{where} in the scene of step 0 (min h <= 0 is a crash); the start "
               "must be strictly safe (every h > 0)")


def _goal_position(plant: Model, controller, stop_at_goal, goal) -> np.ndarray:
    """The goal position for :func:`closed_loop`'s ``stop_at_goal``, checked."""
    real("stop_at_goal", stop_at_goal, 0.0, strict=True)
    if plant.position is None:
        raise fail("stop_at_goal", stop_at_goal, f"the plant {plant.name} has no position "
                   "(Model.position) to measure the distance to the goal on")
    if goal is None:
        goal = getattr(controller, "goal", None)
        if goal is None:
            raise fail("goal", None, f"{type(controller).__name__} has no goal attribute; "
                       "give goal= (a physical state or a position)")
    pos = list(plant.position)
    try:
        g = np.asarray(goal, dtype=float).ravel()
    except (TypeError, ValueError) as exc:
        raise fail("goal", goal, "expected a numeric state or position") from exc
    if g.size in (plant.nx, plant.n_physical):
        g = g[pos]
    elif g.size != len(pos):
        raise fail("goal", goal, f"must be a state of {plant.n_physical} (or {plant.nx}) "
                   f"entries or a position of {len(pos)}")
    if not np.all(np.isfinite(g)):
        raise fail("goal", goal, "must be finite")
    return g

"""One arena episode: a controller with given settings on a system, a generated map and a
disturbance, from given random streams; shared by the arena's tasks and its tuning runs.

Everything built here is cached per process (maps, set-ups, controllers, thresholds): a worker
that runs many episodes of one (system, map, settings) builds them once.

A system is named as in the config: a registered name or an entry (``"module:function"`` or
``"path/file.py:function"``) that a worker process loads itself (:func:`arena_system`). A system
built from a model runs on its own scene, never on a generated map (assumptions §12.4).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from functools import cache

import numpy as np

from workbench.sampling.feedback import FeedbackWeights
from workbench.sampling.robust import RMPPIConfig
from workbench.scenarios.maps import LAYOUT_FAMILIES, GeneratedMap, MapFamily, generate, scaled
from workbench.scenarios.methods import build, method
from workbench.scenarios.model_system import resolve_system
from workbench.scenarios.navigation import NavigationSetup, navigation_setup
from workbench.scenarios.scenes import ObstacleScene
from workbench.scenarios.systems import System
from workbench.scenarios.tuned import ControllerSettings
from workbench.sim import Disturbance, closed_loop


@cache
def _entry_system(entry: str) -> System:
    return resolve_system(entry)


def arena_system(name: str) -> System:
    """The system a config names: a registered name, or an entry whose system is loaded and
    registered in this process the first time
    (:func:`~workbench.scenarios.model_system.resolve_system`; cached per process), so a
    spawned worker loads it itself."""
    return _entry_system(name) if ":" in name else resolve_system(name)


def own_scene(name: str) -> bool:
    """Whether the system ``name`` runs on a scene of its own (a system built from a model:
    start, goal and constraints of its own), where the generated maps do not apply."""
    return arena_system(name).scene is not None


@cache
def arena_map(family: MapFamily, seed: int) -> GeneratedMap:
    """The generated map of ``family`` and ``seed`` (cached per process)."""
    return generate(family, seed)


def capacity(family: MapFamily, seeds: tuple[int, ...]) -> int | None:
    """Circle slots for every map of ``family`` with these seeds, rounded up to a multiple of
    8: all of them share one compiled set of kernels per system. None for a family whose maps
    are signed-distance grids (one grid of the family's shape: its scene sizes itself)."""
    if family.family in LAYOUT_FAMILIES:
        return None
    most = max(len(arena_map(family, s).circles) for s in seeds)
    return 8 * math.ceil(most / 8)


@dataclass(frozen=True)
class Where:
    """A system on one map: the map's family and seed, and the circle slots of its kernels.
    A system with a scene of its own runs on that scene whatever the map (``capacity`` None:
    no circle slots; so does a map that is a signed-distance grid, whose scene sizes the
    plant's input); the map's seed then only selects the episode's random streams."""

    system: str
    family: MapFamily
    seed: int
    capacity: int | None

    @property
    def spec(self) -> System:
        return arena_system(self.system)

    @property
    def own(self) -> bool:
        return self.spec.scene is not None

    def scene(self):
        if self.own:
            return self.spec.scene
        m = scaled(arena_map(self.family, self.seed), self.spec.scale)
        return m.scene(circle_slots=self.capacity) if self.family.predict else m.scene()

    def moving(self, dt: float):
        """The moving scene ``k -> circles`` (None for a static map or a scene of the
        system's own), in the system's scale; with the circles' velocities when the family
        predicts them."""
        if self.own:
            return None
        m = arena_map(self.family, self.seed)
        if not m.moving:
            return None
        m = scaled(m, self.spec.scale)
        return m.velocity_scene(dt) if self.family.predict else m.moving_scene(dt)


@dataclass(frozen=True)
class Controls:
    """A controller's name and settings, with the shared robust, feedback and seed settings."""

    name: str
    settings: ControllerSettings
    robust: RMPPIConfig
    feedback: FeedbackWeights | None
    calibration_seed: int


@cache
def setup(where: Where, settings: ControllerSettings) -> NavigationSetup:
    scene = where.scene()  # an ObstacleScene sizes its own slots
    return navigation_setup(scene, system=where.spec, q_beta=settings.q_beta,
                            mppi=settings.sampler,
                            scene_capacity=None if isinstance(scene, ObstacleScene)
                            else where.capacity)


@cache
def controller(where: Where, c: Controls):
    """The controller on this map (robust ones calibrate their alpha rule on it first: one
    undisturbed episode seeded with ``c.calibration_seed``)."""
    nav = setup(where, c.settings)
    s = c.settings
    threshold = (nav.threshold(s.rule, method(c.name).feedback, c.robust, c.feedback,
                               c.calibration_seed, s.methods)
                 if method(c.name).robust else None)
    return build(nav, c.name, c.settings.methods, threshold=threshold, robust=c.robust,
                 weights=c.feedback)


@dataclass(frozen=True)
class Outcome:
    crashed: bool
    reached: bool
    steps: int
    final_error: float
    min_h: float
    time_to_goal_s: float
    collision_free_fraction: float
    ess_mean: float
    mean_step_ms: float
    X: np.ndarray
    U: np.ndarray
    activity: dict[str, float]
    step_wall_s: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    step_cpu_s: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))

    @property
    def success(self) -> bool:
        return self.reached and not self.crashed

    def row(self) -> dict[str, object]:
        return {k: v for k, v in dataclasses.asdict(self).items()
                if k not in ("X", "U", "activity", "mean_step_ms", "step_wall_s",
                             "step_cpu_s")}


def run_episode(where: Where, c: Controls, disturbance: Disturbance, steps: int,
                goal_radius: float, rng_controller: np.random.Generator,
                rng_plant: np.random.Generator, threads: int = 1) -> Outcome:
    """One closed-loop episode; it ends at a crash, within ``goal_radius`` (scaled by the
    system) of the goal, or after ``steps`` steps. A system with a scene of its own uses its
    own goal radius in its own distance to the goal (:meth:`System.goal_distance`) instead."""
    nav = setup(where, c.settings)
    ctrl = controller(where, c)
    lib = getattr(getattr(ctrl, "sampler", None), "lib", None)
    if lib is not None:
        lib.set_threads(threads)
    if where.own:
        ep = closed_loop(ctrl, nav.plant, nav.x0, steps, rng_controller, rng_plant,
                         disturbance, stop_at_goal=where.spec.goal_radius,
                         goal_distance=lambda x: float(nav.goal_distance(x)[0]),
                         check_episode=False)
        dist = nav.goal_distance(ep.X)
    else:
        radius = goal_radius * where.spec.scale
        ep = closed_loop(ctrl, nav.plant, nav.x0, steps, rng_controller, rng_plant,
                         disturbance, scene=where.moving(nav.plant.dt), stop_at_goal=radius,
                         goal=nav.goal, check_episode=False)  # the report checks every cell
        pos = list(nav.plant.position)
        dist = np.linalg.norm(ep.X[:, pos] - nav.goal[pos], axis=1)
    stats = [i.stats for i in ep.infos]
    cf = np.array([s.n_collision_free / max(s.n_samples, 1) for s in stats])
    keys = sorted({k for s in stats for k in s.activity})
    activity = {k: float(np.mean([s.activity.get(k, 0.0) for s in stats])) for k in keys}
    return Outcome(
        crashed=bool(ep.crashed), reached=bool(ep.reached_goal), steps=len(ep.U),
        final_error=float(dist[-1]), min_h=float(ep.min_margin),
        time_to_goal_s=(ep.goal_step * nav.plant.dt if ep.goal_step is not None else math.nan),
        collision_free_fraction=float(cf.mean()) if cf.size else math.nan,
        ess_mean=float(np.mean([s.ess for s in stats])) if stats else math.nan,
        mean_step_ms=float(1e3 * ep.step_time_s.mean()), X=ep.X, U=np.asarray(ep.U),
        activity=activity, step_wall_s=ep.step_time_s, step_cpu_s=ep.step_cpu_s)

"""One arena episode: a controller with given settings on a system, a generated map and a
disturbance, from given random streams; shared by the arena's tasks and its tuning runs.

Everything built here is cached per process (maps, set-ups, controllers, thresholds): a worker
that runs many episodes of one (system, map, settings) builds them once.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from functools import cache

import numpy as np

from workbench.sampling.feedback import FeedbackWeights
from workbench.sampling.robust import RMPPIConfig
from workbench.scenarios.maps import GeneratedMap, MapFamily, generate, scaled
from workbench.scenarios.methods import build, method
from workbench.scenarios.navigation import NavigationSetup, navigation_setup
from workbench.scenarios.systems import System, system
from workbench.scenarios.tuned import ControllerSettings
from workbench.sim import Disturbance, closed_loop


@cache
def arena_map(family: MapFamily, seed: int) -> GeneratedMap:
    """The generated map of ``family`` and ``seed`` (cached per process)."""
    return generate(family, seed)


def capacity(family: MapFamily, seeds: tuple[int, ...]) -> int:
    """Circle slots for every map of ``family`` with these seeds, rounded up to a multiple of
    8: all of them share one compiled set of kernels per system."""
    most = max(len(arena_map(family, s).circles) for s in seeds)
    return 8 * math.ceil(most / 8)


@dataclass(frozen=True)
class Where:
    """A system on one map: the map's family and seed, and the circle slots of its kernels."""

    system: str
    family: MapFamily
    seed: int
    capacity: int

    @property
    def spec(self) -> System:
        return system(self.system)

    def scene(self):
        return scaled(arena_map(self.family, self.seed), self.spec.scale).scene()

    def moving(self, dt: float):
        """The moving scene ``k -> circles`` (None for a static map), in the system's scale."""
        m = arena_map(self.family, self.seed)
        return scaled(m, self.spec.scale).moving_scene(dt) if m.moving else None


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
    return navigation_setup(where.scene(), system=where.system, q_beta=settings.q_beta,
                            mppi=settings.sampler, scene_capacity=where.capacity)


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

    @property
    def success(self) -> bool:
        return self.reached and not self.crashed

    def row(self) -> dict[str, object]:
        return {k: v for k, v in dataclasses.asdict(self).items()
                if k not in ("X", "U", "activity", "mean_step_ms")}


def run_episode(where: Where, c: Controls, disturbance: Disturbance, steps: int,
                goal_radius: float, rng_controller: np.random.Generator,
                rng_plant: np.random.Generator, threads: int = 1) -> Outcome:
    """One closed-loop episode; it ends at a crash, within ``goal_radius`` (scaled by the
    system) of the goal, or after ``steps`` steps."""
    nav = setup(where, c.settings)
    ctrl = controller(where, c)
    lib = getattr(getattr(ctrl, "sampler", None), "lib", None)
    if lib is not None:
        lib.set_threads(threads)
    radius = goal_radius * where.spec.scale
    ep = closed_loop(ctrl, nav.plant, nav.x0, steps, rng_controller, rng_plant, disturbance,
                     scene=where.moving(nav.plant.dt), stop_at_goal=radius, goal=nav.goal,
                     check_episode=False)  # the report checks every cell
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
        activity=activity)

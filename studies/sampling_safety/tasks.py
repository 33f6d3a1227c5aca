"""Tasks of the sampling-safety study: one closed-loop episode per (controller, variance,
realisation), with per-step sample statistics.

Common random numbers: a realisation's stream key is (variance, realisation) only, so every
controller meets the same plant disturbances (``ctx.rng(1)``) and draws from the same
controller stream (``ctx.rng(0)``) in realisation j at a variance.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from functools import partial

import numpy as np

from studies.sampling_safety.config import RESULT_VERSION, Resolved, StudyConfig, variance_key
from workbench.sampling.calibration import calibrate
from workbench.sampling.kernels import threads
from workbench.sampling.threshold import Threshold
from workbench.scenarios.maps import generate, scaled
from workbench.scenarios.methods import build, feedback_law, method, slowest_first
from workbench.scenarios.methods.settings import fingerprint as settings_data
from workbench.scenarios.model_system import resolve_system
from workbench.scenarios.navigation import NavigationSetup, navigation_setup
from workbench.sim import Disturbance, closed_loop
from workbench.study import TaskContext, TaskOutput
from workbench.study.cost_pass import CostPlan
from workbench.study.latency import step_table
from workbench.study.spec import Declaration, Finished


@dataclass(frozen=True)
class Realisation:
    controller: str
    variance: float
    realisation: int

    def stream_key(self) -> tuple[int, int]:
        return variance_key(self.variance), self.realisation  # not the controller: CRN

    def columns(self) -> dict[str, object]:
        return {"controller": self.controller, "variance": self.variance,
                "realisation": self.realisation}


_SETUPS: dict = {}


def setup(s: Resolved) -> NavigationSetup:
    """The set-up of ``s`` on the system its name resolves to now (cached per process, per
    settings and per system object: a system registered anew under the same name, e.g. by
    compare_methods, gets its own)."""
    sysm = resolve_system(s.entry)
    key = (s, id(sysm))
    hit = _SETUPS.get(key)
    if hit is None or hit[0] is not sysm:
        scene = (None if s.scene is None else sysm.scaled(s.scene.scene())) \
            if s.family is None else scaled(generate(s.family, s.map_seed), sysm.scale).scene()
        hit = _SETUPS[key] = (sysm, navigation_setup(scene, system=sysm, q_beta=s.q_beta,
                                                     mppi=s.sampler))
    return hit[1]


Thresholds = dict[str, Threshold]


def prepare(config: StudyConfig, out=None) -> Thresholds:
    """Each robust controller's threshold, calibrated once in the coordinating process on an
    undisturbed episode of that controller with its own feedback law."""
    s = config.resolved()
    nav = setup(s)
    return {name: calibrate(s.rule, nav.problem, nav.goal, nav.plant, nav.x0, nav.mppi,
                            feedback_law(nav, method(name).feedback or "", s.methods,
                                         s.feedback), s.robust,
                            seed=config.calibration_seed, progress=nav.progress())
            for name in config.controllers if method(name).robust}


_CONTROLLERS: dict = {}


def controller(s: Resolved, name: str, thresholds: Thresholds):
    key = (s, id(setup(s)), name)
    if key not in _CONTROLLERS:
        _CONTROLLERS[key] = build(setup(s), name, s.methods, threshold=thresholds.get(name),
                                  robust=s.robust, weights=s.feedback)
    return _CONTROLLERS[key]


def disturbance(nav: NavigationSetup, variance: float) -> Disturbance:
    """``variance`` (the double integrator's units) on the system's disturbed states, scaled
    by its level_scale."""
    sysm = nav.system
    return Disturbance(variance * sysm.level_scale, states=sysm.disturbed)


def step_rows(infos) -> dict[str, np.ndarray]:
    """Per control step: samples, collision-free samples, ESS, compute time."""
    st = [i.stats for i in infos]
    return {"step": np.arange(len(st)), "n_samples": np.array([s.n_samples for s in st]),
            "n_collision_free": np.array([s.n_collision_free for s in st]),
            "ess": np.array([s.ess for s in st], dtype=float)}


def activity_rows(infos) -> dict[str, np.ndarray]:
    """Per mechanism of the controller: its mean activity over the episode's steps."""
    keys = sorted({k for i in infos for k in i.stats.activity})
    means = [float(np.mean([i.stats.activity.get(k, 0.0) for i in infos])) for k in keys]
    return {"mechanism": np.array(keys, dtype=str), "activity": np.array(means, dtype=float)}


def run_task(task: Realisation, ctx: TaskContext, config: StudyConfig,
             prepared: Thresholds) -> TaskOutput:
    s = config.resolved()
    nav = setup(s)
    ctrl = controller(s, task.controller, prepared)
    lib = getattr(ctrl.sampler, "lib", None)
    if lib is not None:
        lib.set_threads(ctx.threads)
    ep = closed_loop(ctrl, nav.plant, nav.x0, config.steps, ctx.rng(0), ctx.rng(1),
                     disturbance(nav, task.variance), check_episode=False)  # the report checks
    steps = step_rows(ep.infos)
    dist = nav.goal_distance(ep.X)
    inside = np.flatnonzero(dist <= s.goal_radius)
    cf = steps["n_collision_free"] / np.maximum(steps["n_samples"], 1)
    episode = {"crashed": ep.crashed, "steps": len(ep.U), "final_error": dist[-1],
               "reached": bool(inside.size), "min_h": ep.min_margin,
               "time_to_goal_s": inside[0] * nav.plant.dt if inside.size else np.nan,
               "collision_free_fraction": float(cf.mean()),
               "ess_mean": float(steps["ess"].mean())}
    # compute time is not reproducible: its own tables, as in the navigation study
    per_step = step_table(ep.step_time_s, ep.step_cpu_s)
    timing = {"mean_step_ms": float(per_step["wall_ms"].mean()),
              "median_step_ms": float(np.median(per_step["wall_ms"])),
              "mean_cpu_ms": float(per_step["cpu_ms"].mean())}
    return TaskOutput(tables={"episodes": {k: np.array([v]) for k, v in episode.items()},
                              "timing": {k: np.array([v]) for k, v in timing.items()},
                              "step_times": per_step,
                              "activity": activity_rows(ep.infos)},
                      arrays={"X": ep.X, "U": np.asarray(ep.U), "collision_free": cf,
                              "ess": steps["ess"]})


_RECORDED: dict = {}


def replay(config: StudyConfig, name: str, thresholds: Thresholds, variance: float,
           steps: int) -> Iterator[None]:
    """The cost pass's episode of ``name``: its first ``steps`` steps of realisation 0 at
    ``variance``, one control step per ``next``. The plant's states come from that episode,
    simulated once per process with the realisation's streams; every replay calls the
    controller on them with the controller stream anew, so it does the same work each time."""
    s = config.resolved()
    ctrl = controller(s, name, thresholds)
    ctx = TaskContext("cost-pass", config.seed, Realisation(name, variance, 0).stream_key())
    key = (s, name, variance, steps, config.seed)
    if key not in _RECORDED:
        nav = setup(s)
        _RECORDED[key] = closed_loop(ctrl, nav.plant, nav.x0, steps, ctx.rng(0), ctx.rng(1),
                                     disturbance(nav, variance), keep_infos=False,
                                     check_episode=False).X
    X, rng = _RECORDED[key], ctx.rng(0)
    state = ctrl.initial_state(X[0])
    for k in range(len(X) - 1):
        state, _, _ = ctrl.step(state, X[k], rng)
        yield


def cost_plan(finished: Finished) -> CostPlan:
    """The run's cost pass: every controller on its own episode (:func:`replay`), kernels on
    one thread, in lock step, ``config.cost_rounds`` rounds."""
    config: StudyConfig = finished.config
    v, n = max(config.variances), min(config.cost_steps, config.steps)
    runs = {c: partial(replay, config, c, finished.prepared, v, n) for c in config.controllers}
    return CostPlan(runs, config.cost_rounds, config.seed,
                    f"every method on the first {n} steps of realisation 0 at variance {v:g}, "
                    "in the coordinating process with no episode running, kernels on one "
                    f"thread, in lock step (one step of each method in a random order, then the "
                    f"next), {config.cost_rounds} rounds after a warm-up round",
                    setting=partial(threads.using, 1))


@dataclass(frozen=True)
class Plan:
    tasks: tuple[Realisation, ...]
    cells: dict[tuple[str, float], tuple[Realisation, ...]]


def plan(config: StudyConfig) -> Plan:
    cells = {(c, v): tuple(Realisation(c, v, j) for j in range(config.realisations))
             for v in config.variances for c in config.controllers}
    order = slowest_first()
    tasks = sorted((t for ts in cells.values() for t in ts),
                   key=lambda t: (order.index(t.controller), t.variance, t.realisation))
    return Plan(tuple(tasks), cells)


def fingerprint(config: StudyConfig) -> dict:
    """What results depend on: the resolved settings and, for a system other than the double
    integrator, the numbers of its definition."""
    s = config.resolved()
    d = settings_data(config)
    for k in ("controllers", "variances", "realisations", "seed", "system", "cost_rounds",
              "cost_steps"):  # the cost pass's sizes change no episode
        d.pop(k)
    d.pop("family")
    d.pop("map_seed")
    if s.family is not None:  # a generated map's family and seed, only when one is used
        d.update(family=settings_data(s.family), map_seed=s.map_seed)
    d.update({k: settings_data(getattr(s, k)) if hasattr(getattr(s, k), "__dataclass_fields__")
              else getattr(s, k) for k in ("scene", "sampler", "q_beta", "feedback",
                                           "goal_radius")})
    if s.system != "double_integrator":
        d["system"] = system_values(resolve_system(s.entry))
    return d


def system_values(sysm) -> dict:
    """The numbers of a system's definition that results depend on, with its model's
    expressions (a change to them must not reuse stored episodes)."""
    out = {k: getattr(sysm, k) for k in ("name", "Q", "S", "sigma", "lam", "q_beta",
                                         "disturbed", "scale", "level_scale", "cost_form",
                                         "horizon", "goal_radius", "state_scale")}
    if sysm.scene is not None:
        m = sysm.model(obstacles=sysm.scene.obstacles(), dt=sysm.scene.dt, u_limit=None,
                       scene_capacity=None, runtime_obstacles=True)
        out.update(start=list(sysm.scene.start), goal=list(sysm.scene.goal),
                   model=[str(m.x_next), str(m.h), list(m.u_min), list(m.u_max), m.dt])
    return out


def declare(config: StudyConfig) -> Declaration:
    p = plan(config)
    return Declaration(p.tasks, run_task, fingerprint(config), RESULT_VERSION, p)

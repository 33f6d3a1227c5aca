"""The study's tasks, the pure task function, and the plan (which tasks make up which cell).

Common random numbers: a :class:`Realisation`'s stream key is (variance, realisation j) and
nothing else, so the controller stream ``ctx.rng(0)`` and the plant-disturbance stream
``ctx.rng(1)`` of realisation j at a variance are the same for every controller and alpha rule.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from functools import cache

import numpy as np

from studies.navigation.config import RESULT_VERSION, ROBUST, StudyConfig, variance_key
from studies.navigation.illustration import illustrate
from studies.navigation.metrics import episode_row, timing_row, velocity_rows
from studies.navigation.scene import MapSpec
from workbench.sampling.calibration import calibrate, calibration_trace
from workbench.sampling.feedback import FeedbackWeights
from workbench.sampling.mppi import MPPIConfig
from workbench.sampling.robust import RMPPIConfig
from workbench.sampling.threshold import AlphaRule, Threshold
from workbench.scenarios.navigation import NavigationSetup, navigation_setup
from workbench.sim import Disturbance, closed_loop
from workbench.study import TaskContext, TaskOutput
from workbench.study.latency import step_table
from workbench.study.spec import Declaration

NO_RULE = AlphaRule(kind="fixed")  # placeholder rule of the MPPI controllers (no selection)
ILLUSTRATION_KEY = 2**32 - 1  # stream word of the Fig. 4 task (one word: no episode has it)


def rule_label(controller: str, rule: AlphaRule) -> str:
    return rule.label() if controller in ROBUST else "-"


@dataclass(frozen=True)
class Realisation:
    """Realisation j of one controller (with its alpha rule) at one disturbance variance."""

    controller: str
    rule: AlphaRule
    variance: float
    realisation: int

    def stream_key(self) -> tuple[int, int]:
        return variance_key(self.variance), self.realisation  # not the controller: CRN

    def columns(self) -> dict[str, object]:
        return {"controller": self.controller, "rule": rule_label(self.controller, self.rule),
                "variance": self.variance, "realisation": self.realisation}


@dataclass(frozen=True)
class Illustration:
    """Fig. 4: one SAIS batch of SA-RMPPI with limits +-u_limit under velocity variance."""

    rule: AlphaRule
    variance: float = 5000.0
    u_limit: float = 50.0
    steps: int = 60

    def stream_key(self) -> tuple[int]:
        return (ILLUSTRATION_KEY,)


@dataclass(frozen=True)
class Controllers:
    """The config's controller settings, as one hashable key for the per-process caches."""

    scene: MapSpec
    sampler: MPPIConfig
    q_beta: float
    robust: RMPPIConfig
    feedback: FeedbackWeights

    @classmethod
    def of(cls, config: StudyConfig, scene: MapSpec | None = None) -> Controllers:
        return cls(scene or config.scene, config.sampler, config.q_beta, config.robust,
                   config.feedback)


@cache
def setup(c: Controllers) -> NavigationSetup:
    """One navigation set-up per process, map and settings."""
    return navigation_setup(c.scene.scene(), q_beta=c.q_beta, mppi=c.sampler)


def illustration_map(scene: MapSpec, task: Illustration) -> MapSpec:
    """The Fig. 4 map: the study's map with the illustration's control limits."""
    return MapSpec(scene.start, scene.goal, scene.seed, scene.circles, task.u_limit)


def feedback_kind(controller: str) -> str:
    """K_safe (BaS-iLQG gains) for SA-RMPPI, plain iLQG gains for RMPPI."""
    return "bas_ilqg" if controller == "sa_rmppi" else "ilqg"


Thresholds = dict[tuple[Controllers, str, AlphaRule], Threshold]


def prepare(config: StudyConfig, out=None) -> Thresholds:
    """Every alpha rule a run uses, calibrated once (in the coordinating process) on the
    controller that uses it, with ``config.calibration_seed``: (settings, controller, rule) ->
    threshold. Rules of one controller with the same calibration length share one episode."""
    p = plan(config)
    needed = dict.fromkeys((Controllers.of(config), t.controller, t.rule)
                           for t in p.tasks if isinstance(t, Realisation)
                           and t.controller in ROBUST)
    if p.illustration is not None:
        big = Controllers.of(config, illustration_map(config.scene, p.illustration))
        needed[(big, "sa_rmppi", p.illustration.rule)] = None
    traces: dict = {}
    out_: Thresholds = {}
    for c, name, rule in needed:
        nav, kind = setup(c), feedback_kind(name)
        key = (c, kind, rule.calibration_steps)
        if rule.needs_calibration and key not in traces:  # the feedback law is built only here
            traces[key] = calibration_trace(
                nav.problem, nav.goal, nav.plant, nav.x0, nav.mppi,
                nav.feedback(kind, c.feedback), c.robust, steps=rule.calibration_steps,
                seed=config.calibration_seed)
        out_[(c, name, rule)] = calibrate(rule, nav.problem, nav.goal, nav.plant, nav.x0,
                                          nav.mppi, None, c.robust, trace=traces.get(key))
    return out_


_CONTROLLERS: dict = {}


def controller(c: Controllers, name: str, rule: AlphaRule, thresholds: Thresholds):
    """One controller per process and key; controllers keep no state between episodes."""
    key = (c, name, rule)
    if key not in _CONTROLLERS:
        _CONTROLLERS[key] = setup(c).controller(
            name, rule, c.robust, c.feedback, threshold=thresholds.get(key))
    return _CONTROLLERS[key]


def run_task(task: Realisation | Illustration, ctx: TaskContext, config: StudyConfig,
             prepared: Thresholds) -> TaskOutput:
    scene = config.scene
    if isinstance(task, Illustration):
        big = Controllers.of(config, illustration_map(scene, task))
        return illustrate(setup(big), controller(big, "sa_rmppi", task.rule, prepared), task,
                          ctx)
    c = Controllers.of(config)
    nav = setup(c)
    ctrl = controller(c, task.controller, task.rule, prepared)
    if ctrl.sampler.lib is not None:
        ctrl.sampler.lib.set_threads(ctx.threads)
    ep = closed_loop(ctrl, nav.plant, nav.x0, config.steps, ctx.rng(0), ctx.rng(1),
                     Disturbance(task.variance), check_episode=False)  # no warning per episode
    dt = nav.plant.dt
    tables = {"episodes": episode_row(ep, nav.goal, dt, config.goal_radius,
                                      scene.circle_array()),
              "velocity": velocity_rows(ep, dt, config.velocity_stride),
              "timing": timing_row(ep),
              "step_times": step_table(ep.step_time_s, ep.step_cpu_s)}
    return TaskOutput(tables=tables, arrays={"X": ep.X, "U": np.asarray(ep.U)})


@dataclass(frozen=True)
class Plan:
    """Tasks in dispatch order (slow first); main cells and the alpha-sweep cells."""

    tasks: tuple[Realisation | Illustration, ...]
    main: dict[tuple[str, float], tuple[Realisation, ...]]
    sweep: dict[tuple[str, float], tuple[Realisation, ...]]  # (rule label, variance)
    illustration: Illustration | None


SPEED = {"sa_rmppi": 0, "rmppi": 1, "bas_mppi": 2, "mppi_crash": 3}  # slowest first


def plan(config: StudyConfig) -> Plan:
    def rule(c: str) -> AlphaRule:
        return config.rule if c in ROBUST else NO_RULE

    main = {(c, v): tuple(Realisation(c, rule(c), v, j) for j in range(config.realisations))
            for v in config.variances for c in config.controllers}
    sc = config.sweep_controller
    sweep = {(r.label(), v): tuple(Realisation(sc, r, v, j)
                                   for j in range(config.sweep_realisations))
             for v in config.sweep_variances for r in (config.rule, *config.sweep_rules)}
    unique = dict.fromkeys(t for ts in (*main.values(), *sweep.values()) for t in ts)
    ordered = sorted(unique, key=lambda t: (SPEED[t.controller], t.variance, t.realisation))
    illu = (Illustration(config.rule, steps=config.illustration_steps)
            if config.illustration else None)
    tasks = ((illu,) if illu else ()) + tuple(ordered)
    return Plan(tasks, main, sweep, illu)


def fingerprint(config: StudyConfig) -> dict:
    """Every input results depend on beyond the task descriptions."""
    return {"scene": asdict(config.scene), "steps": config.steps,
            "goal_radius": config.goal_radius, "velocity_stride": config.velocity_stride,
            "mppi": asdict(config.sampler), "q_beta": config.q_beta,
            "robust": asdict(config.robust), "feedback": asdict(config.feedback),
            "calibration_seed": config.calibration_seed}


def declare(config: StudyConfig) -> Declaration:
    p = plan(config)
    return Declaration(p.tasks, run_task, fingerprint(config), RESULT_VERSION, p)

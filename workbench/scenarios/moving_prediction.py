"""Does predicting a moving obstacle help? A paired experiment on the moving-obstacle example.

The scene of ``examples/moving_obstacle.py``: a planar double integrator drives from (0, 0) to
(4, 4) past two fixed circles while a circle of radius 0.45 m crosses its straight-line path,
timed to reach the diagonal at (2, 2) after 1.13 s, here at ``speed`` m/s (it stops after
4.5 s). The model is built with a :class:`~workbench.problem.scene_layout.SceneLayout` of two
circle slots and one moving slot, and BaS-MPPI runs in two arms on the same kernels:

* ``predicted``: each step the controller gets the circle's true position and velocity
  (:class:`~workbench.problem.scene_kinds.MovingCircle`) and its rollouts see it at c + v t;
* ``present``: the same position with the velocity zeroed (the circle held where it is over the
  horizon, as controllers without prediction do).

The plant checks crashes against the circle's true position in both arms. Seed i gives both
arms the same controller and plant generators (spawned from ``SeedSequence([base_seed, i])``),
so the arms are paired. :func:`run_trial` reports the crashes per arm, the discordant pairs,
the exact McNemar test (statsmodels), the paired difference in crash rate (present minus
predicted) with Newcombe's 95 % score interval for paired proportions (Newcombe 1998, method
10, :func:`~workbench.study.stats.paired_difference_interval`), and whether prediction acted:
on the predicted arm, along each step's chosen plan (the applied control then the shifted
plan, rolled out on the model), the share of steps on which the smallest margin of the plan
differs between the predicted scenes and the present one by more than ``MARGIN_DIFF``.

    python -m workbench.scenarios.moving_prediction [--seeds 30] [--speed 0.7]
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np

from workbench.problem.barrier import embed_barrier
from workbench.problem.models import Model, double_integrator
from workbench.problem.obstacles import Circle
from workbench.problem.prediction import step_scenes
from workbench.problem.scene_kinds import MovingCircle
from workbench.problem.scene_layout import SceneLayout
from workbench.sampling.mppi import MPPI, MPPIConfig
from workbench.sampling.problem import navigation_costs
from workbench.sampling.samples import Keep
from workbench.sim import closed_loop
from workbench.study.stats import paired_counts, paired_difference_interval
from workbench.validation import fail, integer, real

START, GOAL = np.array([0.0, 0.0, 0.0, 0.0]), np.array([4.0, 4.0, 0.0, 0.0])
FIXED = (Circle((1.0, 2.8), 0.4), Circle((3.3, 2.0), 0.4))
RADIUS = 0.45  # m, the moving circle's
MEET_S = 1.13  # s, when the moving circle's centre crosses (2, 2)
STOP_S = 4.5  # s, when it stops
DIRECTION = np.array([-1.0, 1.0]) / np.sqrt(2.0)
LAYOUT = SceneLayout.of(circles=len(FIXED), moving=1)
ARMS = ("predicted", "present")
MARGIN_DIFF = 0.01  # m^2: a plan's smallest margin "differs" between the scenes beyond this


@dataclass(frozen=True)
class TrialConfig:
    """``seeds`` paired episodes (seed i = 0 .. seeds - 1 of ``base_seed``), the moving circle
    at ``speed`` m/s, ``steps`` plant steps of ``dt`` s; BaS-MPPI with ``mppi`` (the example's
    settings by default)."""

    seeds: int = 30
    speed: float = 0.7
    steps: int = 250
    dt: float = 0.02
    base_seed: int = 2026
    mppi: MPPIConfig = MPPIConfig(n_samples=256, horizon=40, sigma=(5.0, 5.0), lam=10.0)

    def __post_init__(self) -> None:
        integer("TrialConfig.seeds", self.seeds, 1, 10_000)
        real("TrialConfig.speed", self.speed, 0.0, maximum=100.0)
        integer("TrialConfig.steps", self.steps, 1, 100_000)
        real("TrialConfig.dt", self.dt, 0.0, strict=True, maximum=1.0)
        integer("TrialConfig.base_seed", self.base_seed, 0)
        if not isinstance(self.mppi, MPPIConfig):
            raise fail("TrialConfig.mppi", self.mppi, "must be an MPPIConfig")


def moving_circle(k: int, dt: float, speed: float, told: bool) -> MovingCircle:
    """The crossing circle at step k: its true centre, and its true velocity when ``told``
    (zero when not, and after it stops)."""
    t = min(k * dt, STOP_S)
    c = np.array([2.0, 2.0]) + (t - MEET_S) * speed * DIRECTION
    v = speed * DIRECTION if told and k * dt < STOP_S else np.zeros(2)
    return MovingCircle((float(c[0]), float(c[1])), RADIUS, (float(v[0]), float(v[1])))


def trial_scene(dt: float, speed: float, told: bool) -> Callable[[int], tuple]:
    """``k -> scene`` for ``closed_loop``: the fixed circles and the crossing one."""
    return lambda k: (*FIXED, moving_circle(k, dt, speed, told))


def trial_model(dt: float, speed: float) -> Model:
    """The plant: the double integrator with the trial's layout (2 circles, 1 moving), its
    own scene that of time 0."""
    return double_integrator(dt=dt, scene_layout=LAYOUT,
                             obstacles=trial_scene(dt, speed, True)(0), u_limit=15.0)


@dataclass(frozen=True)
class ArmResult:
    crashed: tuple[bool, ...]  # per seed
    min_margin: tuple[float, ...]  # closest approach per seed (m^2, squared-distance margin)
    steps: tuple[int, ...]  # plant steps per seed (fewer: crashed)


@dataclass(frozen=True)
class TrialResult:
    """Crashes per arm, the paired comparison and the mechanism check (see the module)."""

    config: dict
    arms: dict[str, ArmResult]
    crashes: dict[str, int]
    discordant: dict[str, int]  # only_present_crashed, only_predicted_crashed
    mcnemar_p: float  # exact, two-sided (statsmodels)
    difference: float  # crash rate present minus predicted
    low: float  # 95 % interval of the difference (Newcombe's score interval, paired)
    high: float
    interval: str
    plan_margin_differs: float  # share of predicted-arm steps (see MARGIN_DIFF)
    plan_margin_diff_mean: float  # mean |min_j h_pred - min_j h_present| along the plans (m^2)

    def as_dict(self) -> dict:
        return asdict(self)


class _PlanRecorder:
    """BaS-MPPI that keeps, per step, the state it planned from, its scene and the chosen
    plan (the applied control, then the shifted plan)."""

    def __init__(self, ctrl: MPPI):
        self.ctrl = ctrl
        self.plans: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def initial_state(self, x0: np.ndarray | None = None):
        return self.ctrl.initial_state(x0)

    def set_scene(self, scene) -> None:
        self.ctrl.set_scene(scene)

    def record_samples(self, k: int = 64, keep: Keep = "spread") -> None:
        self.ctrl.record_samples(k, keep)

    def step(self, state, x, rng):
        new, u, info = self.ctrl.step(state, x, rng)
        plan = np.vstack([np.asarray(u, float)[None], new.U[:-1]])
        self.plans.append((np.asarray(x, float).copy(), self.ctrl.consts.scene.copy(), plan))
        return new, u, info


def _plan_margins(model: Model, x, scene, plan) -> tuple[float, float]:
    """Smallest margin along the plan's states x_1..x_T: in the predicted scenes, and in the
    present one."""
    T = plan.shape[0]
    X = np.empty((T + 1, 4))
    X[0] = x[:4]
    for k in range(T):  # the Euler double integrator (positions do not depend on the scene)
        X[k + 1] = np.r_[X[k, :2] + model.dt * X[k, 2:], X[k, 2:] + model.dt * plan[k]]
    S = step_scenes(model, scene, T)
    pred = min(float(np.min(LAYOUT.numpy_margins(X[k + 1, :2], S[:, k]))) for k in range(T))
    now = float(np.min(LAYOUT.numpy_margins(X[1:, :2], scene)))
    return pred, now


def run_trial(config: TrialConfig = TrialConfig()) -> TrialResult:
    """Run both arms on ``config.seeds`` paired seeds (see the module)."""
    from statsmodels.stats.contingency_tables import mcnemar

    if not isinstance(config, TrialConfig):
        raise fail("config", config, "must be a TrialConfig")
    model = trial_model(config.dt, config.speed)
    sp = navigation_costs(embed_barrier(model), q_beta=0.01)
    ctrl = _PlanRecorder(MPPI(sp, GOAL, config.mppi))
    out: dict[str, dict[str, list]] = {a: {"crashed": [], "min_margin": [], "steps": []}
                                        for a in ARMS}
    diffs: list[float] = []
    for i in range(config.seeds):
        for arm in ARMS:
            rc, rp = (np.random.default_rng(s) for s in
                      np.random.SeedSequence([config.base_seed, i]).spawn(2))
            ctrl.plans = []
            ep = closed_loop(ctrl, model, START, config.steps, rc, rp, keep_infos=False,
                             scene=trial_scene(config.dt, config.speed, arm == "predicted"))
            out[arm]["crashed"].append(bool(ep.crashed))
            out[arm]["min_margin"].append(float(ep.min_margin))
            out[arm]["steps"].append(len(ep.U))
            if arm == "predicted":
                for x, scene, plan in ctrl.plans:
                    pred, now = _plan_margins(model, x, scene, plan)
                    diffs.append(abs(pred - now))
    arms = {a: ArmResult(tuple(v["crashed"]), tuple(v["min_margin"]), tuple(v["steps"]))
            for a, v in out.items()}
    safe_pred = ~np.array(arms["predicted"].crashed)
    safe_now = ~np.array(arms["present"].crashed)
    a, b, c, d = paired_counts(safe_pred, safe_now)  # b: only predicted safe
    table = np.array([[a, b], [c, d]])
    p = float(mcnemar(table, exact=True).pvalue)
    diff, low, high = paired_difference_interval(a, b, c, d)
    dd = np.asarray(diffs)
    return TrialResult(
        config={"seeds": config.seeds, "speed": config.speed, "steps": config.steps,
                "dt": config.dt, "base_seed": config.base_seed,
                "n_samples": config.mppi.n_samples, "horizon": config.mppi.horizon},
        arms=arms, crashes={arm: int(sum(arms[arm].crashed)) for arm in ARMS},
        discordant={"only_present_crashed": b, "only_predicted_crashed": c}, mcnemar_p=p,
        difference=diff, low=low, high=high,
        interval="Newcombe (1998) method 10 score interval for paired proportions, 95 %",
        plan_margin_differs=float(np.mean(dd > MARGIN_DIFF)) if dd.size else 0.0,
        plan_margin_diff_mean=float(np.mean(dd)) if dd.size else 0.0)


def main(argv: list[str] | None = None) -> TrialResult:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=30)
    ap.add_argument("--speed", type=float, default=0.7)
    ap.add_argument("--base-seed", type=int, default=2026)
    args = ap.parse_args(argv)
    res = run_trial(TrialConfig(seeds=args.seeds, speed=args.speed, base_seed=args.base_seed))
    d = res.as_dict()
    d["arms"] = {k: {"crashed_seeds": [i for i, c in enumerate(v["crashed"]) if c]}
                 for k, v in d["arms"].items()}
    print(json.dumps(d))
    return res


if __name__ == "__main__":
    main()

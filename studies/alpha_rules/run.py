"""Episodes on the paper map per (controller, alpha rule, variance), on the study framework.

Common random numbers: a task's streams are keyed by (variance, realisation) only, so
realisation j at variance v sees the same plant disturbance and controller noise seeds for every
controller and rule.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workbench.sampling.threshold import AlphaRule
from workbench.scenarios.navigation import navigation_setup
from workbench.sim import Disturbance, closed_loop
from workbench.study import Study, TaskContext, TaskOutput

RULES = {
    "progress_k0.1": AlphaRule(kappa=0.1),
    "progress_k0": AlphaRule(kappa=0.0),
    "progress_k0.25": AlphaRule(kappa=0.25),
    "quantile_q0.9": AlphaRule(kind="quantile", quantile=0.9),
    "start_x1.5": AlphaRule(kind="start", factor=1.5),
}
DEFAULT_RULE = "progress_k0.1"


@dataclass(frozen=True)
class Episode:
    controller: str
    rule: str  # key of RULES ("-" for BaS-MPPI)
    variance: float
    episode: int
    steps: int

    def stream_key(self) -> tuple[int, ...]:
        return (round(self.variance * 1000), self.episode)


def tasks(episodes: int, steps: int, variances) -> tuple[Episode, ...]:
    out = []
    for v in variances:
        cells = [("sa_rmppi", r) for r in RULES] + [("rmppi", DEFAULT_RULE), ("bas_mppi", "-")]
        out += [Episode(c, r, float(v), j, steps) for c, r in cells for j in range(episodes)]
    return tuple(out)


_NAV = {}


def run_episode(task: Episode, ctx: TaskContext) -> TaskOutput:
    if "nav" not in _NAV:
        _NAV["nav"] = navigation_setup()
    nav = _NAV["nav"]
    ctrl = nav.controller(task.controller, RULES.get(task.rule, AlphaRule()))
    if ctrl.sampler.lib is not None:
        ctrl.sampler.lib.set_threads(ctx.threads)
    ep = closed_loop(ctrl, nav.plant, nav.x0, task.steps, ctx.rng(0), ctx.rng(1),
                     Disturbance(task.variance))
    inf = ep.infos
    robust = task.controller != "bas_mppi"

    def count(attr):
        return int(sum(bool(getattr(i, attr)) for i in inf)) if robust else 0

    reasons = sorted({i.ksafe_fallback for i in inf if robust and i.ksafe_fallback})
    row = {"crashed": ep.crashed, "n_steps": len(inf),
           "final_error": float(np.linalg.norm(ep.X[-1, :2] - nav.goal[:2])),
           "nominal_differs": count("nominal_differs"), "alpha_fallback": count("fallback_used"),
           "ksafe_fallback": count("ksafe_fallback"), "ksafe_reasons": ",".join(reasons),
           "nominal_unsafe": count("nominal_unsafe"),
           "step_ms": float(1e3 * np.mean(ep.step_time_s))}
    return TaskOutput(tables={"episodes": {k: np.array([v]) for k, v in row.items()}},
                      arrays={"path": ep.X[:, :2]})


def study(episodes: int, steps: int, seed: int, variances) -> Study:
    return Study("alpha_rules", tasks(episodes, steps, variances), run_episode, seed=seed,
                 config={"episodes": episodes, "steps": steps, "variances": list(variances)},
                 fingerprint={"rules": {k: repr(v) for k, v in RULES.items()}})

"""Episodes on the paper map for each (controller, alpha rule, variance), common random numbers.

Episode j at variance v uses the plant-noise stream SeedSequence((seed, round(v*1000), j)) and
the controller stream SeedSequence((seed, j)) for every controller, so controllers are compared
on the same disturbance realisations.
"""

from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np

from workbench.navigation import navigation_setup
from workbench.sampling.threshold import AlphaRule
from workbench.sim import Disturbance, closed_loop

RULES = {
    "progress_k0.1": AlphaRule(kappa=0.1),
    "progress_k0": AlphaRule(kappa=0.0),
    "progress_k0.25": AlphaRule(kappa=0.25),
    "quantile_q0.9": AlphaRule(kind="quantile", quantile=0.9),
    "start_x1.5": AlphaRule(kind="start", factor=1.5),
}
DEFAULT_RULE = "progress_k0.1"


@dataclass(frozen=True)
class Cell:
    controller: str
    rule: str  # key of RULES ("-" for BaS-MPPI)
    variance: float


def cells(variances=(10.0, 100.0)) -> list[Cell]:
    out = []
    for v in variances:
        out += [Cell("sa_rmppi", r, v) for r in RULES]
        out += [Cell("rmppi", DEFAULT_RULE, v), Cell("bas_mppi", "-", v)]
    return out


_NAV = None


def _episode(args) -> dict:
    cell, j, seed, steps = args
    global _NAV
    if _NAV is None:
        _NAV = navigation_setup()
    nav = _NAV
    rule = RULES.get(cell.rule, AlphaRule())
    ctrl = nav.controller(cell.controller, rule)
    ctrl.sampler.lib.set_threads(1)
    rng_c = np.random.default_rng(np.random.SeedSequence((seed, j)))
    rng_w = np.random.default_rng(np.random.SeedSequence((seed, round(cell.variance * 1000), j)))
    ep = closed_loop(ctrl, nav.plant, nav.x0, steps, rng_c, rng_w, Disturbance(cell.variance))
    inf = ep.infos
    robust = cell.controller != "bas_mppi"
    reasons = [i.ksafe_fallback for i in inf if robust and i.ksafe_fallback]
    return {
        "controller": cell.controller, "rule": cell.rule, "variance": cell.variance,
        "episode": j, "crashed": bool(ep.crashed), "steps": len(inf),
        "final_error": float(np.linalg.norm(ep.X[-1, :2] - nav.goal[:2])),
        "nominal_differs": int(sum(i.nominal_differs for i in inf)) if robust else 0,
        "alpha_fallback": int(sum(i.fallback_used for i in inf)) if robust else 0,
        "ksafe_fallback": len(reasons),
        "ksafe_reasons": ",".join(sorted(set(reasons))),
        "nominal_unsafe": int(sum(i.nominal_unsafe for i in inf)) if robust else 0,
        "step_ms": float(1e3 * np.mean(ep.step_time_s)),
        "path": ep.X[:, :2],
    }


def run(episodes: int, seed: int, steps: int, workers: int, variances) -> list[dict]:
    jobs = [(c, j, seed, steps) for c in cells(variances) for j in range(episodes)]
    with ProcessPoolExecutor(workers) as pool:
        return list(pool.map(_episode, jobs, chunksize=1))

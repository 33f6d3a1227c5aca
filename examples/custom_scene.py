"""A scene of your own circles through SA-RMPPI.

Five circles between start and goal (``CircleScene``), the navigation set-up on it (double
integrator, barrier state, sampling costs of
assumptions §8.2), SA-RMPPI with K_safe from BaS-iLQG whose
feedback weights are sized from the model (``FeedbackWeights.for_model``), its selection
threshold calibrated once on this map (``nav.threshold``: one undisturbed episode), then one
disturbed episode (velocity variance 10) against BaS-MPPI with the same disturbance.

    .venv/bin/python examples/custom_scene.py
"""

from __future__ import annotations

import numpy as np

import workbench as wb
from workbench.scenarios.navigation import TUNED_LAMBDA, TUNED_SIGMA

SCENE = wb.CircleScene.from_circles(
    [(1.8, 1.6, 0.5), (3.0, 3.2, 0.6), (1.2, 3.4, 0.5), (3.6, 1.4, 0.45), (4.4, 4.2, 0.4)],
    start=(0.5, 0.5), goal=(5.0, 5.0))
RULE = wb.AlphaRule(kappa=0.1, calibration_steps=300)


def run(name: str, nav: wb.NavigationSetup, threshold, weights: wb.FeedbackWeights, steps: int,
        seed: int, variance: float) -> dict:
    ctrl = nav.controller(name, RULE, weights=weights, threshold=threshold)
    ep = wb.closed_loop(ctrl, nav.plant, nav.x0, steps, np.random.default_rng(seed),
                        np.random.default_rng(seed + 1), wb.Disturbance(variance))
    robust = [i.nominal_differs for i in ep.infos if hasattr(i, "nominal_differs")]
    return {"crashed": bool(ep.crashed), "steps": len(ep.U), "min_h": float(ep.min_margin),
            "final_error": float(np.linalg.norm(ep.X[-1, :2] - nav.goal[:2])),
            "robust_active": float(np.mean(robust)) if robust else 0.0}


def main(steps: int = 350, seed: int = 11, variance: float = 10.0) -> dict:
    wb.set_threads(2)
    nav = wb.navigation_setup(SCENE, mppi=wb.MPPIConfig(n_samples=256, horizon=50,
                                                        sigma=TUNED_SIGMA, lam=TUNED_LAMBDA))
    weights = wb.FeedbackWeights.for_model(nav.plant, q=300.0)
    threshold = nav.threshold(RULE, "bas_ilqg", weights=weights)  # once, for every SA-RMPPI
    out = {name: run(name, nav, threshold, weights, steps, seed, variance)
           for name in ("sa_rmppi", "bas_mppi")}
    for name, r in out.items():
        print(f"{name:9s} crashed {r['crashed']}, {r['steps']} steps, min h {r['min_h']:.3f}, "
              f"final error {r['final_error']:.3f} m, robust part active "
              f"{100 * r['robust_active']:.0f}% of steps")
    return out


if __name__ == "__main__":
    main()

"""The three controllers' nominal solutions (assumptions §6.1-§6.3) on the tracking scene
(assumptions §3.3)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from studies.tracking_comparison.config import METHODS, Variant
from workbench.filters.ecbf import ECBFOptions, ecbf_rows
from workbench.ilqg import ILQGOptions, ilqg
from workbench.ilqg.al import ALOptions, al_ilqg, al_problem
from workbench.ilqg.bas import TrackingWeights, bas_ilqg, tracking_params, tracking_problem
from workbench.problem.barrier import BarrierOptions
from workbench.problem.models import Model, double_integrator
from workbench.scenarios.scenes import TrackingScene
from workbench.validation import one_of


@dataclass(frozen=True)
class Setup:
    """Values held fixed across the sweep (each [A] unless the paper says otherwise)."""

    scene: TrackingScene = field(default_factory=TrackingScene)
    weights: TrackingWeights = field(default_factory=TrackingWeights)
    barrier: BarrierOptions = field(default_factory=BarrierOptions)
    ecbf: ECBFOptions = field(default_factory=ECBFOptions)
    al: ALOptions = field(default_factory=ALOptions)
    ilqg: ILQGOptions = field(default_factory=ILQGOptions)

    def model(self, *, obstacle: bool = True) -> Model:
        """Euler double integrator (assumptions §2.2) with the scene's obstacle, or with none."""
        obstacles = (self.scene.obstacle,) if obstacle else ()
        return double_integrator(dt=self.scene.dt, obstacles=obstacles,
                                 u_limit=self.scene.u_limit)

    def weights_for(self, variant: Variant) -> TrackingWeights:
        Q = tuple(variant.q_scale * q for q in self.weights.Q)
        return replace(self.weights, Q=Q, q_beta=variant.q_beta)

    def ecbf_for(self, variant: Variant) -> ECBFOptions:
        return replace(self.ecbf, poles=(variant.pole, variant.pole))

    def fixed(self) -> dict[str, str]:
        """Text form of every fixed input, for task keys and the report."""
        return {name: repr(getattr(self, name))
                for name in ("scene", "weights", "barrier", "ecbf", "al", "ilqg")}


@dataclass(frozen=True)
class Nominal:
    """A method's planned trajectory and feedback policy. X (T+1, nx) with nx = 5 for BaS
    (x and the barrier state), U (T, nu), K (T, nu, nx); info: solver diagnostics."""

    method: str
    X: np.ndarray
    U: np.ndarray
    K: np.ndarray
    info: dict


def solve_nominal(method: str, variant: Variant, setup: Setup) -> Nominal:
    """ECBF: iLQG without the obstacle; AL: AL-iLQG; BaS: BaS-iLQG (all from U = 0)."""
    one_of("method", method, METHODS)
    sc = setup.scene
    ref, x0, target = sc.reference(), np.array(sc.start), np.array(sc.target)
    weights = setup.weights_for(variant)
    U0 = np.zeros((sc.horizon, 2))
    model = setup.model()
    if method == "bas":
        res, _ = bas_ilqg(model, x0, ref, target, U0, weights=weights, barrier=setup.barrier,
                          options=setup.ilqg)
        info = {"cost": res.cost, "converged": res.converged, "iterations": res.iterations,
                "solve_time_s": res.solve_time_s}
        return Nominal(method, res.X, res.U, res.K, info)
    if method == "al":
        plain = tracking_problem(model, weights)
        P = tracking_params(plain, ref, target)
        res = al_ilqg(al_problem(model, plain.cost), x0, U0, P, setup.al)
        info = {"cost": res.cost, "converged": res.converged, "iterations": res.inner_iterations,
                "outer_iterations": len(res.history), "max_violation": res.max_violation,
                "solve_time_s": res.solve_time_s}
        return Nominal(method, res.X, res.U, res.K, info)
    free = tracking_problem(setup.model(obstacle=False), weights)
    res = ilqg(free, x0, U0, tracking_params(free, ref, target), setup.ilqg)
    lie = ecbf_rows(model, setup.ecbf_for(variant)).lie
    h, lfh = (float(np.asarray(v).ravel()[0]) for v in lie(x0, model.scene_value)[:2])
    info = {"cost": res.cost, "converged": res.converged, "iterations": res.iterations,
            "solve_time_s": res.solve_time_s,
            # initial-condition requirement (assumptions §7.1): h(x0) >= 0, dh(x0) + p1 h(x0) >= 0
            "ecbf_initial_condition_ok": bool(h >= 0 and lfh + variant.pole * h >= 0)}
    return Nominal(method, res.X, res.U, res.K, info)

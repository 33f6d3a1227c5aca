"""Tracking problems of assumptions §6 and BaS-iLQG (assumptions §6.1): iLQG on the
barrier-embedded problem."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workbench.ilqg import ILQGOptions, ILQGResult, ilqg
from workbench.problem.barrier import BarrierOptions, embed_barrier
from workbench.problem.costs import BetaCost, quadratic_tracking
from workbench.problem.models import Model
from workbench.problem.problem import Problem
from workbench.validation import as_array, fail, real


@dataclass(frozen=True)
class TrackingWeights:
    """Tracking weights (diagonals). Defaults assumptions §6 [A]: Q=diag(10,10,1,1), R=1e-3 I,
    S=diag(1e3,1e3,1e2,1e2); barrier weights q_beta=1e-2 (swept 1e-3..1) and s_beta=0.05."""

    Q: tuple[float, ...] = (10.0, 10.0, 1.0, 1.0)
    R: tuple[float, ...] = (1e-3, 1e-3)
    S: tuple[float, ...] = (1e3, 1e3, 1e2, 1e2)
    q_beta: float = 1e-2
    s_beta: float = 0.05
    beta_cost: BetaCost = "relative"

    def __post_init__(self) -> None:
        for name in ("Q", "R", "S"):
            w = np.asarray(getattr(self, name), dtype=float)
            if w.ndim != 1 or not np.all(np.isfinite(w)) or np.any(w < 0):
                raise fail(f"TrackingWeights.{name}", w, "must be finite diagonal entries >= 0")
            object.__setattr__(self, name, tuple(float(v) for v in w))
        for name in ("q_beta", "s_beta"):
            real(f"TrackingWeights.{name}", getattr(self, name), 0.0)

    @classmethod
    def for_model(cls, model: Model, *, state_scale=None, control_scale=None,
                  terminal: float = 100.0, **kw) -> TrackingWeights:
        """Weights sized to ``model``'s physical states and controls: Q_i = 1 / s_i^2 with
        ``state_scale`` s (default 1 per state), R_j = 1e-3 / c_j^2 with ``control_scale`` c
        (default the half-width of control j's box, 1 where it is unbounded), S = ``terminal``
        Q; other fields (q_beta, s_beta, beta_cost) through ``kw``. With s = (1, 1, sqrt 10,
        sqrt 10) and c = 1, Q and S are a tenth of the double integrator's defaults."""
        n = model.n_physical
        s = np.ones(n) if state_scale is None else as_array("state_scale", state_scale, (n,))
        if np.any(s <= 0):
            raise fail("state_scale", s, "must be numbers > 0, one per physical state")
        if control_scale is None:
            half = 0.5 * (np.asarray(model.u_max, float) - np.asarray(model.u_min, float))
            c = np.where(np.isfinite(half) & (half > 0), half, 1.0)
        else:
            c = as_array("control_scale", control_scale, (model.nu,))
            if np.any(c <= 0):
                raise fail("control_scale", c, "must be numbers > 0, one per control")
        real("terminal", terminal, 0.0)
        Q = 1.0 / s**2
        return cls(Q=tuple(Q), R=tuple(1e-3 / c**2), S=tuple(terminal * Q), **kw)


def tracking_problem(model: Model, weights: TrackingWeights = TrackingWeights(), *,
                     barrier: BarrierOptions | None = None) -> Problem:
    """Plain tracking problem (barrier=None) or its barrier-embedded counterpart."""
    m = embed_barrier(model, barrier) if barrier is not None else model
    cost = quadratic_tracking(m, Q=weights.Q, R=weights.R, S=weights.S, q_beta=weights.q_beta,
                              s_beta=weights.s_beta, beta_cost=weights.beta_cost)
    return Problem.build(m, cost)


def tracking_params(problem: Problem, x_ref, target) -> np.ndarray:
    """Parameters (T+1, n_p): x_ref for stages, the target for the terminal row, and the
    barrier value of the target as beta_ref (assumptions §4.5: beta_f = sum_i B(h_i(x_f)))."""
    model = problem.model
    x_ref = as_array("x_ref", x_ref, (None, model.n_physical))
    target = as_array("target", target, (model.n_physical,))
    T = x_ref.shape[0] - 1
    rows = x_ref.copy()
    rows[-1] = target
    blocks = {"x_ref": rows}
    if model.nx > model.n_physical:
        blocks["beta_ref"] = model.lift(target)[model.n_physical:]
    return problem.cost.params(T, **blocks)


def bas_ilqg(model: Model, x0, x_ref, target, U0=None, *,
             weights: TrackingWeights = TrackingWeights(),
             barrier: BarrierOptions | None = None,
             options: ILQGOptions | None = None) -> tuple[ILQGResult, Problem]:
    """BaS-iLQG: iLQG on the safety-embedded tracking problem (x0 is the physical state)."""
    problem = tracking_problem(model, weights, barrier=barrier or BarrierOptions())
    P = tracking_params(problem, x_ref, target)
    T = P.shape[0] - 1
    U0 = np.zeros((T, model.nu)) if U0 is None else U0
    return ilqg(problem, x0, U0, P, options), problem

"""AL-iLQG (assumptions §6.2): a PHR augmented-Lagrangian outer loop around the same iLQG core.

Constraints c_{i,k}(x_k) = -h_i(x_k) <= 0 for k = 1..T. The inner problem is iLQG on the model
*without* margins (so the line search does not treat h < 0 as a crash) with the cost

    l_k + sum_i mu_{i,k}/2 * max(0, c_i(x_k) + lambda_{i,k}/mu_{i,k})^2

where stage row k carries the term for x_k (k = 0..T-1) and the terminal row the one for x_T.
Multipliers and penalties are parameter blocks ("lam", "mu") of ONE Problem, built (and
compiled) once; the outer loop only rewrites the parameter array. Row 0 depends only on the fixed
x_0, so its term is a constant: its multipliers stay 0 and are never updated (x_0 is strictly
safe, so with lambda = 0 the term is exactly 0). State Hessians are Gauss-Newton: mu grad(c)
grad(c)^T on the active branch, dropping the indefinite (mu c + lambda) Hess(c) term.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Literal

import casadi as ca
import numpy as np

from workbench.ilqg import ILQGOptions, ilqg, make_passes
from workbench.problem.costs import Cost
from workbench.problem.models import Model
from workbench.problem.prediction import predicts, scenes
from workbench.problem.problem import Problem
from workbench.validation import fail, integer, one_of, real


@dataclass(frozen=True)
class ALOptions:
    """Outer-loop settings; defaults assumptions §6.2 [A] / ALTRO (phi, tau, individual mu update).

    inner: the iLQG options of each inner solve (tol_rel 1e-6 [A]; with the 1e-4 of assumptions
    §6.2 the tracking
    scene ended 1.9e-3 above the IPOPT cost, outside the 1e-3 acceptance).
    """

    lambda_init: float = 0.0
    mu_init: float = 1.0
    phi: float = 10.0
    tau: float = 0.25
    mu_max: float = 1e8
    max_outer: int = 20
    constraint_tol: float = 1e-4
    mu_update: Literal["individual", "uniform"] = "individual"
    inner: ILQGOptions = field(default_factory=lambda: ILQGOptions(tol_rel=1e-6))

    def __post_init__(self) -> None:
        real("ALOptions.lambda_init", self.lambda_init, 0.0)
        real("ALOptions.mu_init", self.mu_init, 0.0, strict=True)
        real("ALOptions.phi", self.phi, 1.0, strict=True)
        if not 0 < real("ALOptions.tau", self.tau) < 1:
            raise fail("ALOptions.tau", self.tau, "must lie in (0, 1)")
        real("ALOptions.mu_max", self.mu_max, 0.0, strict=True)
        if self.mu_max < self.mu_init:
            raise fail("ALOptions.mu_max", self.mu_max, f"must be >= mu_init = {self.mu_init}")
        integer("ALOptions.max_outer", self.max_outer, 1)
        real("ALOptions.constraint_tol", self.constraint_tol, 0.0, strict=True)
        one_of("ALOptions.mu_update", self.mu_update, ("individual", "uniform"))
        if not isinstance(self.inner, ILQGOptions):
            raise fail("ALOptions.inner", self.inner, "must be an ILQGOptions")


@dataclass(frozen=True, eq=False)
class ALProblem:
    """The inner problem (built once) and what the outer loop needs around it.

    problem: Problem on the margin-free model, parameters [base p; lam (nh); mu (nh); scene]
    (the scene enters the penalty through h, so it rides in the parameters, one per time:
    the same scene, or with moving circles the scene predicted to each state's time).
    constraints: (x, scene) -> c(x) = -h(x) (nh). base_stage / base_terminal: the original cost,
    to report the cost without penalty terms.
    """

    problem: Problem
    model: Model
    constraints: ca.Function
    base_stage: ca.Function
    base_terminal: ca.Function
    n_base_params: int

    @property
    def nh(self) -> int:
        return self.model.nh

    def params(self, P_base: np.ndarray, lam: np.ndarray, mu: np.ndarray,
               scene=None) -> np.ndarray:
        """Inner parameter array (T+1, n_p) from the base parameters, the AL blocks and the
        scene (default: the model's own); row k's scene is the one of x_k's time, k dt (the
        scene itself unless it has moving circles)."""
        s = self.model.scene_vector(scene)
        return np.hstack([P_base, lam, mu, self._scenes(s, P_base.shape[0])])

    def _scenes(self, s: np.ndarray, n: int) -> np.ndarray:
        """(n, n_scene): row k the scene predicted to k dt."""
        return scenes(self.model, s, n, first=0).T

    def constraint_values(self, X: np.ndarray, scene=None) -> np.ndarray:
        """c(x_k) = -h(x_k) for every row of X (T+1, nx) -> (T+1, nh), in ``scene`` (row k
        in the scene of x_k's time when it has moving circles)."""
        n = X.shape[0]
        s = self.model.scene_vector(scene)
        if predicts(self.model):
            c = self.constraints.map(n)
            return np.asarray(c(X.T, self._scenes(s, n).T)).T.reshape(n, self.nh)
        c = self.constraints.map("c", "serial", n, [1], [])
        return np.asarray(c(X.T, s)).T.reshape(n, self.nh)

    def base_cost(self, X: np.ndarray, U: np.ndarray, P_base: np.ndarray) -> float:
        """The original cost (no penalty terms) of a trajectory."""
        T = U.shape[0]
        stage = self.base_stage.map(T)(X[:-1].T, U.T, P_base[:-1].T)
        return float(np.sum(np.asarray(stage))) + float(self.base_terminal(X[-1], P_base[-1]))


def al_problem(model: Model, cost: Cost) -> ALProblem:
    """Build the AL inner problem for ``cost`` on ``model`` with constraints -h(x) <= 0."""
    if model.nh == 0:
        raise fail("model.h", model.name, "AL-iLQG needs at least one safety margin")
    if model.n_physical != model.nx:
        raise fail("model", model.name, "AL-iLQG works on the plain (not barrier-embedded) model")
    x, u, nh = model.x, model.u, model.nh
    c = -model.h
    lam, mu = ca.SX.sym("lam", nh), ca.SX.sym("mu", nh)
    shifted = mu * c + lam  # mu (c + lam / mu), the active branch where > 0
    penalty = ca.sum1(0.5 / mu * ca.fmax(0.0, shifted) ** 2)
    jc = ca.jacobian(c, x)
    gn = sum((ca.if_else(shifted[i] > 0, mu[i], 0.0) * ca.mtimes(jc[i, :].T, jc[i, :])
              for i in range(nh)), ca.SX.zeros(model.nx, model.nx))
    hess_stage = cost.stage_hessian_x if cost.stage_hessian_x is not None else ca.hessian(
        cost.stage, x)[0]
    hess_term = cost.terminal_hessian_x if cost.terminal_hessian_x is not None else ca.hessian(
        cost.terminal, x)[0]
    scene = model.scene
    p = ca.vertcat(cost.p, lam, mu, scene)
    aug = Cost(
        stage=cost.stage + penalty, terminal=cost.terminal + penalty, p=p,
        param_layout=(*cost.param_layout, ("lam", nh), ("mu", nh), ("scene", model.n_scene)),
        description=f"{cost.description} + PHR augmented Lagrangian",
        stage_hessian_x=hess_stage + gn, terminal_hessian_x=hess_term + gn)
    inner_model = dataclasses.replace(model, name=f"{model.name}_al", h=ca.SX(0, 1),
                                      obstacles=(), scene=ca.SX(0, 1),
                                      scene_value=np.zeros(0), scene_capacity=0,
                                      scene_layout=None)
    return ALProblem(
        problem=Problem.build(inner_model, aug), model=model,
        constraints=ca.Function("c", [x, scene], [ca.densify(c)], ["x", "scene"], ["c"]),
        base_stage=ca.Function("l", [x, u, cost.p], [cost.stage]),
        base_terminal=ca.Function("lT", [x, cost.p], [cost.terminal]),
        n_base_params=cost.n_p)


@dataclass(frozen=True)
class OuterIteration:
    """One outer iteration: after the inner solve, before the multiplier update."""

    iteration: int
    cost: float
    al_cost: float
    max_violation: float
    inner_iterations: int
    inner_converged: bool
    mu_max: float
    lambda_max: float


@dataclass(frozen=True)
class ALResult:
    """AL-iLQG solution. X (T+1,nx), U (T,nu), k (T,nu), K (T,nu,nx) from the last inner solve;
    multipliers / penalties (T+1, nh) used in it; cost without penalty terms."""

    X: np.ndarray
    U: np.ndarray
    k: np.ndarray
    K: np.ndarray
    cost: float
    al_cost: float
    multipliers: np.ndarray
    penalties: np.ndarray
    max_violation: float
    min_margin: float
    converged: bool
    stop_reason: str
    history: tuple[OuterIteration, ...]
    inner_iterations: int
    solve_time_s: float


def al_ilqg(alp: ALProblem, x0, U0, P_base, options: ALOptions | None = None,
            passes=None, scene=None) -> ALResult:
    """Minimise the base cost s.t. h(x_k) >= 0, k = 1..T, by PHR AL around iLQG; ``scene``:
    the obstacles (default: the model's own)."""
    opts = options or ALOptions()
    t0 = time.perf_counter()
    problem = alp.problem
    U = problem.check_controls(U0)
    T = U.shape[0]
    if T < 1:
        raise fail("U0", U.shape, "the horizon must have at least one step")
    x0 = np.asarray(x0, dtype=float).ravel()
    scene = alp.model.scene_vector(scene)
    h0 = -alp.constraint_values(x0[None], scene)[0] if x0.size == alp.model.nx else None
    if h0 is None or np.min(h0) <= 0:
        raise fail("x0", x0, f"must be a state of {alp.model.nx} entries strictly inside the "
                   "safe set (h > 0)")
    P_base = np.asarray(P_base, dtype=float)
    if P_base.shape != (T + 1, alp.n_base_params):
        raise fail("P_base", P_base.shape, f"expected shape ({T + 1}, {alp.n_base_params})")
    nh = alp.nh
    lam = np.zeros((T + 1, nh))
    lam[1:] = opts.lambda_init
    mu = np.full((T + 1, nh), opts.mu_init)
    viol_prev = np.full((T + 1, nh), np.inf)  # so mu first grows after the second inner solve
    passes = passes or make_passes(problem, T, opts.inner.backend)
    history: list[OuterIteration] = []
    converged, stop, n_inner, res, C = False, "max_outer", 0, None, None
    for it in range(1, opts.max_outer + 1):
        P = alp.params(P_base, lam, mu, scene)
        res = ilqg(problem, x0, U, P, opts.inner, passes)
        U, n_inner = res.U, n_inner + res.iterations
        C = alp.constraint_values(res.X, scene)
        viol = np.maximum(0.0, C)
        viol[0] = 0.0
        max_viol = float(viol.max())
        history.append(OuterIteration(
            iteration=it, cost=alp.base_cost(res.X, res.U, P_base), al_cost=res.cost,
            max_violation=max_viol, inner_iterations=res.iterations,
            inner_converged=res.converged, mu_max=float(mu.max()), lambda_max=float(lam.max())))
        if max_viol <= opts.constraint_tol and res.converged:
            converged, stop = True, "converged"
            break
        if it == opts.max_outer:
            break
        lam[1:] = np.maximum(0.0, lam[1:] + mu[1:] * C[1:])
        if opts.mu_update == "uniform":
            grow = np.ones_like(mu, dtype=bool)
        else:
            grow = viol > opts.tau * viol_prev
        grow[0] = False
        mu = np.where(grow, np.minimum(opts.mu_max, opts.phi * mu), mu)
        viol_prev = viol
    assert res is not None and C is not None  # ALOptions.max_outer >= 1: the loop ran
    return ALResult(
        X=res.X, U=res.U, k=res.k, K=res.K, cost=alp.base_cost(res.X, res.U, P_base),
        al_cost=res.cost, multipliers=lam.copy(), penalties=mu.copy(),
        max_violation=float(np.maximum(0.0, C[1:]).max()), min_margin=float(-C[1:].max()),
        converged=converged, stop_reason=stop, history=tuple(history),
        inner_iterations=n_inner, solve_time_s=time.perf_counter() - t0)

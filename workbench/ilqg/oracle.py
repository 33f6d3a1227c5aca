"""IPOPT (through ``casadi.nlpsol``) on exactly the problem iLQG solves: the independent oracle.

``solve_ipopt``: single shooting over U with the problem's own dynamics and costs, the control
box as variable bounds, and optionally hard path constraints h(x_k) >= 0 (for AL-iLQG's
constrained problem). ``MultipleShootingNLP``: the same problem as a multiple-shooting NLP,
built once, for IPOPT or FATROP (the speed baselines of ``make bench``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from workbench.problem.prediction import scene_at, scene_sx_at
from workbench.problem.problem import Problem


@dataclass(frozen=True)
class NLPResult:
    """Solution of an NLP solver (IPOPT or FATROP) on an optimal-control problem."""

    X: np.ndarray
    U: np.ndarray
    cost: float
    status: str
    success: bool
    solve_time_s: float
    iterations: int
    solver: str = "ipopt"


IpoptResult = NLPResult


def solve_ipopt(problem: Problem, x0, U0, P=None, *, hard_constraints: bool = False,
                tol: float = 1e-10, max_iter: int = 3000, scene=None) -> IpoptResult:
    """Minimise the problem's cost over U (T,nu) from the guess U0 with IPOPT (exact Hessian),
    in ``scene`` (default: the model's own; moving circles predicted to each state's time)."""
    s = problem.scene_vector(scene)
    x0 = problem.check_initial_state(x0, s)
    U0 = problem.check_controls(U0)
    T, nu = U0.shape
    P = problem.check_params(P, T)
    f = problem.functions
    u = ca.SX.sym("U", nu, T)
    x = ca.SX(x0)
    J = ca.SX(0)
    g = []
    for t in range(T):
        J += f["stage"](x, u[:, t], P[t])
        st = scene_at(problem.model, s, (t + 1) * problem.model.dt)  # x_{t+1}'s time
        x = f["dyn"](x, u[:, t], st)
        if hard_constraints and problem.nh:
            g.append(f["margins"](x, st))
    J += f["term"](x, P[T])
    nlp = {"x": ca.vec(u), "f": J, "g": ca.vertcat(*g) if g else ca.SX(0, 1)}
    opts: dict[str, Any] = {"print_time": False, "ipopt": {
        "print_level": 0, "tol": tol, "max_iter": max_iter, "sb": "yes"}}
    solver = ca.nlpsol("oracle", "ipopt", nlp, opts)
    lbx = np.tile(problem.model.u_min, T)
    ubx = np.tile(problem.model.u_max, T)
    ng = nlp["g"].numel()
    t0 = time.perf_counter()
    sol = solver(x0=U0.ravel(), lbx=lbx, ubx=ubx, lbg=np.zeros(ng), ubg=np.full(ng, np.inf))
    elapsed = time.perf_counter() - t0
    stats = solver.stats()
    U = np.asarray(sol["x"]).reshape(T, nu)
    return IpoptResult(
        X=problem.rollout(x0, U, s), U=U, cost=float(sol["f"]), status=stats["return_status"],
        success=bool(stats["success"]), solve_time_s=elapsed, iterations=int(stats["iter_count"]),
    )




class MultipleShootingNLP:
    """The problem as a multiple-shooting NLP, built once, solved by IPOPT or FATROP.

    Variables stage-wise [x_0, u_0, x_1, u_1, ..., x_T]; constraints, stage by stage, the gap
    x_{k+1} - F(x_k, u_k) = 0 and (``hard_constraints``) the margins h(x_k) >= 0, k >= 1; x_0
    and the control box are variable bounds. x_0 and the parameters P are NLP parameters, so
    one solver serves every solve. Moving circles of the scene are predicted to each state's
    time (step k's gap and x_k's margins in the scene of k dt). FATROP detects the stage
    structure from this layout (``structure_detection="auto"``). Exact Hessians, CasADi's
    virtual machine for the functions (no code generation), ``solve`` times the solver call
    only.
    """

    def __init__(self, problem: Problem, T: int, solver: str = "ipopt", *,
                 hard_constraints: bool = False, tol: float = 1e-8, max_iter: int = 3000):
        if solver not in ("ipopt", "fatrop"):
            raise ValueError(f"solver: {solver!r} is not one of ('ipopt', 'fatrop')")
        self.problem, self.T, self.solver_name = problem, T, solver
        nx, nu, n_p = problem.nx, problem.nu, problem.n_p
        f = problem.functions
        xs = [ca.SX.sym(f"x{k}", nx) for k in range(T + 1)]
        us = [ca.SX.sym(f"u{k}", nu) for k in range(T)]
        x0 = ca.SX.sym("x0", nx)
        Ps = [ca.SX.sym(f"p{k}", n_p) for k in range(T + 1)]
        sc = ca.SX.sym("scene", problem.n_scene)
        model = problem.model

        def at(k: int):  # the scene of x_k's time (moving circles at c + v k dt)
            return scene_sx_at(model, sc, k * model.dt)

        w, g, eq, J = [], [], [], ca.SX(0)
        nh = problem.nh if hard_constraints else 0
        for k in range(T):
            w += [xs[k], us[k]]
            J += f["stage"](xs[k], us[k], Ps[k])
            g.append(xs[k + 1] - f["dyn"](xs[k], us[k], at(k + 1)))
            eq += [True] * nx
            if nh and k >= 1:
                g.append(f["margins"](xs[k], at(k)))
                eq += [False] * nh
        w.append(xs[T])
        J += f["term"](xs[T], Ps[T])
        if nh:
            g.append(f["margins"](xs[T], at(T)))
            eq += [False] * nh
        self._eq = np.array(eq)
        nlp = {"x": ca.vertcat(*w), "f": J, "g": ca.vertcat(*g),
               "p": ca.vertcat(x0, *Ps, sc)}
        opts: dict[str, Any]
        if solver == "ipopt":
            opts = {"print_time": False, "ipopt": {"print_level": 0, "tol": tol,
                                                   "max_iter": max_iter, "sb": "yes"}}
        else:
            opts = {"print_time": False, "structure_detection": "auto", "equality": eq,
                    "fatrop": {"print_level": 0, "tol": tol, "max_iter": max_iter}}
        self._solver = ca.nlpsol(f"ms_{solver}", solver, nlp, opts)
        # x_0 is fixed through its bounds (filled per solve), controls boxed, states free
        lb = [np.full(nx, -np.inf)] + [problem.model.u_min, np.full(nx, -np.inf)] * T
        ub = [np.full(nx, np.inf)] + [problem.model.u_max, np.full(nx, np.inf)] * T
        self._lbx, self._ubx = np.concatenate(lb), np.concatenate(ub)
        self._lbg = np.zeros(len(eq))
        self._ubg = np.where(self._eq, 0.0, np.inf)

    def solve(self, x0, U0, P=None, scene=None) -> NLPResult:
        """Solve from the initial guess U0 (states: its rollout) in ``scene`` (default: the
        model's own); times the solver call."""
        p = self.problem
        s = p.scene_vector(scene)
        x0 = p.check_initial_state(x0, s)
        U0 = p.check_controls(U0, self.T)
        P = p.check_params(P, self.T)
        X0 = p.rollout(x0, U0, s)
        nx, nu, T = p.nx, p.nu, self.T
        w0 = np.concatenate([np.r_[X0[k], U0[k]] for k in range(T)] + [X0[T]])
        lbx, ubx = self._lbx.copy(), self._ubx.copy()
        lbx[:nx] = ubx[:nx] = x0
        t0 = time.perf_counter()
        sol = self._solver(x0=w0, p=np.r_[x0, P.ravel(), s], lbx=lbx, ubx=ubx, lbg=self._lbg,
                           ubg=self._ubg)
        elapsed = time.perf_counter() - t0
        stats = self._solver.stats()
        z = np.asarray(sol["x"]).ravel()
        XU = z[: T * (nx + nu)].reshape(T, nx + nu)
        X = np.vstack([XU[:, :nx], z[T * (nx + nu):][None]])
        status = str(stats.get("return_status", stats.get("unified_return_status", "")))
        return NLPResult(X=X, U=XU[:, nx:].copy(), cost=float(sol["f"]), status=status,
                         success=bool(stats["success"]), solve_time_s=elapsed,
                         iterations=int(stats.get("iter_count", -1)), solver=self.solver_name)

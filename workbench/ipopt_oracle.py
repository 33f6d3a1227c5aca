"""IPOPT (through ``casadi.nlpsol``) on exactly the problem iLQG solves: the independent oracle.

Single shooting over U with the problem's own dynamics and costs, the control box as variable
bounds, and optionally hard path constraints h(x_k) >= 0 (for AL-iLQG's constrained problem).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import casadi as ca
import numpy as np

from workbench.problem import Problem


@dataclass(frozen=True)
class IpoptResult:
    X: np.ndarray
    U: np.ndarray
    cost: float
    status: str
    success: bool
    solve_time_s: float
    iterations: int


def solve_ipopt(problem: Problem, x0, U0, P=None, *, hard_constraints: bool = False,
                tol: float = 1e-10, max_iter: int = 3000) -> IpoptResult:
    """Minimise the problem's cost over U (T,nu) from the guess U0 with IPOPT (exact Hessian)."""
    x0 = problem.check_initial_state(x0)
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
        x = f["dyn"](x, u[:, t])
        if hard_constraints and problem.nh:
            g.append(f["margins"](x))
    J += f["term"](x, P[T])
    nlp = {"x": ca.vec(u), "f": J, "g": ca.vertcat(*g) if g else ca.SX(0, 1)}
    opts = {"print_time": False, "ipopt": {"print_level": 0, "tol": tol, "max_iter": max_iter,
                                           "sb": "yes"}}
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
        X=problem.rollout(x0, U), U=U, cost=float(sol["f"]), status=stats["return_status"],
        success=bool(stats["success"]), solve_time_s=elapsed, iterations=int(stats["iter_count"]),
    )

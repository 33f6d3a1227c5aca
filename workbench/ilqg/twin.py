"""The twin of the compiled iLQG passes (:class:`~workbench.ilqg.compiled.CompiledPasses`):
:class:`PassesTwin`, the same algorithm in plain NumPy (derivatives, backward pass with its box
QP, forward pass, line search), pass by pass.

Derivatives come from the problem's CasADi Functions evaluated by the CasADi virtual machine,
mapped over the horizon. Every branch mirrors workbench/ilqg/core.c; ``tests/test_twins.py``
compares the two pass by pass at relative tolerance. Layout: time-major trajectories, X (T+1, nx),
U (T, nu), gains (T, nu, nx), as the compiled passes (no batch dimension, nothing to convert).

Moving circles: for a model whose scene has moving slots the twin evaluates step t (the
dynamics, its crash test and derivatives) in the scene predicted to (t + 1) dt, and
:func:`~workbench.ilqg.solver.make_passes` always returns it (the compiled passes hold one
scene over the horizon).

Run-time fallback: :func:`~workbench.ilqg.solver.make_passes` returns this twin when no C
compiler is available (or with ``backend="numpy"``, ``WORKBENCH_NO_CODEGEN=1``); every iLQG
solve and every feedback law then runs on it.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from workbench.ilqg.passes import (
    BackwardResult,
    BoxQPResult,
    ForwardResult,
    LineSearchResult,
)
from workbench.problem.prediction import predicts, step_scenes
from workbench.problem.problem import Problem

CRASH_PENALTY = 1e10
CRASH_MARGIN = 1e-15


def step_function(problem: Problem) -> ca.Function:
    """One forward-pass step (x, u, p, scene) -> (x_next, l + crash penalty), fused for speed.

    The penalty (assumptions §4.6, line search) is 1e10 when any margin of x_next is below 1e-15 or
    NaN.
    """
    f = problem.functions
    x, u, p, s = (ca.SX.sym(n, m) for n, m in (("x", problem.nx), ("u", problem.nu),
                                                 ("p", problem.n_p), ("scene", problem.n_scene)))
    x_next = f["dyn"](x, u, s)
    cost = f["stage"](x, u, p)
    if problem.nh:
        h = f["margins"](x_next, s)
        bad = sum((ca.logic_not(h[i] >= CRASH_MARGIN) for i in range(problem.nh)), ca.SX(0))
        cost = cost + ca.if_else(bad > 0, CRASH_PENALTY, 0.0)
    return ca.Function("step", [x, u, p, s], [x_next, cost], ["x", "u", "p", "scene"],
                       ["x_next", "cost"], {"cse": True})


def box_qp(H, g, lo, hi, x0, max_iter: int = 100):
    """Projected-Newton box QP (Tassa et al. 2014): min ½x'Hx + g'x, lo <= x <= hi.

    Result codes as in core.c; ``L`` is the Cholesky factor of H[free, free].
    """
    n = g.size
    min_grad, min_rel, step_dec, min_step, armijo = 1e-8, 1e-8, 0.6, 1e-22, 0.1
    x = np.clip(np.where(np.isfinite(x0), x0, 0.0), lo, hi)
    clamped = np.zeros(n, bool)
    free = np.ones(n, bool)
    L = np.zeros((0, 0))
    value = x @ g + 0.5 * x @ H @ x
    oldvalue = 0.0
    result = 0
    it = 0
    for it in range(1, max_iter + 1):
        if it > 1 and (oldvalue - value) < min_rel * abs(oldvalue):
            result = 4
            break
        oldvalue = value
        grad = g + H @ x
        old = clamped
        clamped = ((x == lo) & (grad > 0)) | ((x == hi) & (grad < 0))
        if clamped.all():
            result, free, L = 6, np.zeros(n, bool), np.zeros((0, 0))
            break
        if it == 1 or np.any(old != clamped):
            free = ~clamped
            try:
                L = np.linalg.cholesky(H[np.ix_(free, free)])
            except np.linalg.LinAlgError:
                result = -1
                break
        if np.linalg.norm(grad[~clamped]) < min_grad:
            result = 5
            break
        gc = g + H @ (x * clamped)
        search = np.zeros(n)
        search[free] = -_chol_solve(L, gc[free]) - x[free]
        sdotg = float(search @ grad)
        if sdotg >= 0:
            break
        step = 1.0
        xc = np.clip(x + step * search, lo, hi)
        vc = xc @ g + 0.5 * xc @ H @ xc
        while (vc - oldvalue) / (step * sdotg) < armijo:
            step *= step_dec
            xc = np.clip(x + step * search, lo, hi)
            vc = xc @ g + 0.5 * xc @ H @ xc
            if step < min_step:
                result = 2
                break
        x, value = xc, vc
        if result:
            break
    else:
        result = 1
    return BoxQPResult(x=x, result=result, free=free, L=L)


def _chol_solve(L, b):
    y = np.linalg.solve(L, b) if L.size else b
    return np.linalg.solve(L.T, y) if L.size else b


class PassesTwin:
    """Rollout, derivatives, backward and forward passes in NumPy (+ CasADi VM)."""

    name = "numpy"

    def __init__(self, problem: Problem, T: int):
        f = problem.functions
        self.problem, self.T = problem, T
        self._moves = predicts(problem.model)
        # the scene is shared, or one per step (moving circles: the scene of x_{t+1}'s time)
        self._jac = (f["dyn_jac"].map(T) if self._moves
                     else f["dyn_jac"].map("dyn_jac", "serial", T, [2], []))
        self._quad = f["stage_quad"].map(T)
        self._tquad = f["term_quad"]
        self._hess = f["dyn_hess"]
        self._step, self._term = step_function(problem), f["term"]
        self.set_scene(problem.model.scene_value)

    def set_scene(self, scene: np.ndarray) -> None:
        """The scene (flat, ``problem.n_scene``) the following passes use; with moving circles
        step t uses it predicted to (t + 1) dt
        (:func:`~workbench.problem.prediction.step_scenes`)."""
        self._S = np.array(scene, dtype=float)
        self._St = (step_scenes(self.problem.model, self._S, self.T) if self._moves
                    else None)

    def _at(self, t: int) -> np.ndarray:
        return self._S if self._St is None else self._St[:, t]

    def derivatives(self, X, U, P):
        """A (T,nx,nx), B (T,nx,nu), lx (T+1,nx), lu, lxx (T+1,nx,nx), luu, lux (T,nu,nx) and
        the trajectory X (T+1,nx) they were taken along (for the second-order backward pass)."""
        T, nx, nu = self.T, self.problem.nx, self.problem.nu
        A, B = (np.asarray(m) for m in self._jac(X[:-1].T, U.T,
                                                  self._S if self._St is None else self._St))
        A = A.reshape(nx, T, nx).transpose(1, 0, 2)
        B = B.reshape(nx, T, nu).transpose(1, 0, 2)
        _, lx, lu, lxx, luu, lux = (np.asarray(m) for m in self._quad(X[:-1].T, U.T, P[:-1].T))
        _, lxT, lxxT = (np.asarray(m) for m in self._tquad(X[-1], P[-1]))
        return {
            "A": A, "B": B,
            "lx": np.vstack([lx.T, lxT.T]),
            "lu": lu.T,
            "lxx": np.concatenate([lxx.reshape(nx, T, nx).transpose(1, 0, 2), lxxT[None]]),
            "luu": luu.reshape(nu, T, nu).transpose(1, 0, 2),
            "lux": lux.reshape(nu, T, nx).transpose(1, 0, 2),
            "X": np.array(X, dtype=float),
        }

    def backward(self, d, U, umin, umax, mu, reg, boxed, second_order=False):
        """The gains k, K and expected decrease dV; status 0 ok or t+1 where Quu failed.

        second_order: full DDP, Q's second derivatives include sum_i V'_x,i Hess F_i (the
        dynamics' Hessians contracted with the next value gradient, ``dyn_hess``)."""
        T, nx, nu = self.T, self.problem.nx, self.problem.nu
        k = np.zeros((T, nu))
        K = np.zeros((T, nu, nx))
        Vx, Vxx = d["lx"][T].copy(), d["lxx"][T].copy()
        dV = np.zeros(2)
        for t in range(T - 1, -1, -1):
            A, B = d["A"][t], d["B"][t]
            Qx = d["lx"][t] + A.T @ Vx
            Qu = d["lu"][t] + B.T @ Vx
            Qxx = d["lxx"][t] + A.T @ Vxx @ A
            Qux = d["lux"][t] + B.T @ Vxx @ A
            Quu = d["luu"][t] + B.T @ Vxx @ B
            if second_order:
                fxx, fuu, fux = (np.asarray(m) for m in self._hess(d["X"][t], U[t], Vx,
                                                                 self._at(t)))
                Qxx, Quu, Qux = Qxx + fxx, Quu + fuu, Qux + fux
            if reg == 0:
                Quu_r, Qux_r = Quu + mu * np.eye(nu), Qux
            else:
                Quu_r, Qux_r = Quu + mu * B.T @ B, Qux + mu * B.T @ A
            if boxed:
                warm = np.zeros(nu) if t == T - 1 else k[t + 1]
                qp = box_qp(Quu_r, Qu, umin - U[t], umax - U[t], warm)
                if qp.result < 1:
                    return BackwardResult(status=t + 1, k=k, K=K, dV=dV)
                kk, free, L = qp.x, qp.free, qp.L
            else:
                try:
                    L = np.linalg.cholesky(Quu_r)
                except np.linalg.LinAlgError:
                    return BackwardResult(status=t + 1, k=k, K=K, dV=dV)
                kk, free = -_chol_solve(L, Qu), np.ones(nu, bool)
            k[t] = kk
            if free.any():
                K[t][free] = -_chol_solve(L, Qux_r[free])
            Kt, kt = K[t], k[t]
            dV += (kt @ Qu, 0.5 * kt @ Quu @ kt)
            Vx = Qx + Kt.T @ Quu @ kt + Kt.T @ Qu + Qux.T @ kt
            Vxx = Qxx + Kt.T @ Quu @ Kt + Kt.T @ Qux + Qux.T @ Kt
            Vxx = 0.5 * (Vxx + Vxx.T)
        return BackwardResult(status=0, k=k, K=K, dV=dV)

    def forward(self, x0, X, U, k, K, P, alpha, umin, umax, use_policy=True):
        """Closed-loop rollout u = clip(ubar + alpha k + K(x - xbar))."""
        T = self.T
        Xn = np.zeros_like(X)
        Un = np.zeros_like(U)
        Xn[0] = x0
        J = 0.0
        for t in range(T):
            v = U[t] + (alpha * k[t] + K[t] @ (Xn[t] - X[t]) if use_policy else 0.0)
            Un[t] = np.clip(v, umin, umax)
            xn, c = self._step(Xn[t], Un[t], P[t], self._at(t))
            Xn[t + 1] = np.asarray(xn).ravel()
            J += float(c)
        return ForwardResult(X=Xn, U=Un, cost=J + float(self._term(Xn[T], P[T])))

    def line_search(self, x0, X, U, k, K, P, J, dV, alphas, z_min, umin, umax):
        """First step size whose actual/expected decrease ratio z exceeds z_min."""
        for alpha in alphas:
            fw = self.forward(x0, X, U, k, K, P, alpha, umin, umax)
            Jn = fw.cost
            expected = -alpha * (dV[0] + alpha * dV[1])
            z = (J - Jn) / expected if expected > 0 else np.sign(J - Jn)
            if np.isfinite(Jn) and z > z_min:
                return LineSearchResult(accepted=True, X=fw.X, U=fw.U, cost=Jn, alpha=alpha,
                                        expected=expected)
        return LineSearchResult(accepted=False, X=X, U=U, cost=J, alpha=0.0, expected=0.0)

"""The optimal-control problem, built once and shared by every method.

A :class:`Problem` turns a :class:`~workbench.problem.Model` and a
:class:`~workbench.problem.Cost` into CasADi Functions with named inputs and outputs and exact
first and second derivatives:

===========  =====================  =====================================
name         inputs                 outputs
===========  =====================  =====================================
dyn          x, u, scene            x_next
dyn_jac      x, u, scene            A (nx,nx), B (nx,nu)
dyn_hess     x, u, lam, scene       fxx, fuu, fux (nu,nx): Hessians of lam'F(x,u)
stage        x, u, p                l
stage_quad   x, u, p                l, lx, lu, lxx, luu, lux (nu,nx)
term         x, p                   l
term_quad    x, p                   l, lx, lxx
margins      x, scene               h (nh)
===========  =====================  =====================================

``scene`` is the model's run-time obstacle data (size ``model.n_scene``, possibly 0): the
barrier-embedded dynamics and the margins depend on it, the costs do not.

iLQG's default, full DDP, adds the dynamics' second derivatives contracted with the value
gradient, ``dyn_hess(x, u, V_x')``, exact from CasADi; Gauss-Newton iLQG
(``ILQGOptions(second_order=False)``, and the safeguard step of the default) is exact in the
costs and first order in the dynamics.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import casadi as ca
import numpy as np

from workbench.problem.costs import Cost
from workbench.problem.models import Model, margin_violation
from workbench.problem.prediction import step_scenes
from workbench.validation import as_array, fail

FUNCTION_NAMES = ("dyn", "dyn_jac", "dyn_hess", "stage", "stage_quad", "term", "term_quad",
                  "margins")


@dataclass(frozen=True, eq=False)
class Problem:
    """Model + cost + their exact-derivative Functions, with a content fingerprint."""

    model: Model
    cost: Cost
    functions: dict[str, ca.Function]
    fingerprint: str

    @classmethod
    def build(cls, model: Model, cost: Cost) -> Problem:
        x, u, p, s = model.x, model.u, cost.p, model.scene
        known = {v.name() for v in ca.symvar(ca.vertcat(x, u, p))}
        for name, expr in (("cost.stage", cost.stage), ("cost.terminal", cost.terminal)):
            if ca.SX(expr).shape != (1, 1):
                raise fail(name, ca.SX(expr).shape, "must be a scalar expression")
            extra = [v.name() for v in ca.symvar(ca.SX(expr)) if v.name() not in known]
            if extra:
                raise fail(name, extra, "may depend only on the model's x, u and the cost's p")
        if ca.depends_on(cost.terminal, u):
            raise fail("cost.terminal", "depends on u", "the terminal cost is a function of x, p")
        opts = {"cse": True}
        d = ca.densify
        ls, lT = cost.stage, cost.terminal
        lxx, lx = ca.hessian(ls, x)
        luu, lu = ca.hessian(ls, u)
        lux = ca.jacobian(lu, x)
        lTxx, lTx = ca.hessian(lT, x)
        lam = ca.SX.sym("lam", model.nx)
        fxx = ca.hessian(ca.dot(lam, model.x_next), x)[0]
        fuu, fu_lam = ca.hessian(ca.dot(lam, model.x_next), u)
        fux = ca.jacobian(fu_lam, x)
        nx = model.nx
        for name, override in (("cost.stage_hessian_x", cost.stage_hessian_x),
                               ("cost.terminal_hessian_x", cost.terminal_hessian_x)):
            if override is not None and ca.SX(override).shape != (nx, nx):
                raise fail(name, ca.SX(override).shape, f"must have shape ({nx}, {nx})")
        if cost.stage_hessian_x is not None:
            lxx = ca.SX(cost.stage_hessian_x)
        if cost.terminal_hessian_x is not None:
            lTxx = ca.SX(cost.terminal_hessian_x)
        fns = {
            "dyn": ca.Function("dyn", [x, u, s], [d(model.x_next)], ["x", "u", "scene"],
                               ["x_next"], opts),
            "dyn_jac": ca.Function(
                "dyn_jac", [x, u, s],
                [d(ca.jacobian(model.x_next, x)), d(ca.jacobian(model.x_next, u))],
                ["x", "u", "scene"], ["A", "B"], opts),
            "dyn_hess": ca.Function(
                "dyn_hess", [x, u, lam, s], [d(fxx), d(fuu), d(fux)],
                ["x", "u", "lam", "scene"], ["fxx", "fuu", "fux"], opts),
            "stage": ca.Function("stage", [x, u, p], [d(ls)], ["x", "u", "p"], ["l"], opts),
            "stage_quad": ca.Function(
                "stage_quad", [x, u, p], [d(ls), d(lx), d(lu), d(lxx), d(luu), d(lux)],
                ["x", "u", "p"], ["l", "lx", "lu", "lxx", "luu", "lux"], opts),
            "term": ca.Function("term", [x, p], [d(lT)], ["x", "p"], ["l"], opts),
            "term_quad": ca.Function(
                "term_quad", [x, p], [d(lT), d(lTx), d(lTxx)], ["x", "p"],
                ["l", "lx", "lxx"], opts),
            "margins": ca.Function("margins", [x, s], [d(model.h)], ["x", "scene"], ["h"], opts),
        }
        digest = hashlib.sha256()
        for name in FUNCTION_NAMES:
            digest.update(name.encode())
            digest.update(fns[name].serialize().encode())
        for arr in (model.u_min, model.u_max, np.array([model.dt])):
            digest.update(np.ascontiguousarray(arr, dtype=float).tobytes())
        return cls(model=model, cost=cost, functions=fns, fingerprint=digest.hexdigest()[:16])

    @property
    def nx(self) -> int:
        return self.model.nx

    @property
    def nu(self) -> int:
        return self.model.nu

    @property
    def n_p(self) -> int:
        return self.cost.n_p

    @property
    def nh(self) -> int:
        return self.model.nh

    @property
    def n_scene(self) -> int:
        return self.model.n_scene

    def scene_vector(self, scene=None) -> np.ndarray:
        """The scene input (see :meth:`Model.scene_vector`); None: the model's own."""
        return self.model.scene_vector(scene)

    def check_initial_state(self, x0, scene=None) -> np.ndarray:
        """Validate x0 (finite, right size, outside every obstacle of ``scene``) and lift it
        if physical."""
        x0 = np.asarray(x0, dtype=float).ravel()
        if x0.size == self.model.n_physical and x0.size != self.nx:
            if not np.all(np.isfinite(x0)):
                raise fail("x0", x0, "all entries must be finite")
            self._check_safe(x0, scene)
            return self.model.lift(x0, scene)
        x0 = as_array("x0", x0, (self.nx,))
        self._check_safe(x0, scene)
        return x0

    def _check_safe(self, x0: np.ndarray, scene=None) -> None:
        """x0 must be strictly safe: every margin h > 0; on a barrier-embedded model h >
        eps_h (the barrier options' crash margin: at h <= eps_h the barrier state is already
        beta_max, a crash)."""
        if not self.nh:
            return
        h = self.model.margins(x0, scene)
        spec = self.model.barrier
        eps = float(spec.options.eps_h) if spec is not None else 0.0
        where = margin_violation(self.model, h, eps)
        if where is None:
            return
        if eps > 0 and np.min(h) > 0:
            raise fail("x0", x0, f"{where}: within BarrierOptions.eps_h of the boundary the "
                       "barrier state counts as a crash; the start must have every h > eps_h")
        raise fail("x0", x0, f"{where}; the start must be strictly safe (every h > 0)")

    def check_controls(self, U, T: int | None = None) -> np.ndarray:
        """Validate a control sequence (T, nu)."""
        return as_array("U0", U, (T, self.nu))

    def check_params(self, P, T: int) -> np.ndarray:
        """Validate a parameter array (T+1, n_p); an empty parameter vector needs no array."""
        if P is None and self.n_p == 0:
            return np.zeros((T + 1, 0))
        return as_array("P", P, (T + 1, self.n_p))

    def rollout(self, x0, U, scene=None) -> np.ndarray:
        """Open-loop state trajectory X (T+1, nx) under controls U (no clipping) in ``scene``
        (step k in the scene predicted to (k + 1) dt when it has moving circles,
        :mod:`workbench.problem.prediction`)."""
        U = np.asarray(U, dtype=float)
        T = U.shape[0]
        sim = self.functions["dyn"].mapaccum(T)
        S = step_scenes(self.model, self.scene_vector(scene), T)
        Xs = np.asarray(sim(np.asarray(x0, dtype=float), U.T, S))
        return np.vstack([np.asarray(x0, dtype=float)[None], Xs.T])

    def total_cost(self, X, U, P) -> float:
        """J = sum_k l(x_k, u_k, p_k) + l_T(x_T, p_T)."""
        T = U.shape[0]
        stage = self.functions["stage"].map(T)
        stages = np.asarray(stage(X[:-1].T, U.T, P[:-1].T))
        return float(stages.sum()) + float(self.functions["term"](X[-1], P[-1]))

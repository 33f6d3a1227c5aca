"""iLQG (assumptions §5): DDP with Tassa's regularisation schedule, an expected-decrease line
search, control limits through a box QP in the backward pass, and termination rules. By default
each iteration tries the full second-order (DDP) step and is redone as a Gauss-Newton iteration
when that step fails (see :class:`ILQGOptions`).

``ilqg(problem, x0, U0, P, options)`` runs the same outer loop over one of two pass backends:
compiled C (default when a compiler exists) or the NumPy twin (``backend="numpy"``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Literal

import numpy as np

from workbench.ilqg.compiled import CompiledPasses, SolveOptions, problem_library
from workbench.ilqg.twin import CRASH_MARGIN, PassesTwin
from workbench.problem.models import margin_violation
from workbench.problem.prediction import predicts
from workbench.problem.problem import Problem
from workbench.validation import fail, flag, integer, one_of, real

Backend = Literal["auto", "compiled", "numpy"]
MAX_ITERATIONS = 10**6  # outer iterations of one solve (the history holds one row each)


@dataclass(frozen=True)
class ILQGOptions:
    """iLQG settings; defaults from assumptions §5 (DBaS-code / Tassa). ``max_iter`` <=
    :data:`MAX_ITERATIONS`.

    Steps: ``second_order`` (default) is full DDP, whose backward pass adds the dynamics'
    second derivatives contracted with the value gradient; ``second_order=False`` is
    Gauss-Newton iLQG. With ``gauss_newton_fallback`` (default; second order only) an iteration
    whose second-order step fails -- its backward pass is not positive definite for any
    regularisation up to ``fallback_mu``, or the line search rejects it at every step size --
    is redone as a Gauss-Newton iteration from the regularisation it started with; the next
    iteration tries second order again. The reason: far from a solution the second-order model
    can be meaningless. On the planar quadrotor started at hover its value gradient grows to
    ~1e9 along the backward pass and every step size crashes; plain DDP then raises the
    regularisation to ~1e4 (and, after backward failures, ~1e8), creeps along short
    gradient-like steps and converges to a worse local minimum (cost 82.3 where IPOPT and
    Gauss-Newton reach 48.2). The Gauss-Newton model is positive semidefinite by construction,
    so its step is a sound move there, while near a solution the second-order steps are
    accepted and converge in fewer iterations. Second-order backward passes that only need
    moderate regularisation are kept (on the tracking scene they need up to ~1.5e3 and those
    steps are what makes DDP fast there). ``Iteration.step`` records the step each iteration
    took and :attr:`ILQGResult.step_counts` sums them.
    """

    max_iter: int = 300
    mu_init: float = 0.5
    mu_factor: float = 1.6
    mu_min: float = 1e-6
    mu_max: float = 1e10
    regularization: Literal["control", "state"] = "control"
    alphas: tuple[float, ...] = tuple(10.0 ** np.linspace(0.0, -3.0, 11))
    z_min: float = 0.0
    tol_abs: float = 0.0
    tol_rel: float = 1e-7
    tol_grad: float = 1e-4
    box_qp: bool = True
    # full DDP: add the dynamics' second derivatives contracted with the value gradient
    second_order: bool = True
    # second order only: a failed second-order step is redone as a Gauss-Newton step
    gauss_newton_fallback: bool = True
    fallback_mu: float = 1e6  # the most regularisation a second-order pass may need
    backend: Backend = "auto"
    outer_loop: Literal["compiled", "python"] = "compiled"  # compiled: wb_solve, when available

    def __post_init__(self) -> None:
        integer("ILQGOptions.max_iter", self.max_iter, 1, MAX_ITERATIONS)
        real("ILQGOptions.mu_init", self.mu_init, 0.0)
        real("ILQGOptions.mu_factor", self.mu_factor, 1.0, strict=True)
        real("ILQGOptions.mu_min", self.mu_min, 0.0)
        real("ILQGOptions.mu_max", self.mu_max, 0.0, strict=True)
        one_of("ILQGOptions.regularization", self.regularization, ("control", "state"))
        if not 0 < len(self.alphas) <= 32:
            raise fail("ILQGOptions.alphas", self.alphas, "need 1 to 32 step sizes in (0, 1]")
        for a in self.alphas:
            real("ILQGOptions.alphas", a, 0.0, strict=True, maximum=1.0)
        real("ILQGOptions.z_min", self.z_min)
        for name in ("tol_abs", "tol_rel", "tol_grad"):
            real(f"ILQGOptions.{name}", getattr(self, name), 0.0)
        flag("ILQGOptions.box_qp", self.box_qp)
        flag("ILQGOptions.second_order", self.second_order)
        flag("ILQGOptions.gauss_newton_fallback", self.gauss_newton_fallback)
        real("ILQGOptions.fallback_mu", self.fallback_mu, 0.0, strict=True)
        one_of("ILQGOptions.backend", self.backend, ("auto", "compiled", "numpy"))
        one_of("ILQGOptions.outer_loop", self.outer_loop, ("compiled", "python"))


Step = Literal["gauss_newton", "second_order", "fallback"]
STEPS: tuple[Step, ...] = ("gauss_newton", "second_order", "fallback")  # C history codes 0, 1, 2


@dataclass(frozen=True, kw_only=True)
class Iteration:
    """One accepted or rejected iteration of the outer loop. ``step``: "gauss_newton",
    "second_order", or "fallback" (the second-order step failed and the iteration was redone as
    a Gauss-Newton iteration, which the other fields describe; see :class:`ILQGOptions`)."""

    iteration: int
    cost: float
    cost_change: float
    expected_change: float
    alpha: float
    mu: float
    grad_norm: float
    accepted: bool
    time_s: float
    step: Step = "gauss_newton"


@dataclass(frozen=True)
class ILQGResult:
    """Solution and diagnostics. Shapes: X (T+1,nx), U (T,nu), k (T,nu), K (T,nu,nx)."""

    X: np.ndarray
    U: np.ndarray
    k: np.ndarray
    K: np.ndarray
    cost: float
    converged: bool
    stop_reason: str
    iterations: int
    history: tuple[Iteration, ...]
    backend: str
    solve_time_s: float
    initial_guess_replaced: bool = False

    @property
    def step_counts(self) -> dict[str, int]:
        """How many iterations took each kind of step (see :attr:`Iteration.step`)."""
        return {kind: sum(h.step == kind for h in self.history) for kind in STEPS}


def make_passes(problem: Problem, T: int, backend: Backend = "auto"):
    """The pass backend for a problem and horizon. A model whose scene has moving circles
    gets the NumPy passes, which evaluate each step in its predicted scene (the compiled
    passes hold one scene over the horizon); ``backend="compiled"`` is refused for it."""
    if backend == "numpy":
        return PassesTwin(problem, T)
    if predicts(problem.model):
        if backend == "compiled":
            raise fail("backend", backend, "the compiled iLQG passes hold one scene over the "
                       "horizon; a model whose scene has moving circles (predicted per step) "
                       "runs on 'numpy' or 'auto'")
        return PassesTwin(problem, T)
    lib = problem_library(problem)
    if lib is None:
        if backend == "compiled":
            raise fail("backend", backend, "no C compiler is available; use 'numpy' or 'auto'")
        return PassesTwin(problem, T)
    return CompiledPasses(problem, T, lib)


def ilqg(problem: Problem, x0, U0, P=None, options: ILQGOptions | None = None,
         passes=None, scene=None) -> ILQGResult:
    """Solve min_U sum_k l(x_k,u_k,p_k) + l_T(x_T,p_T) s.t. x_{k+1} = F(x_k,u_k), u in the box.

    x0 may be a physical state (it is lifted for barrier-embedded models). U0 (T,nu) is the
    initial guess; if its rollout crashes or is not finite, zeros are used (assumptions §6.1) and
    ``initial_guess_replaced`` is set. ``scene``: the obstacles (see
    :meth:`~workbench.problem.Model.scene_vector`; default the model's own), held fixed over
    the horizon, except its moving circles, predicted at each step's time
    (:mod:`workbench.problem.prediction`).
    """
    opts = options or ILQGOptions()
    t_start = time.perf_counter()
    scene_v = problem.scene_vector(scene)
    x0 = problem.check_initial_state(x0, scene_v)
    _check_start_margin(problem, x0, scene_v)
    U = problem.check_controls(U0)
    T = U.shape[0]
    if T < 1:
        raise fail("U0", U.shape, "the horizon must have at least one step")
    P = problem.check_params(P, T)
    umin, umax = problem.model.u_min, problem.model.u_max
    boxed = opts.box_qp and bool(np.any(np.isfinite(umin)) or np.any(np.isfinite(umax)))
    reg = 0 if opts.regularization == "control" else 1
    passes = passes or make_passes(problem, T, opts.backend)
    passes.set_scene(scene_v)
    zeros_k, zeros_K = np.zeros((T, problem.nu)), np.zeros((T, problem.nu, problem.nx))

    def open_loop(Uc):
        return passes.forward(x0, np.zeros((T + 1, problem.nx)), Uc, zeros_k, zeros_K, P, 0.0,
                              umin, umax, use_policy=False)

    fw = open_loop(U)
    replaced = False
    if not np.isfinite(fw.cost) or fw.cost >= 1e10:
        fw = open_loop(np.zeros_like(U))
        replaced = True
        if not np.isfinite(fw.cost) or fw.cost >= 1e10:
            raise fail("U0", U0, "neither the initial guess nor zero controls give a safe, "
                       "finite rollout from x0 = " + np.array2string(x0, precision=6)
                       + _zero_rollout_failure(problem, fw.X, scene_v))
    X, U, J = fw.X, fw.U, fw.cost
    if opts.outer_loop == "compiled" and hasattr(passes, "solve"):
        return _compiled_loop(passes, opts, x0, X, U, J, P, reg, boxed, t_start, replaced)
    mu, delta = opts.mu_init, 1.0
    k, K = zeros_k, zeros_K
    history: list[Iteration] = []
    stop, converged, d = "max_iter", False, None
    fallback = opts.second_order and opts.gauss_newton_fallback
    mu_cap = min(opts.fallback_mu, opts.mu_max)
    for it in range(1, opts.max_iter + 1):
        t_it = time.perf_counter()
        if d is None:
            d = passes.derivatives(X, U, P)
        mu0, delta0, second = mu, delta, opts.second_order
        kind: Step = "second_order" if second else "gauss_newton"
        while True:  # the second-order attempt, then (fallback) the Gauss-Newton one
            outcome = "searched"
            while True:
                bw = passes.backward(d, U, umin, umax, mu, reg, boxed, second)
                k, K, dV = bw.k, bw.K, bw.dV
                if bw.status == 0:
                    break
                delta = max(delta * opts.mu_factor, opts.mu_factor)
                mu = max(mu * delta, opts.mu_min)
                if second and fallback and mu > mu_cap:
                    outcome = "indefinite"
                    break
                if mu > opts.mu_max:
                    outcome = "regularization_limit"
                    break
            if outcome == "searched":
                grad_norm = float(np.mean(np.max(np.abs(k) / (np.abs(U) + 1.0), axis=1)))
                if grad_norm < opts.tol_grad and mu < 1e-5:
                    outcome = "gradient"
                else:
                    ls = passes.line_search(x0, X, U, k, K, P, J, dV, opts.alphas, opts.z_min,
                                            umin, umax)
            if outcome in ("regularization_limit", "gradient") or not (
                    second and fallback and (outcome == "indefinite" or not ls.accepted)):
                break
            second, kind, mu, delta = False, "fallback", mu0, delta0
        if outcome == "regularization_limit":
            stop = "regularization_limit"
            break
        if outcome == "gradient":
            delta = min(delta / opts.mu_factor, 1.0 / opts.mu_factor)
            mu = mu * delta * (mu > opts.mu_min)
            stop, converged = "gradient", True
            history.append(Iteration(iteration=it, cost=J, cost_change=0.0, expected_change=0.0,
                                     alpha=0.0, mu=mu, grad_norm=grad_norm, accepted=False,
                                     time_s=time.perf_counter() - t_it, step=kind))
            break
        dJ = J - ls.cost
        if ls.accepted:
            delta = min(delta / opts.mu_factor, 1.0 / opts.mu_factor)
            mu = mu * delta * (mu > opts.mu_min)
            X, U, J, d = ls.X, ls.U, ls.cost, None
            history.append(Iteration(iteration=it, cost=J, cost_change=dJ,
                                     expected_change=ls.expected, alpha=ls.alpha, mu=mu,
                                     grad_norm=grad_norm, accepted=True,
                                     time_s=time.perf_counter() - t_it, step=kind))
            if dJ <= max(opts.tol_abs, opts.tol_rel * abs(J)):
                stop, converged = "cost_change", True
                break
        else:
            delta = max(delta * opts.mu_factor, opts.mu_factor)
            mu = max(mu * delta, opts.mu_min)
            history.append(Iteration(iteration=it, cost=J, cost_change=0.0, expected_change=0.0,
                                     alpha=0.0, mu=mu, grad_norm=grad_norm, accepted=False,
                                     time_s=time.perf_counter() - t_it, step=kind))
            if mu > opts.mu_max:
                stop = "line_search_failed"
                break
    if d is None:  # gains about the returned trajectory, for use as a feedback policy
        d = passes.derivatives(X, U, P)
        bw = passes.backward(d, U, umin, umax, mu, reg, boxed, opts.second_order)
        if bw.status != 0 and fallback:
            bw = passes.backward(d, U, umin, umax, mu, reg, boxed, False)
        if bw.status == 0:
            k, K = bw.k, bw.K
    return ILQGResult(
        X=X, U=U, k=k, K=K, cost=float(J), converged=converged, stop_reason=stop,
        iterations=len(history), history=tuple(history), backend=passes.name,
        solve_time_s=time.perf_counter() - t_start, initial_guess_replaced=replaced,
    )


def _check_start_margin(problem: Problem, x0: np.ndarray, scene: np.ndarray) -> None:
    """The forward pass counts a margin below ``CRASH_MARGIN`` (1e-15) as a crash: a start on
    an obstacle's boundary up to rounding (0 < h < 1e-15) is refused here, naming x0, rather
    than later as a crashed rollout of the initial guess."""
    if not problem.nh:
        return
    h = problem.model.margins(x0, scene)
    if np.all(h >= CRASH_MARGIN):
        return
    where = margin_violation(problem.model, h, CRASH_MARGIN)
    raise fail("x0", x0, f"{where}: on the boundary up to rounding (min h = 0), where the "
               "solver's rollouts count a crash; the start must be strictly safe")


def _zero_rollout_failure(problem: Problem, X: np.ndarray, scene: np.ndarray) -> str:
    """Where the zero-control rollout X failed: its first non-finite state or the first state
    whose margin is below the crash margin; empty when neither (its cost was too large)."""
    bad = np.flatnonzero(~np.all(np.isfinite(X), axis=1))
    if bad.size:
        return f" (the zero-control rollout is not finite from step {int(bad[0])})"
    if not problem.nh:
        return ""
    for k, x in enumerate(X[1:], start=1):
        h = problem.model.margins(x, scene)
        if not np.all(h >= CRASH_MARGIN):
            i = int(np.argmin(h))
            return (f" (the zero-control rollout crashes at step {k}: h[{i}] = {h[i]:.4g}); "
                    "give an initial guess U0 that steers clear, or, if no control can, start "
                    "farther from the obstacle (or moving away from it)")
    return (" (the zero-control rollout stays safe but costs 1e10 or more, the crash penalty: "
            "e.g. a barrier state close to its cap)")


_STOPS = ("max_iter", "regularization_limit", "gradient", "cost_change", "line_search_failed")


def _compiled_loop(passes, opts: ILQGOptions, x0, X, U, J, P, reg, boxed, t_start, replaced):
    """The same outer loop in C (core.c ``wb_solve``); per-iteration times are the mean."""
    problem = passes.problem
    core = SolveOptions(
        max_iter=int(opts.max_iter), reg=int(reg), boxed=int(boxed),
        second_order=int(opts.second_order),
        gn_fallback=int(opts.second_order and opts.gauss_newton_fallback),
        fallback_mu=float(opts.fallback_mu),
        mu_init=float(opts.mu_init),
        mu_factor=float(opts.mu_factor), mu_min=float(opts.mu_min), mu_max=float(opts.mu_max),
        z_min=float(opts.z_min), tol_abs=float(opts.tol_abs), tol_rel=float(opts.tol_rel),
        tol_grad=float(opts.tol_grad))
    res = passes.solve(x0, X, U, J, P, problem.model.u_min, problem.model.u_max, core,
                       opts.alphas)
    elapsed = time.perf_counter() - t_start
    per = elapsed / max(len(res.history), 1)
    history = tuple(Iteration(iteration=i + 1, cost=float(h[0]), cost_change=float(h[1]),
                              expected_change=float(h[2]), alpha=float(h[3]), mu=float(h[4]),
                              grad_norm=float(h[5]), accepted=bool(h[6]), time_s=per,
                              step=STEPS[int(h[7])])
                    for i, h in enumerate(res.history))
    return ILQGResult(X=res.X, U=res.U, k=res.k, K=res.K, cost=res.cost,
                      converged=res.converged, stop_reason=_STOPS[res.stop],
                      iterations=len(history), history=history, backend=passes.name,
                      solve_time_s=elapsed, initial_guess_replaced=replaced)

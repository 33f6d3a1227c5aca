"""The augmented-Lagrangian feedback law of Robust MPPI (what it shares with the ECBF law:
:mod:`workbench.sampling.feedback`).

* :class:`ALFeedback` — one derivative evaluation and one backward pass of the AL-iLQG inner
  problem (:func:`workbench.ilqg.al.al_problem`, the PHR augmented Lagrangian) with the current
  multipliers. Multipliers are carried from step to step in the returned :class:`ALGains`
  (shifted by the stride) and updated once per call on the nominal rollout,
  lambda <- min(lambda_max, max(0, lambda + mu c(x_k))): one outer AL iteration per control
  step, a real-time-iteration reading of AL-iLQG (Diehl, Bock & Schlöder 2005) in which the
  sampler, not an inner iLQG solve, moves the primal trajectory. Where no penalty term is
  active (mu c + lambda <= 0 everywhere) the gains are exactly the plain tracking gains. The
  inner problem's state Hessian is Gauss-Newton (mu grad(c) grad(c)^T on the active terms), so
  the multipliers enter the gains only through the active set: their size moves only the
  feedforward term, which the sampler does not use. Warm-started multipliers keep a term
  active (mu c + lambda > 0) after the nominal has left the constraint boundary.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TypedDict

import numpy as np

from workbench.codegen.fastcall import FastFunction
from workbench.ilqg import make_passes
from workbench.ilqg.al import al_problem
from workbench.problem.costs import quadratic_tracking
from workbench.problem.models import Model
from workbench.problem.prediction import predicts
from workbench.sampling.feedback.base import (
    FeedbackWeights,
    Gains,
    check_plain_law,
    fallback_gains,
    pad_gains,
    regularised_backward,
)
from workbench.validation import as_array, fail, real


@dataclass(frozen=True)
class ALFeedbackOptions:
    """PHR settings of :class:`ALFeedback`.

    mu: the penalty, fixed over time and horizon ([A] 1e3: with the default tracking weights
    Q = (500, 500, 100, 100) the Gauss-Newton term mu grad(c) grad(c)^T of an active circle
    constraint (|grad c| ~ 2 r) is then of the order of Q; with ALOptions' mu_init = 1 it would
    barely move the gains). lambda_init: the multipliers of the first call and of the steps
    that enter at the end of the horizon. lambda_max: cap of the update (a nominal that stays
    in violation would otherwise grow the multipliers without bound).
    """

    mu: float = 1e3
    lambda_init: float = 0.0
    lambda_max: float = 1e8

    def __post_init__(self) -> None:
        real("ALFeedbackOptions.mu", self.mu, 0.0, strict=True)
        real("ALFeedbackOptions.lambda_init", self.lambda_init, 0.0)
        real("ALFeedbackOptions.lambda_max", self.lambda_max, 0.0, strict=True)
        if self.lambda_max < self.lambda_init:
            raise fail("ALFeedbackOptions.lambda_max", self.lambda_max,
                       f"must be >= lambda_init = {self.lambda_init}")


@dataclass(frozen=True)
class ALGains(Gains):
    """Gains of :class:`ALFeedback` with the multipliers for the next call.

    multipliers (T+1, nh): lambda after this call's update (row k belongs to x_k of this call's
    horizon; row 0 stays 0: x_0 is fixed). multipliers_used: the ones the gains were computed
    with."""

    multipliers: np.ndarray | None = None
    multipliers_used: np.ndarray | None = None


class _ALRecord(TypedDict):
    """The :class:`ALGains` fields a call sets whether or not its gains are computed."""

    nominal_unsafe: bool
    activity: Mapping[str, float]
    multipliers: np.ndarray
    multipliers_used: np.ndarray


class ALFeedback:
    """Gains of the AL-iLQG inner problem about the nominal rollout (see the module docstring).

    ``model``: a plain model with margins h(x) (constraints c = -h <= 0); ``nx_full``: the
    sampler's state size (gains zero-padded to it). The scene rides in the AL parameters
    (per time: moving circles predicted to each state's time).
    Fallbacks as in :class:`~workbench.sampling.feedback.ilqg.ILQGFeedback`: when the derivatives or
    the gains are not finite, or the backward pass fails at every regularisation level, the
    previous gains shifted by the stride are used and the reason is reported (K = 0 only when
    there are no previous gains, also reported). The multiplier update does not depend on the
    gains and happens in every call with a finite nominal rollout.

    Activity: ``al_active`` — the share of the horizon's constrained steps x_1..x_T where some
    penalty term is active (mu c + lambda > 0) in the gains' parameters: only an active term
    moves the gains away from the plain tracking gains (its Gauss-Newton term mu grad(c)
    grad(c)^T). Robust MPPI counts it only on steps where the gains reach the plant (the
    nominal state differs from the measured one, :mod:`workbench.sampling.feedback.effect`).
    """

    def __init__(self, model: Model, horizon: int, nx_full: int,
                 weights: FeedbackWeights = FeedbackWeights(),
                 options: ALFeedbackOptions = ALFeedbackOptions(), name: str = "al_ilqg"):
        check_plain_law(model, horizon, nx_full, weights, "ALFeedback")
        if not isinstance(options, ALFeedbackOptions):
            raise fail("options", options, "must be an ALFeedbackOptions")
        cost = quadratic_tracking(model, Q=weights.Q, R=weights.R, S=weights.Q)
        self.tracking_cost = cost
        self.al = al_problem(model, cost)
        self.problem = self.al.problem
        self.passes = make_passes(self.problem, horizon)
        self.passes.set_scene(np.zeros(0))  # the inner model has none: the scene is in P
        self.model, self.name, self.w, self.opt = model, name, weights, options
        self.T, self.nx_full, self.nh = horizon, nx_full, model.nh
        nx, nu = model.nx, model.nu
        self._zk, self._zK = np.zeros((horizon, nu)), np.zeros((horizon, nu, nx))
        self._X0 = np.zeros((horizon + 1, nx))
        self._c = FastFunction(self.al.constraints, horizon + 1, shared=(1,))
        self.set_scene(None)

    def set_scene(self, scene) -> None:
        """The obstacles the gains and the multiplier update use (see
        :meth:`~workbench.problem.Model.scene_vector`; None: the model's own)."""
        self._scene = self.model.scene_vector(scene)
        z = np.zeros((self.T + 1, self.nh))
        # the open-loop rollout's cost is not used: any parameters with mu > 0 will do
        self._P0 = self.al.params(np.zeros((self.T + 1, self.al.n_base_params)), z,
                                  z + self.opt.mu, self._scene)

    def nominal(self, x_nom: np.ndarray, U: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The clipped open-loop nominal trajectory (X (T+1, nx), U (T, nu))."""
        m = self.model
        fw = self.passes.forward(x_nom[: m.nx], self._X0, U, self._zk, self._zK, self._P0, 0.0,
                                 m.u_min, m.u_max, use_policy=False)
        return fw.X, fw.U

    def constraint_values(self, X: np.ndarray) -> np.ndarray:
        """c(x_k) = -h(x_k) (T+1, nh) along X (T+1, nx) in the current scene (x_k in the
        scene predicted to k dt when it has moving circles)."""
        if predicts(self.model):
            return self.al.constraint_values(X, self._scene)
        return self._c(X, self._scene)[0].reshape(self.T + 1, self.nh)

    def initial_multipliers(self) -> np.ndarray:
        lam = np.full((self.T + 1, self.nh), self.opt.lambda_init)
        lam[0] = 0.0
        return lam

    def warm_start(self, previous: Gains | None, stride: int) -> np.ndarray:
        """The multipliers of this call: the previous call's (after its update) shifted by
        ``stride``, new tail rows at lambda_init; lambda_init without a previous AL call."""
        lam = self.initial_multipliers()
        prev = getattr(previous, "multipliers", None)
        if prev is None or prev.shape != lam.shape:
            return lam
        s = max(int(stride), 0)
        lam[1 : self.T + 1 - s] = prev[1 + s :]
        return lam

    def params(self, X: np.ndarray, U: np.ndarray, lam: np.ndarray) -> np.ndarray:
        """AL parameters: track (X, U) with multipliers ``lam``, penalty mu, this scene."""
        P_base = self.tracking_cost.params(self.T, x_ref=X, u_ref=np.vstack([U, U[-1:]]))
        mu = np.full((self.T + 1, self.nh), self.opt.mu)
        return self.al.params(P_base, lam, mu, self._scene)

    def gains(self, x_nom, U, previous: Gains | None, stride: int) -> ALGains:
        U = as_array("U", U, (self.T, self.model.nu))
        X, Uc = self.nominal(x_nom, U)
        lam = self.warm_start(previous, stride)
        C = self.constraint_values(X) if np.all(np.isfinite(X)) else np.full(lam.shape, np.nan)
        finite_c = bool(np.all(np.isfinite(C)))
        unsafe = finite_c and bool(np.max(C) >= 0.0)
        active = (self.opt.mu * C[1:] + lam[1:] > 0.0).any(axis=1) if finite_c else None
        activity = {"al_active": float(active.mean()) if active is not None else 0.0}
        lam_next = lam.copy()
        if finite_c:
            lam_next[1:] = np.minimum(self.opt.lambda_max,
                                      np.maximum(0.0, lam[1:] + self.opt.mu * C[1:]))
        m = self.model
        record: _ALRecord = {"nominal_unsafe": unsafe, "activity": activity,
                             "multipliers": lam_next, "multipliers_used": lam}
        d = self.passes.derivatives(X, Uc, self.params(X, Uc, lam))
        K, mu, reason = regularised_backward(self.passes, d, Uc, m, self.w.mu, self.w.mu_max)
        if K is not None:
            return ALGains(K=pad_gains(K, self.nx_full), fallback=None, mu=mu, **record)
        K = fallback_gains(previous, stride, (self.T, m.nu, self.nx_full))
        return ALGains(K=K, fallback=reason, mu=np.nan, **record)

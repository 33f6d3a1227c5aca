"""Tracking feedback from iLQG: :class:`ILQGFeedback` on the barrier-embedded model gives
K_safe of SA-RMPPI (assumptions §10.2), on the physical model the plain iLQG tracking gains of
RMPPI (assumptions §9.4). The gains come from one derivative evaluation and one backward pass
along the clipped open-loop nominal rollout (see :mod:`workbench.sampling.feedback.base`);
:meth:`ILQGFeedback.fast_gains` is the same in one compiled call
(:mod:`workbench.sampling.feedback.compiled`).

Moving circles (a scene with moving slots): the rollout, derivatives and backward pass see
each step's predicted scene (the NumPy passes, :func:`~workbench.ilqg.make_passes`); there is
no compiled law for such a model (:meth:`ILQGFeedback.fast_gains` then calls
:meth:`ILQGFeedback.gains`).
"""

from __future__ import annotations

import numpy as np

from workbench.codegen.fastcall import FastFunction
from workbench.ilqg import make_passes
from workbench.problem.costs import quadratic_tracking
from workbench.problem.models import Model
from workbench.problem.prediction import predicts, scene_at
from workbench.problem.problem import Problem
from workbench.sampling.feedback.base import (
    FeedbackWeights,
    Gains,
    pad_gains,
    regularised_backward,
    shifted,
)
from workbench.sampling.feedback.compiled import KSafeKernel, ksafe_library
from workbench.validation import as_array, fail, flag


class ILQGFeedback:
    """Tracking gains from one iLQG derivative evaluation and backward pass.

    ``model`` is the model whose state the gains act on: the barrier-embedded model gives
    K_safe (the β cost shapes the gains through the barrier's curvature), the physical model
    the plain tracking gains of RMPPI. ``nx_full`` is the sampler's state size (gains are
    zero-padded to it).

    :meth:`gains` computes the gains step by step (the passes' own calls from Python);
    :meth:`fast_gains` computes the same gains in one compiled call
    (:mod:`workbench.sampling.feedback.compiled`, built at its first call when ``compiled`` is
    True, the default, and a C compiler is available; else it calls :meth:`gains`).
    """

    def __init__(self, model: Model, horizon: int, nx_full: int,
                 weights: FeedbackWeights = FeedbackWeights(), name: str | None = None,
                 compiled: bool = True):
        n = model.n_physical
        if len(weights.Q) != n:
            raise fail("FeedbackWeights.Q", weights.Q, f"need {n} entries (the physical state "
                       f"of {model.name}); FeedbackWeights.for_model sizes them")
        if len(weights.R) != model.nu:
            raise fail("FeedbackWeights.R", weights.R, f"need {model.nu} entries")
        embedded = model.nx > n
        cost = quadratic_tracking(model, Q=weights.Q, R=weights.R, S=weights.Q,
                                  q_beta=weights.q_beta if embedded else 0.0,
                                  s_beta=weights.q_beta if embedded else 0.0,
                                  beta_cost="absolute")
        self.problem = Problem.build(model, cost)
        self.passes = make_passes(self.problem, horizon)
        self.name = name or ("bas_ilqg" if embedded else "ilqg")
        self.w, self.T, self.nx_full = weights, horizon, nx_full
        nu, nxf = model.nu, model.nx
        self._zk, self._zK = np.zeros((horizon, nu)), np.zeros((horizon, nu, nxf))
        self._X0 = np.zeros((horizon + 1, nxf))
        # the open-loop rollout's cost is not used: any parameters will do
        self._P0 = np.zeros((horizon + 1, self.problem.n_p))
        if model.nh:
            self._margins = FastFunction(model.margins_function, horizon + 1, shared=(1,))
        self._ksafe: KSafeKernel | None = None
        # built on first use; never for moving circles (the compiled law holds one scene)
        self._want_compiled = flag("ILQGFeedback.compiled", compiled) and not predicts(model)
        self.set_scene(None)

    @property
    def compiled(self) -> bool:
        """:meth:`fast_gains` runs as one compiled call (builds it when not built yet)."""
        return self._kernel() is not None

    def _kernel(self) -> KSafeKernel | None:
        if self._ksafe is None and self._want_compiled:
            self._want_compiled = False  # one attempt: None without a compiler
            lib = ksafe_library(self.problem)
            if lib is not None:
                self._ksafe = KSafeKernel(self.problem, self.T, lib)
                self._ksafe.set_scene(self._scene)
        return self._ksafe

    def set_scene(self, scene) -> None:
        """The obstacles the gains are computed in (see
        :meth:`~workbench.problem.Model.scene_vector`; None: the model's own)."""
        self._scene = self.problem.model.scene_vector(scene)
        self.passes.set_scene(self._scene)
        if self._ksafe is not None:
            self._ksafe.set_scene(self._scene)

    def nominal(self, x_nom: np.ndarray, U: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The clipped open-loop nominal trajectory (X (T+1, nx), U (T, nu))."""
        m = self.problem.model
        fw = self.passes.forward(x_nom[: self.problem.nx], self._X0, U, self._zk, self._zK,
                                 self._P0, 0.0, m.u_min, m.u_max, use_policy=False)
        return fw.X, fw.U

    def _params(self, X, U) -> np.ndarray:
        """Track the nominal trajectory itself: x_ref = X (physical part), u_ref = U."""
        n = self.problem.model.n_physical
        return self.problem.cost.params(self.T, x_ref=X[:, :n], u_ref=np.vstack([U, U[-1:]]))

    def fast_gains(self, x_nom, U, previous: Gains | None, stride: int) -> Gains:
        """:meth:`gains` in one compiled call (the same numbers); :meth:`gains` itself when
        the law is not compiled."""
        k = self._ksafe or self._kernel()
        if k is None:
            return self.gains(x_nom, U, previous, stride)
        U = as_array("U", U, (self.T, self.problem.nu))
        r = k(np.asarray(x_nom, dtype=float)[: self.problem.nx], U, self.w.mu,
                        self.w.mu_max)
        if r.reason == "nonfinite_rollout":  # refused by the tracking parameters' checks
            return self.gains(x_nom, U, previous, stride)
        if r.reason is None:
            return Gains(K=self._pad(r.K), fallback=None, nominal_unsafe=r.unsafe, mu=r.mu)
        return self._fallback(r.reason, r.unsafe, previous, stride)

    def gains(self, x_nom, U, previous: Gains | None, stride: int) -> Gains:
        """Gains about the clipped open-loop rollout of ``U`` from ``x_nom``, step by step;
        on failure the previous gains shifted by ``stride`` (K = 0 without previous ones) and
        the reason. :meth:`fast_gains` is the same in one compiled call."""
        U = as_array("U", U, (self.T, self.problem.nu))
        X, Uc = self.nominal(x_nom, U)
        m = self.problem.model
        if predicts(m):  # x_k in the scene of its time, k dt
            h = [m.margins(X[j, : m.n_physical], scene_at(m, self._scene, j * m.dt))
                 for j in range(X.shape[0])]
            unsafe = bool(np.min(h) <= 0.0)
        else:
            unsafe = bool(m.nh) and bool(
                np.min(self._margins(X[:, : m.n_physical], self._scene)[0]) <= 0.0)
        d = self.passes.derivatives(X, Uc, self._params(X, Uc))
        K, mu, reason = regularised_backward(self.passes, d, Uc, m, self.w.mu, self.w.mu_max)
        if K is not None:
            return Gains(K=self._pad(K), fallback=None, nominal_unsafe=unsafe, mu=mu)
        return self._fallback(reason or "backward_failed", unsafe, previous, stride)

    def _fallback(self, reason: str, unsafe: bool, previous: Gains | None,
                  stride: int) -> Gains:
        m = self.problem.model
        if previous is None:
            # no earlier gains to shift: the only honest finite choice left is K = 0, reported
            return Gains(K=np.zeros((self.T, m.nu, self.nx_full)), fallback=reason,
                         nominal_unsafe=unsafe, mu=np.nan)
        return Gains(K=shifted(previous.K, stride), fallback=reason, nominal_unsafe=unsafe,
                     mu=np.nan)

    def _pad(self, K: np.ndarray) -> np.ndarray:
        return pad_gains(K, self.nx_full)

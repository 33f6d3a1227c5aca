"""What every feedback law of Robust MPPI shares: gains K_k (T, nu, nx) about the nominal
trajectory, the law's protocol, the zero law and the fallback rules.

A :class:`FeedbackLaw` turns the nominal state x*_0 and the nominal control sequence u* into
gains for the SAIS dual rollout (assumptions §9.2, §10.1) and for the applied
control (assumptions §9.5):

* :class:`ILQGFeedback` on the barrier-embedded model — K_safe of SA-RMPPI (assumptions §10.2);
* :class:`ILQGFeedback` on the physical model — the plain iLQG tracking feedback of RMPPI
  (assumptions §9.4); its gains on the barrier state are zero;
* :class:`NoFeedback` — K = 0 (SAIS then reduces to MPPI sampling).

The gains are one derivative evaluation and one backward pass along the nominal trajectory the
sampler actually uses (the clipped open-loop rollout of u* from x*_0) with the tracking cost
½|x-x*|²_Q + ½ q_beta β² + ½|u-u*|²_R. They are the unconstrained (no box QP) gains: the kernels
clip every control, so a gain on a saturated input still acts once the input leaves the limit.
A nominal rollout that leaves the safe set needs no special case: the barrier's crash rule
(β = β_max, assumptions §4.6) keeps the derivatives finite. When the backward pass fails at every
regularisation level, or the derivatives are not finite, the previous gains shifted by the
stride are used and the reason is reported — the gains are never silently set to zero.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from workbench.problem.models import Model
from workbench.validation import fail, integer, real

FALLBACK_REASONS = ("backward_failed", "nonfinite_derivatives", "nonfinite_gains")


@dataclass(frozen=True)
class FeedbackWeights:
    """Tracking weights of the feedback law (assumptions §9.4, §10.2 [A]); sized to the model."""

    Q: tuple[float, ...] = (500.0, 500.0, 100.0, 100.0)
    R: tuple[float, ...] = (1.0, 1.0)
    q_beta: float = 1.0
    mu: float = 1e-6  # first regularisation level of the backward pass
    mu_max: float = 1e6

    def __post_init__(self) -> None:
        for name in ("Q", "R"):
            w = np.asarray(getattr(self, name), dtype=float)
            if w.ndim != 1 or not np.all(np.isfinite(w)) or np.any(w < 0):
                raise fail(f"FeedbackWeights.{name}", getattr(self, name),
                           "must be a sequence of finite numbers >= 0")
            object.__setattr__(self, name, tuple(float(v) for v in w))
        for name in ("q_beta", "mu", "mu_max"):
            real(f"FeedbackWeights.{name}", getattr(self, name), 0.0)
        if not self.mu_max > self.mu:
            raise fail("FeedbackWeights.mu_max", self.mu_max, f"must exceed mu = {self.mu}")

    @classmethod
    def for_model(cls, model: Model, q: float = 100.0, r: float = 1.0, **kw) -> FeedbackWeights:
        """Uniform weights sized to a model's physical state and control."""
        return cls(Q=(q,) * model.n_physical, R=(r,) * model.nu, **kw)


@dataclass(frozen=True)
class Gains:
    """Feedback gains and how they were obtained."""

    K: np.ndarray  # (T, nu, nx) on the full (embedded) state
    fallback: str | None = None  # one of FALLBACK_REASONS, or None when computed
    nominal_unsafe: bool = False  # the nominal rollout left the safe set (crash-safe gains)
    mu: float = 0.0  # regularisation used
    # how often the law's own safety mechanism acted for these gains, in [0, 1] (e.g. the
    # share of horizon steps with an active constraint); empty for laws without one
    activity: Mapping[str, float] = field(default_factory=dict)


class FeedbackLaw(Protocol):
    """Gains about the nominal trajectory of (x*_0, u*)."""

    name: str

    def gains(self, x_nom: np.ndarray, U: np.ndarray, previous: Gains | None,
              stride: int) -> Gains: ...

    def set_scene(self, scene) -> None:
        """Compute the following gains in this scene (flat scene vector)."""


class NoFeedback:
    """K = 0."""

    name = "none"

    def __init__(self, nx: int, nu: int):
        self.nx, self.nu = nx, nu

    def gains(self, x_nom, U, previous, stride) -> Gains:
        return Gains(K=np.zeros((U.shape[0], self.nu, self.nx)))

    def set_scene(self, scene) -> None:
        """K = 0 in every scene."""


def shifted(K: np.ndarray, stride: int) -> np.ndarray:
    """Gains slid by ``stride`` steps, the last one held."""
    if stride <= 0:
        return K
    out = np.empty_like(K)
    out[:-stride] = K[stride:]
    out[-stride:] = K[-1]
    return out


def check_plain_law(model: Model, horizon: int, nx_full: int, weights: FeedbackWeights,
                 law: str) -> None:
    """Validate a feedback law's plain (physical) model, horizon, state size and weights."""
    integer("horizon", horizon, 1)
    integer("nx_full", nx_full, model.nx)
    if model.n_physical != model.nx:
        raise fail("model", model.name, f"{law} acts on the plain (physical) model; pass "
                   "workbench.sampling.planning.physical_model(embedded_model)")
    if model.nh == 0:
        raise fail("model.h", model.name, f"{law} needs at least one safety margin")
    if len(weights.Q) != model.nx:
        raise fail("FeedbackWeights.Q", weights.Q, f"need {model.nx} entries (the state of "
                   f"{model.name}); FeedbackWeights.for_model sizes them")
    if len(weights.R) != model.nu:
        raise fail("FeedbackWeights.R", weights.R, f"need {model.nu} entries")


def pad_gains(K: np.ndarray, nx_full: int) -> np.ndarray:
    """Gains (T, nu, nx) zero-padded to the sampler's state size (gains on beta are 0)."""
    if K.shape[2] == nx_full:
        return K
    out = np.zeros((K.shape[0], K.shape[1], nx_full))
    out[:, :, : K.shape[2]] = K
    return out


def regularised_backward(passes, d: Mapping[str, np.ndarray], U: np.ndarray, model: Model,
                         mu: float, mu_max: float) -> tuple[np.ndarray | None, float, str | None]:
    """One backward pass of ``passes`` on the derivatives ``d`` about the controls ``U``, the
    regularisation raised tenfold (from at least 1e-8) until it succeeds, up to ``mu_max``:
    ``(K, mu, None)``, or ``(None, nan, reason)`` with a reason of :data:`FALLBACK_REASONS`."""
    if not all(np.all(np.isfinite(a)) for a in d.values()):
        return None, np.nan, "nonfinite_derivatives"
    while mu <= mu_max:
        bw = passes.backward(d, U, model.u_min, model.u_max, mu, 0, False)
        if bw.status == 0:
            if not np.all(np.isfinite(bw.K)):
                return None, np.nan, "nonfinite_gains"
            return bw.K, mu, None
        mu = max(mu * 10.0, 1e-8)
    return None, np.nan, "backward_failed"


def fallback_gains(previous: Gains | None, stride: int, shape: tuple[int, int, int]) -> np.ndarray:
    """The gains of a failed computation: the previous ones shifted, or (none) K = 0."""
    if previous is None or previous.K.shape != shape:
        return np.zeros(shape)
    return shifted(previous.K, stride)

"""Feedback laws for Robust MPPI: gains K_k (T, nu, nx) about the nominal trajectory.

* :mod:`~workbench.sampling.feedback.base` — what every law shares: :class:`FeedbackWeights`,
  :class:`Gains`, the :class:`FeedbackLaw` protocol, :class:`NoFeedback` (K = 0) and the
  fallback rules (:data:`FALLBACK_REASONS`, :func:`shifted`, :func:`fallback_gains`);
* :mod:`~workbench.sampling.feedback.ilqg` — :class:`ILQGFeedback`: K_safe from BaS-iLQG
  (SA-RMPPI) or plain iLQG tracking gains (RMPPI);
* :mod:`~workbench.sampling.feedback.compiled` — K_safe in one compiled call (the library
  behind :meth:`ILQGFeedback.fast_gains`);
* :mod:`~workbench.sampling.feedback.al` — :class:`ALFeedback`: gains from an augmented
  Lagrangian iLQG on the plain model;
* :mod:`~workbench.sampling.feedback.ecbf` — :class:`ECBFFeedback`: the sensitivity of an
  exponential-CBF safety filter;
* :mod:`~workbench.sampling.feedback.effect` — what counts as a mechanism acting, for every
  method (an effect on what reaches the plant, by more than ``EFFECT_RTOL``); here because the
  laws use it too.

The AL and ECBF laws come from the paper's two other safety mechanisms. Next to K_safe (barrier
states, :class:`~workbench.sampling.feedback.ilqg.ILQGFeedback` on the barrier-embedded model),
these laws put the augmented Lagrangian and the ECBF filter inside the SAIS sampler, so the
three mechanisms can be compared with everything else equal. Both act on a plain (physical)
model with safety margins and zero-pad their gains to the sampler's state size; both linearise
about the nominal trajectory the sampler uses (the clipped open-loop rollout of u* from x*_0)
and track it with the cost of the plain iLQG feedback (½|x-x*|²_Q + ½|u-u*|²_R, terminal
½|x-x*|²_Q).
"""

from workbench.sampling.feedback.al import ALFeedback, ALFeedbackOptions, ALGains
from workbench.sampling.feedback.base import (
    FALLBACK_REASONS,
    FeedbackLaw,
    FeedbackWeights,
    Gains,
    NoFeedback,
    check_plain_law,
    fallback_gains,
    pad_gains,
    shifted,
)
from workbench.sampling.feedback.ecbf import ECBFFeedback, FilterSensitivity
from workbench.sampling.feedback.ilqg import ILQGFeedback

__all__ = [
    "FALLBACK_REASONS",
    "ALFeedback",
    "ALFeedbackOptions",
    "ALGains",
    "ECBFFeedback",
    "FeedbackLaw",
    "FeedbackWeights",
    "FilterSensitivity",
    "Gains",
    "ILQGFeedback",
    "NoFeedback",
    "check_plain_law",
    "fallback_gains",
    "pad_gains",
    "shifted",
]

"""Sampling-based control: MPPI, BaS-MPPI, Robust MPPI and SA-RMPPI on compiled kernels.

Public entry points for your own model (README: "Bring your own model"):
:class:`~workbench.sampling.problem.SamplingProblem` (``from_costs(model, q, phi, p)``: state
costs in CasADi), :func:`set_threads` (OpenMP threads of every sampler library),
:mod:`~workbench.sampling.controllers` (``MPPI``, ``RobustMPPI``),
:mod:`~workbench.sampling.feedback` (``FeedbackWeights.for_model``, ``ILQGFeedback``),
:mod:`~workbench.sampling.threshold` (alpha rules).
"""

from workbench.sampling.kernels.library import get_threads, set_threads
from workbench.sampling.problem import SamplingProblem

__all__ = ["SamplingProblem", "get_threads", "set_threads"]

"""Sampling-based control: MPPI, BaS-MPPI, Robust MPPI and SA-RMPPI on compiled kernels.

Public entry points for your own model (README: "Bring your own model"):
:class:`~workbench.sampling.problem.SamplingProblem` (``from_costs(model, q, phi, p)``: state
costs in CasADi), :func:`set_threads` (OpenMP threads of every sampler library),
:mod:`~workbench.sampling.mppi` (``MPPI``), :mod:`~workbench.sampling.robust` (``RobustMPPI``),
:mod:`~workbench.sampling.feedback` (``FeedbackWeights.for_model``, ``ILQGFeedback``),
:mod:`~workbench.sampling.threshold` (alpha rules).

The package:

* top-level modules — the sampling problem (``problem``), the controllers (``mppi``,
  ``robust`` with its vectorised step ``robust_step``), the planning helpers they share
  (``planning``), the batch sampler over the kernels (``sampler``), importance ``weights``,
  thresholds and their ``calibration``, per-step ``step_stats`` and recorded ``samples``; the
  kernels' plain NumPy twin (``twin``, sample-major; its model evaluation ``twin_model``);
* :mod:`~workbench.sampling.feedback` — the feedback laws of Robust MPPI (iLQG tracking and
  K_safe, its compiled form, AL and ECBF gains);
* :mod:`~workbench.sampling.methods` — the safe-sampling methods (Tube-MPPI, CBF projection,
  Shield-MPPI, gatekeeper), the sampler they share (``methods.sampler``) and the safe kernel's
  twin (``methods.twin``);
* :mod:`~workbench.sampling.kernels` — the generated C: the SX-to-C lane emitter, the cached
  and verified libraries, vector maths, the safe-sampling and candidate-start kernels.
"""

from workbench.sampling.kernels.library import get_threads, set_threads
from workbench.sampling.problem import SamplingProblem

__all__ = ["SamplingProblem", "get_threads", "set_threads"]

"""Lemma 1 (free-energy bound) estimators and checks, assumptions §11.2-§11.4.

* :mod:`.free_energy` — F̂ by log-sum-exp, Ê by the delta method / MPPI-G / bootstrap;
* :mod:`.tube` — tube radius R (pairwise, quantile, position-only, about the mean nominal);
* :mod:`.lipschitz` — local and global Lipschitz constants of q, φ, secant check; per-segment
  gradient maxima for the sampled-tube bound;
* :mod:`.disturbance` — D (a quantile of ‖w‖) and D_F;
* :mod:`.step` — :class:`BoundStep` from one SA-RMPPI step's first SAIS batch;
* :mod:`.checks` — T1, T2, T3, T3b, T3c, T3d (and T1s);
* :mod:`.episode` — :class:`BoundRecorder`, a controller wrapper for ``sim.closed_loop``;
* :mod:`.summary` — fractions holding (Wilson), slack quantiles, global/local ratios by stratum;
* :mod:`.tightness` — RHS/LHS on informative steps, shares within a factor, paired comparisons.
"""

from workbench.bound.checks import Check, episode_checks, step_checks, transition_checks
from workbench.bound.disturbance import chi_radius, d_f, disturbance_bound
from workbench.bound.episode import BoundRecorder
from workbench.bound.free_energy import (
    Bootstrap,
    FreeEnergy,
    bootstrap_free_energy,
    free_energy_estimate,
    free_energy_lse,
)
from workbench.bound.lipschitz import CostGradients, Lipschitz, LipschitzGrid, Segments
from workbench.bound.step import (
    BoundConfig,
    BoundEstimator,
    BoundStep,
    first_batch,
    independent_batch,
    sampled_deltas,
    with_diagnostics,
)
from workbench.bound.summary import STRATA, CheckSummary, summarize
from workbench.bound.tightness import Comparison, Tightness
from workbench.bound.tube import Tube, tube_radius

__all__ = [
    "STRATA",
    "Bootstrap",
    "BoundConfig",
    "BoundEstimator",
    "BoundRecorder",
    "BoundStep",
    "Check",
    "CheckSummary",
    "Comparison",
    "CostGradients",
    "FreeEnergy",
    "Lipschitz",
    "LipschitzGrid",
    "Segments",
    "Tightness",
    "Tube",
    "bootstrap_free_energy",
    "chi_radius",
    "d_f",
    "disturbance_bound",
    "episode_checks",
    "first_batch",
    "free_energy_estimate",
    "free_energy_lse",
    "independent_batch",
    "sampled_deltas",
    "step_checks",
    "summarize",
    "transition_checks",
    "tube_radius",
    "with_diagnostics",
]

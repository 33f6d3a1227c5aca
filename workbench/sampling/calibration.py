"""Calibrating the selection threshold alpha of Robust MPPI: one explicit, seeded step.

An alpha rule (:class:`~workbench.sampling.threshold.AlphaRule`) is read off an undisturbed
closed loop of the robust controller whose selection is switched off (alpha = +inf, so the
real-state candidate is always taken): the visited states and the free energy of the real-state
candidate at each step. :func:`calibrate` runs that episode and returns the threshold; call it
once and hand the threshold to every controller (and worker) that needs it.
"""

from __future__ import annotations

import warnings
from dataclasses import replace

import casadi as ca
import numpy as np

from workbench.problem.models import Model
from workbench.sampling.feedback.base import FeedbackLaw
from workbench.sampling.mppi import MPPIConfig
from workbench.sampling.problem import SamplingProblem
from workbench.sampling.robust import RMPPIConfig, RobustMPPI
from workbench.sampling.threshold import (
    AlphaRule,
    ConstantThreshold,
    Threshold,
    make_threshold,
)
from workbench.sim import closed_loop
from workbench.validation import fail, integer


def calibration_trace(problem: SamplingProblem, goal, plant: Model, x0, mppi: MPPIConfig,
                      feedback: FeedbackLaw, robust: RMPPIConfig = RMPPIConfig(), *,
                      steps: int = 600, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The undisturbed episode of ``steps`` plant steps from ``x0`` with alpha = +inf: visited
    plant states (n, nx_plant) and the real-state candidate free energies (n,) (NaN where a step
    evaluated no candidate). The controller draws from ``default_rng(seed)``, the plant from
    ``default_rng(seed + 1)`` (it draws nothing without a disturbance). The episode runs
    without ``mppi.deadline_s`` (every sample drawn): the threshold is reproducible and does
    not depend on the machine's load."""
    steps = integer("steps", steps, 1)
    seed = integer("seed", seed, 0)
    mppi = replace(mppi, deadline_s=None)
    # diagnostics off: the episode keeps every step's info, and a diagnostic batch is MBs
    ctrl = RobustMPPI(problem, goal, mppi, replace(robust, alpha=np.inf, diagnostics=False),
                      feedback, ConstantThreshold.selection_off())  # the explicit opt-out
    ep = closed_loop(ctrl, plant, x0, steps, np.random.default_rng(seed),
                     np.random.default_rng(seed + 1))
    F = np.array([i.candidate_free_energy[-1] if i.candidate_free_energy.size else np.nan
                  for i in ep.infos])
    if ep.crashed:
        warnings.warn(f"the undisturbed calibration episode crashed after {len(ep.U)} steps: "
                      "its free energies hold crash costs, so the selection threshold is so "
                      "high that the robust selection will seldom act; start further from "
                      "the constraints or check the sampler settings", stacklevel=3)
    return ep.X[: len(F)], F


def calibrate(rule: AlphaRule, problem: SamplingProblem, goal, plant: Model, x0,
              mppi: MPPIConfig, feedback: FeedbackLaw, robust: RMPPIConfig = RMPPIConfig(), *,
              seed: int = 0, trace: tuple[np.ndarray, np.ndarray] | None = None,
              progress: ca.SX | ca.Function | None = None) -> Threshold:
    """The threshold of ``rule`` for this problem, goal and start: a fixed rule directly, every
    other rule from :func:`calibration_trace` (``rule.calibration_steps`` steps, ``seed``), or
    from ``trace``, that function's result for the same controller (rules that differ only
    in how they read the episode can share it). The progress rule measures the distance to
    the goal in the plant's position coordinates, or by ``progress``: a scalar CasADi
    expression in ``plant.x`` (or a Function of the plant's state), >= 0 and 0 at the goal,
    for a model without position coordinates or with a better measure (e.g. a heading
    error)."""
    measure = _progress_function(progress, plant)
    if not rule.needs_calibration:
        return make_threshold(rule)
    X, F = trace if trace is not None else calibration_trace(
        problem, goal, plant, x0, mppi, feedback, robust, steps=rule.calibration_steps,
        seed=seed)
    return make_threshold(rule, X, F, goal, plant.position, measure)


def _progress_function(progress, plant: Model) -> ca.Function | None:
    if progress is None or isinstance(progress, ca.Function):
        if progress is not None and (progress.n_in() != 1 or progress.numel_in(0) != plant.nx
                                     or progress.numel_out(0) != 1):
            raise fail("progress", progress.name(), f"a progress Function maps the plant's "
                       f"state ({plant.nx}) to one number")
        return progress
    expr = ca.SX(progress)
    if expr.numel() != 1:
        raise fail("progress", expr.shape, "the progress measure must be a scalar expression")
    known = {v.name() for v in ca.symvar(plant.x)}
    extra = [v.name() for v in ca.symvar(expr) if v.name() not in known]
    if extra:
        raise fail("progress", extra, "may depend only on the plant's state symbols plant.x")
    return ca.Function("progress", [plant.x], [expr])

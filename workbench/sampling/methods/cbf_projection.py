"""MPPI with every sample control projected onto the discrete CBF constraint.

Tao, Kim, Yoon, Hovakimyan, Voulgaris, "Control Barrier Function Augmentation in Sampling-based
Control Algorithm for Sample Efficiency", ACC 2022, arXiv:2111.06974.

Each rollout step of each sample, the sampled control v0 = clip(u + sigma z) is moved to the
minimum-norm point of the linearised most restrictive discrete CBF constraint
c_{i*}(x, v) >= 0 (:mod:`workbench.problem.dcbf`) when that constraint is violated, and clipped
to the box (the safe kernel, :mod:`workbench.sampling.kernels.safe`, with project = 1 and no
DCBF cost). The likelihood ratio uses the effective noise v_hat - u (the projection is treated
like the clip) and the plan is updated to the weighted average of the *applied* sample
controls. With ``project_applied`` the control sent to the plant is projected once more, at the
measured state, by the same closed form (a CasADi Function evaluated in place).

Moving circles (a scene with moving slots): the rollouts predict them over the horizon (the
safe kernel: each step's constraints in the scene of its start state's time, its dynamics and
crash test in the next state's); the projection of the applied control acts at the current
step only and uses the present scene, as the kernel's first step does.

``record_samples(k)`` (:mod:`workbench.sampling.samples`) hands out the last batch's samples
with their projected controls (``nominal`` None).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from workbench.codegen.fastcall import FastFunction
from workbench.problem.dcbf import DEFAULT_GAMMA, check_gamma, discrete_cbf
from workbench.sampling.feedback.effect import differs
from workbench.sampling.kernels.safe import projection_function
from workbench.sampling.methods.sampler import (
    SafeMPPIController,
    SafeMPPIPlanner,
    SafeMPPIState,
    SafeOptions,
)
from workbench.sampling.mppi import MPPIConfig
from workbench.sampling.planning import shift_plan
from workbench.sampling.problem import SamplingProblem
from workbench.sampling.samples import RecordsSamples, SampleTrajectories
from workbench.sampling.step_stats import StepStats
from workbench.validation import fail, flag


@dataclass(frozen=True)
class CBFProjectionConfig:
    """``gamma`` in (0, 1]: the discrete CBF's class-K rate (default
    :data:`~workbench.problem.dcbf.DEFAULT_GAMMA`, an assumed value for the navigation double
    integrator, see there); ``project_applied``: project the applied control at the measured
    state too."""

    gamma: float = DEFAULT_GAMMA
    project_applied: bool = True

    def __post_init__(self) -> None:
        check_gamma("CBFProjectionConfig.gamma", self.gamma)
        flag("CBFProjectionConfig.project_applied", self.project_applied)


@dataclass(frozen=True, kw_only=True)
class CBFProjectionInfo:
    """One step. ``projected``: the last batch's share of sample-steps (out of N T) whose
    control the projection moved (by more than
    :data:`~workbench.sampling.feedback.effect.EFFECT_RTOL`: a violated constraint whose
    projection the box clips back, or whose gradient in u is 0, moves nothing and does not
    count); ``infeasible``: the share where the linearised constraint was violated and the
    projected control still violated a constraint (box clip), an event;
    ``applied_projected``: the applied control was moved at the measured state;
    ``applied_c_min``: min_i c_i at the measured state and the applied control (nan without
    ``project_applied``)."""

    free_energy: float
    ess: float
    n_crashed: int
    n_samples: int
    valid_weights: bool
    time_s: float
    projected: float
    infeasible: float
    applied_projected: bool
    applied_c_min: float
    samples: SampleTrajectories | None = None  # with record_samples, else None

    @property
    def stats(self) -> StepStats:
        return StepStats(n_samples=self.n_samples,
                         n_collision_free=self.n_samples - self.n_crashed, ess=self.ess,
                         activity={"projected": self.projected, "infeasible": self.infeasible,
                                   "applied_projected": float(self.applied_projected)})


class CBFProjectionMPPI(RecordsSamples, SafeMPPIController):
    """MPPI with per-sample CBF projection (see module docstring) on a sampling problem
    (physical or barrier-embedded). ``sampler`` is its
    :class:`~workbench.sampling.methods.sampler.SafeSampler`."""

    def __init__(self, sp: SamplingProblem, goal, config: MPPIConfig = MPPIConfig(),
                 cbf: CBFProjectionConfig | None = None):
        cbf = CBFProjectionConfig() if cbf is None else cbf
        if not isinstance(cbf, CBFProjectionConfig):
            raise fail("cbf", cbf, "must be a CBFProjectionConfig")
        self.sp, self.cfg, self.ccfg = sp, config, cbf
        self.dcbf = discrete_cbf(sp.model)
        self.planner = SafeMPPIPlanner(sp, goal, config,
                                       SafeOptions(project=True, w_dcbf=0.0, gamma=cbf.gamma))
        self.sampler = self.planner.sampler
        self._project = FastFunction(projection_function(self.dcbf))

    def project(self, xb, u) -> tuple[np.ndarray, bool, float]:
        """(v_hat, moved, min_i c_i(xb, v_hat)): the closed-form projection of clip(u) at the
        full state xb in the current scene; ``moved``: v_hat differs from clip(u)
        (:func:`~workbench.sampling.feedback.effect.differs`)."""
        lo, hi = self.sp.model.u_min, self.sp.model.u_max
        u0 = np.clip(u, lo, hi)
        v, _, cmin = self._project(xb, u0, self.ccfg.gamma, self.scene, lo, hi)
        return v, bool(differs(v, u0)), float(cmin[0])

    def step(self, state: SafeMPPIState, x, rng: np.random.Generator):
        t0 = time.perf_counter()
        xb = self.planner.full_state(x)
        U, W, b = self.planner.plan(state, xb, rng)
        u = U[0].copy()
        acted, cmin = False, float("nan")
        if self.ccfg.project_applied:
            u, acted, cmin = self.project(xb, u)
        steps = b.v.shape[0] * self.cfg.n_samples
        dt = time.perf_counter() - t0
        rec = self.sample_recorder
        samples = None if rec is None else rec.record(
            x0=xb, v=b.v, crashed=b.crashed, weights=W.w, scene=self.scene)
        info = CBFProjectionInfo(
            free_energy=W.free_energy, ess=W.ess, n_crashed=int(b.crashed.sum()),
            n_samples=self.cfg.n_samples, valid_weights=W.valid, time_s=dt,
            projected=float(b.moved.sum() / steps),
            infeasible=float(b.infeasible.sum() / steps), applied_projected=acted,
            applied_c_min=cmin, samples=samples)
        return SafeMPPIState(U=shift_plan(U, 1, self.cfg.tail)), u, info


__all__ = ["CBFProjectionConfig", "CBFProjectionInfo", "CBFProjectionMPPI"]

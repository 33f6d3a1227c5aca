"""Shield-MPPI: MPPI whose samples pay for violating the discrete CBF, plus a local repair of the
applied control.

Yin, Dawson, Fan, Tsiotras, "Shield Model Predictive Path Integral: A Computationally Efficient
Robust MPC Method Using Control Barrier Functions", IEEE RA-L 2023, arXiv:2302.11719.

1. Sampling: every step of every sample adds w_dcbf sum_i max(0, -c_i(x_k, v_k)) to its cost,
   c_i the discrete CBF constraints of :mod:`workbench.problem.dcbf` (the safe kernel,
   :mod:`workbench.sampling.kernels.safe`, with project = 0); the samples are not modified, the
   update is MPPI's.
2. Shield: the first control u of the updated plan is repaired at the measured state x0 until
   c_i(x0, u) >= 0 for every i (h(x1) >= (1 - gamma) h(x0) for margins of relative degree 1,
   the high-order psi of the margin otherwise), with at most ``repair_steps`` steps. Yin et al.
   take plain gradient steps on the violation; here the gradients are scaled by dt^2 for the
   double integrator (|dc/du| ~ 1e-3 m^2 per m/s^2), so a fixed gradient step would need a
   problem-specific step size of ~1e3-1e6. Each step is instead the normalised Gauss-Newton
   (Newton-Raphson) step on the most violated constraint i*,
   u <- clip(u - c_{i*} g_{i*} / |g_{i*}|^2), g = dc_{i*}/du: the minimum-norm point of its
   linearisation, the same closed form as the per-sample projection (exact in one step for
   convex quadratic c unless the box clips; further steps handle other constraints and the
   clip). A constraint counts as met at c_i >= -INFEASIBLE_TOL (rounding,
   :data:`~workbench.sampling.kernels.safe.INFEASIBLE_TOL`). When steps run out the last
   iterate is applied and the step reports ``shield_failed``.

Moving circles (a scene with moving slots): the sampling (1) predicts them over the horizon
(the safe kernel's rule); the shield (2) acts at the current step only and uses the present
scene, as the kernel's constraints of the first step do.

``record_samples(k)`` (:mod:`workbench.sampling.samples`) hands out the last batch's samples
(``nominal`` None; the weights include the DCBF cost).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import casadi as ca
import numpy as np

from workbench.codegen.fastcall import FastFunction
from workbench.problem.barrier import min_margin
from workbench.problem.dcbf import DEFAULT_GAMMA, check_gamma, discrete_cbf
from workbench.sampling.feedback.effect import differs
from workbench.sampling.kernels.safe import INFEASIBLE_TOL, projection_function
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
from workbench.validation import fail, integer, real

# [A] an assumed default for the navigation double integrator with the sampler's lambda = 10:
# a violated step has c ~ -(0.01 .. 0.05) m^2 (c is a second difference of the squared
# distance, scaled by dt^2 = 4e-4), and a sample that heads into an obstacle violates for tens
# of steps, so its violation sum is ~0.1-1 m^2; w_dcbf = 1e3 makes that 100-1000 cost units,
# i.e. 10-100 lambda (such samples get negligible weight) while staying far below the crash
# cost 1e6 and comparable to the state-cost spread of the batch (~1e2-1e3).
DEFAULT_W_DCBF = 1e3
# each repair step is a Gauss-Newton step on the most violated constraint; a handful fixes
# every case seen on the navigation map, so far more than this means a typo
MAX_REPAIR_STEPS = 1000


@dataclass(frozen=True)
class ShieldConfig:
    """``gamma`` in (0, 1]: the discrete CBF's class-K rate (an assumed default, see
    :data:`~workbench.problem.dcbf.DEFAULT_GAMMA`); ``w_dcbf`` >= 0: the weight of the DCBF
    violation in the sample costs (:data:`DEFAULT_W_DCBF`, assumed); ``repair_steps`` in
    [1, 1000] (:data:`MAX_REPAIR_STEPS`): at most this many repair steps on the applied
    control."""

    gamma: float = DEFAULT_GAMMA
    w_dcbf: float = DEFAULT_W_DCBF
    repair_steps: int = 10

    def __post_init__(self) -> None:
        check_gamma("ShieldConfig.gamma", self.gamma)
        real("ShieldConfig.w_dcbf", self.w_dcbf, 0.0)
        integer("ShieldConfig.repair_steps", self.repair_steps, 1, MAX_REPAIR_STEPS)


@dataclass(frozen=True, kw_only=True)
class ShieldInfo:
    """One step. ``proposed``: MPPI's first control (clipped); ``applied``: the control the
    shield sent (the repaired one); ``repair_iterations`` repair steps taken;
    ``c_min_before``/``c_min_after``: min_i c_i(x0, .) at the proposed and the applied control;
    ``dcbf_active``: share of the last batch's samples whose cost the DCBF term changed (by
    more than :data:`~workbench.sampling.feedback.effect.EFFECT_RTOL`; none when ``w_dcbf``
    is 0).

    Activity (effects, :mod:`workbench.sampling.feedback.effect`): ``shield_acted`` when the
    applied control differs from the proposal (repair steps that the box clips back move
    nothing and do not count), ``dcbf_active``; event: ``shield_failed``."""

    free_energy: float
    ess: float
    n_crashed: int
    n_samples: int
    valid_weights: bool
    time_s: float
    proposed: np.ndarray
    applied: np.ndarray
    repair_iterations: int
    c_min_before: float
    c_min_after: float
    dcbf_active: float
    samples: SampleTrajectories | None = None  # with record_samples, else None

    @property
    def shield_acted(self) -> bool:
        return bool(differs(self.applied, self.proposed))

    @property
    def shield_failed(self) -> bool:
        return bool(self.c_min_after < -INFEASIBLE_TOL)

    @property
    def stats(self) -> StepStats:
        return StepStats(n_samples=self.n_samples,
                         n_collision_free=self.n_samples - self.n_crashed, ess=self.ess,
                         activity={"shield_acted": float(self.shield_acted),
                                   "shield_failed": float(self.shield_failed),
                                   "dcbf_active": self.dcbf_active})


@dataclass(frozen=True)
class Repair:
    """Outcome of the shield's repair of one control."""

    u: np.ndarray  # the repaired control
    iterations: int
    c_min_before: float
    c_min_after: float


class ShieldMPPI(RecordsSamples, SafeMPPIController):
    """Shield-MPPI (see module docstring) on a sampling problem (physical or barrier-embedded).
    ``sampler`` is its :class:`~workbench.sampling.methods.sampler.SafeSampler`."""

    def __init__(self, sp: SamplingProblem, goal, config: MPPIConfig = MPPIConfig(),
                 shield: ShieldConfig | None = None):
        shield = ShieldConfig() if shield is None else shield
        if not isinstance(shield, ShieldConfig):
            raise fail("shield", shield, "must be a ShieldConfig")
        self.sp, self.cfg, self.scfg = sp, config, shield
        self.dcbf = discrete_cbf(sp.model)
        self.planner = SafeMPPIPlanner(
            sp, goal, config, SafeOptions(project=False, w_dcbf=shield.w_dcbf,
                                          gamma=shield.gamma))
        self.sampler = self.planner.sampler
        self._step = FastFunction(projection_function(self.dcbf))
        m = sp.model
        x, u = ca.SX.sym("x", m.nx), ca.SX.sym("u", m.nu)
        g, s = ca.SX.sym("gamma"), ca.SX.sym("scene", m.n_scene)
        self._cmin = FastFunction(ca.Function(
            "dcbf_min", [x, u, g, s], [min_margin(self.dcbf.c(x, u, g, s), range(self.dcbf.nh))]))

    def repair(self, xb, u) -> Repair:
        """The shield's repair of clip(u) at the full state xb (see module docstring)."""
        lo, hi = self.sp.model.u_min, self.sp.model.u_max
        gamma, s = self.scfg.gamma, self.scene
        u = np.clip(np.asarray(u, dtype=float), lo, hi)
        c = c0 = float(self._cmin(xb, u, gamma, s)[0][0])
        it = 0
        while it < self.scfg.repair_steps and c < -INFEASIBLE_TOL:
            u, _, cm = self._step(xb, u, gamma, s, lo, hi)
            c = float(cm[0])
            it += 1
        return Repair(u=u, iterations=it, c_min_before=c0, c_min_after=c)

    def step(self, state: SafeMPPIState, x, rng: np.random.Generator):
        t0 = time.perf_counter()
        xb = self.planner.full_state(x)
        U, W, b = self.planner.plan(state, xb, rng)
        proposed = np.clip(U[0], self.sp.model.u_min, self.sp.model.u_max)
        r = self.repair(xb, proposed)
        dt = time.perf_counter() - t0
        rec = self.sample_recorder
        samples = None if rec is None else rec.record(
            x0=xb, v=b.v, crashed=b.crashed, weights=W.w, scene=self.scene)
        info = ShieldInfo(
            free_energy=W.free_energy, ess=W.ess, n_crashed=int(b.crashed.sum()),
            n_samples=self.cfg.n_samples, valid_weights=W.valid, time_s=dt, proposed=proposed,
            applied=r.u, repair_iterations=r.iterations, c_min_before=r.c_min_before,
            c_min_after=r.c_min_after,
            dcbf_active=float(np.mean(differs(b.S, b.S - self.scfg.w_dcbf * b.dcbf,
                                              axis=()))),
            samples=samples)
        return SafeMPPIState(U=shift_plan(U, 1, self.cfg.tail)), r.u, info


__all__ = ["DEFAULT_W_DCBF", "MAX_REPAIR_STEPS", "Repair", "ShieldConfig", "ShieldInfo",
           "ShieldMPPI"]

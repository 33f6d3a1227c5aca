"""Tube-MPPI: MPPI on a nominal system plus an ancillary tracking controller.

Williams, Goldfain, Drews, Saigol, Rehg, Theodorou, "Robust Sampling Based Model Predictive
Control with Sparse Objective Information", RSS 2018; the reset rule follows ACDSLab's
MPPI-Generic (``TubeMPPIController::computeControl``).

Each step runs two MPPI batches with the compiled sampler (:meth:`Sampler.mppi`): one from the
measured state with the *actual* plan U_a, one from the nominal state x_nom with the *nominal*
plan U_n. The applied control tracks the nominal::

    u = clip(U_n[0] + K_0 (x - x_nom))

with K the ancillary tracker's gains about the nominal trajectory (by default iLQG tracking
gains, :class:`~workbench.sampling.feedback.ilqg.ILQGFeedback`, on the physical model), and the
nominal advances without noise, x_nom <- f(x_nom, clip(U_n[0])). The plans shift like MPPI's.
Moving circles (a scene with moving slots) are predicted over the horizon in both batches (the
sampler's kernels) and in the nominal's advance (the scene of x_nom's next time, dt from now).

``record_samples(k)`` (:mod:`workbench.sampling.samples`) hands out both batches of the last
iteration, the same lanes (common random numbers): ``real`` the actual batch from the measured
state, ``nominal`` the nominal batch (from the nominal state it started at, before any reset
of that iteration); ``weights`` the nominal batch's, ``weights_real`` the actual batch's.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from workbench.codegen.fastcall import FastFunction
from workbench.problem.prediction import step_scene
from workbench.sampling.feedback.base import FeedbackLaw, FeedbackWeights, Gains
from workbench.sampling.feedback.effect import differs
from workbench.sampling.feedback.ilqg import ILQGFeedback
from workbench.sampling.kernels.constants import SamplerConstants
from workbench.sampling.mppi import MPPI, MPPIConfig
from workbench.sampling.planning import full_state, physical_model, shift_plan
from workbench.sampling.problem import SamplingProblem
from workbench.sampling.samples import RecordsSamples, SampleTrajectories
from workbench.sampling.step_stats import StepStats
from workbench.sampling.weights import importance_weights, weighted_controls
from workbench.validation import as_array, fail, real


@dataclass(frozen=True)
class TubeConfig:
    """Tube-MPPI settings.

    ``threshold`` (cost units, any sign): the nominal resets to the measured state (and U_n
    to U_a) when the nominal batch's baseline (minimum sample cost) exceeds the actual batch's
    by more than this, ``rho_nom > rho_act + threshold``. MPPI-Generic writes the same rule as
    "keep the nominal iff rho_act >= rho_nom + nominal_threshold_", so its
    ``nominal_threshold_`` is ``-threshold`` here; the default -20 is its default 20: the
    nominal is kept only while it is at least 20 cheaper than the measured state. 0 resets
    only when the measured state is strictly better; larger values keep the nominal longer.
    """

    threshold: float = -20.0

    def __post_init__(self) -> None:
        real("TubeConfig.threshold", self.threshold)


@dataclass(frozen=True)
class TubeState:
    U_a: np.ndarray  # (T, nu) actual plan (MPPI from the measured state)
    U_n: np.ndarray  # (T, nu) nominal plan (MPPI from x_nom)
    x_nom: np.ndarray | None  # nominal state for the next step (full), None before the first
    gains: Gains | None = None  # last tracking gains (a failed computation shifts them)


@dataclass(frozen=True, kw_only=True)
class TubeInfo:
    """One Tube-MPPI step. ``free_energy``, ``ess``, ``n_crashed`` and ``n_samples`` describe
    the batch the applied plan comes from: the nominal batch, or the actual batch on a step
    where the nominal reset in the last iteration (then U_n = U_a). ``nominal_reset``: the
    nominal reset in some iteration of this step (an event: the tube's fall-back to the
    measured state). ``nominal_tracked``: the applied control differs from the first control
    of the actual plan (the one MPPI from the measured state applies) by more than
    :data:`~workbench.sampling.feedback.effect.EFFECT_RTOL`: the tube changed what reaches the
    plant (never on a step whose last iteration reset the nominal)."""

    free_energy: float
    ess: float
    n_crashed: int
    n_samples: int
    time_s: float
    nominal_reset: bool
    nominal_tracked: bool
    baseline_actual: float  # min sample cost of the actual batch (last iteration)
    baseline_nominal: float  # min sample cost of the nominal batch, before any reset
    free_energy_actual: float
    free_energy_nominal: float
    x_nom: np.ndarray  # the nominal state the control tracked this step (after any reset)
    feedback_fallback: str | None  # the feedback law's fallback reason, or None
    gains_activity: dict[str, float] = field(default_factory=dict)
    samples: SampleTrajectories | None = None  # with TubeMPPI.record_samples, else None

    @property
    def stats(self) -> StepStats:
        """The applied plan's batch (see the class docstring); activity (effects,
        :mod:`workbench.sampling.feedback.effect`): ``nominal_tracked``, and the tracking law's
        own activity on such a step only (else no gain reached the plant); events: the nominal
        reset this step, the tracking law fell back."""
        gate = 1.0 if self.nominal_tracked else 0.0
        act = {"nominal_tracked": gate, "nominal_reset": float(self.nominal_reset),
               "feedback_fallback": float(self.feedback_fallback is not None),
               **{k: gate * v for k, v in self.gains_activity.items()}}
        return StepStats(n_samples=self.n_samples,
                         n_collision_free=self.n_samples - self.n_crashed, ess=self.ess,
                         activity=act)


def default_tracker(sp: SamplingProblem, horizon: int) -> ILQGFeedback:
    """iLQG tracking gains on the problem's physical model, zero-padded to its full state
    (like ``NavigationSetup.feedback("ilqg")``). Weights: :class:`FeedbackWeights`'s defaults
    when they fit the model (the navigation double integrator), else uniform ones
    (:meth:`FeedbackWeights.for_model`)."""
    m = sp.model if sp.nx == sp.model.n_physical else physical_model(sp.model)
    w = FeedbackWeights()
    if len(w.Q) != m.n_physical or len(w.R) != m.nu:
        w = FeedbackWeights.for_model(m)
    return ILQGFeedback(m, horizon, sp.nx, w, name="ilqg")


class TubeMPPI(RecordsSamples):
    """Tube-MPPI on a sampling problem (physical or barrier-embedded).

    Weights: each batch gets the plain MPPI weights of its own costs, w_n proportional to
    exp(-(S_n - rho)/lambda), with S_n exactly the MPPI kernel's sample cost (state costs,
    crash cost, and the likelihood-ratio control cost
    (lambda (1 - nu_mix) / 2) sum_t u_t' Sigma^-1 (u_t + 2 eps_t) with the clipped noise
    eps_t). The ancillary feedback is *not* in the samples (unlike Robust MPPI's SAIS batch):
    the tracker only acts on the applied control.

    Each iteration draws ONE seed, ``rng.integers(0, 2**63)``, used by both batches (common
    random numbers; MPPI-Generic's original Tube-MPPI copies the actual batch's noise to the
    nominal's); after an iteration's nominal reset, the next iteration's nominal batch starts
    from the measured state. On the first step the nominal is the measured state.
    """

    def __init__(self, sp: SamplingProblem, goal, config: MPPIConfig = MPPIConfig(),
                 tube: TubeConfig = TubeConfig(), feedback: FeedbackLaw | None = None):
        if not isinstance(tube, TubeConfig):
            raise fail("tube", tube, "must be a TubeConfig")
        if config.deadline_s is not None:
            raise fail("MPPIConfig.deadline_s", config.deadline_s, "Tube-MPPI has no deadline; "
                       "leave it None (MPPI, BaS-MPPI and the robust controllers apply one)")
        self._mppi = MPPI(sp, goal, config)
        self.goal = self._mppi.goal  # read-only, as given
        self.sp, self.cfg, self.tcfg = sp, config, tube
        self.sampler = self._mppi.sampler
        self.feedback = feedback if feedback is not None else default_tracker(
            sp, config.horizon)
        self._dyn = FastFunction(sp.functions()["dyn"])
        self.set_scene(None)

    @property
    def consts(self) -> SamplerConstants:
        """The sampler constants both batches use (the MPPI settings, goal and scene)."""
        return self._mppi.consts

    @property
    def scene(self) -> np.ndarray:
        """The current scene vector."""
        return self._mppi.consts.scene

    def set_scene(self, scene) -> None:
        """Plan (both batches), advance the nominal and compute the tracking gains in ``scene``
        from the next step on (see :meth:`MPPI.set_scene`)."""
        self._mppi.set_scene(scene)
        set_fb = getattr(self.feedback, "set_scene", None)
        if set_fb is not None:
            set_fb(self.scene)

    def initial_state(self, x0=None) -> TubeState:
        Z = np.zeros((self.cfg.horizon, self.sp.nu))
        return TubeState(U_a=Z, U_n=Z.copy(), x_nom=None)

    def step(self, state: TubeState, x, rng: np.random.Generator):
        t0 = time.perf_counter()
        cfg, sp, c = self.cfg, self.sp, self.consts
        xb = full_state(sp, x, c.scene)
        for name, U in (("state.U_a", state.U_a), ("state.U_n", state.U_n)):
            if (not isinstance(U, np.ndarray) or U.shape != (cfg.horizon, sp.nu)
                    or not np.all(np.isfinite(U))):
                raise fail(name, getattr(U, "shape", U),
                           f"the plan must be a finite ({cfg.horizon}, {sp.nu}) array")
        U_a, U_n = state.U_a, state.U_n
        x_nom = xb if state.x_nom is None else as_array("state.x_nom", state.x_nom, (sp.nx,))
        reset = last = False  # a reset in any iteration / in the last one
        for _ in range(cfg.iterations):
            x_start = x_nom  # the nominal batch's start (before this iteration's reset)
            seed = int(rng.integers(0, 2**63))
            ba = self.sampler.mppi(xb, U_a, cfg.n_samples, c, seed)
            bn = self.sampler.mppi(x_nom, U_n, cfg.n_samples, c, seed)
            Wa = importance_weights(ba.S, cfg.lam)
            Wn = importance_weights(bn.S, cfg.lam)
            if Wa.valid:
                U_a = cfg.smooth(weighted_controls(ba.v, Wa.w))
            if Wn.valid:
                U_n = cfg.smooth(weighted_controls(bn.v, Wn.w))
            last = bool(Wn.rho > Wa.rho + self.tcfg.threshold)
            if last:
                x_nom, U_n = xb, U_a
            reset = reset or last
        gains = self.feedback.gains(x_nom, U_n, state.gains, 0 if state.gains is None else 1)
        lo, hi = sp.model.u_min, sp.model.u_max
        u = np.clip(U_n[0] + gains.K[0] @ (xb - x_nom), lo, hi)
        x_next = self._dyn(x_nom, np.clip(U_n[0], lo, hi), step_scene(sp.model, c.scene))[0]
        b, W = (ba, Wa) if last else (bn, Wn)
        dt = time.perf_counter() - t0
        rec = self.sample_recorder
        samples = None if rec is None else rec.record(
            x0=xb, v=ba.v, crashed=ba.crashed, weights=Wn.w, scene=c.scene, x0_nominal=x_start,
            v_nominal=bn.v, crashed_nominal=bn.crashed, weights_real=Wa.w)
        info = TubeInfo(
            free_energy=W.free_energy, ess=W.ess, n_crashed=int(b.crashed.sum()),
            n_samples=cfg.n_samples, time_s=dt, nominal_reset=reset,
            nominal_tracked=bool(differs(u, np.clip(U_a[0], lo, hi))),
            baseline_actual=Wa.rho, baseline_nominal=Wn.rho, free_energy_actual=Wa.free_energy,
            free_energy_nominal=Wn.free_energy, x_nom=x_nom, feedback_fallback=gains.fallback,
            gains_activity=dict(gains.activity), samples=samples)
        new = TubeState(U_a=shift_plan(U_a, 1, cfg.tail), U_n=shift_plan(U_n, 1, cfg.tail),
                        x_nom=x_next, gains=gains)
        return new, u, info


__all__ = ["TubeConfig", "TubeInfo", "TubeMPPI", "TubeState", "default_tracker"]

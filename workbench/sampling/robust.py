"""Robust MPPI with explicit state: ``state, u, info = ctrl.step(state, x, rng)``.

:class:`RobustMPPI` runs the SAIS sampler of Algorithm 1 with a feedback law
(:mod:`workbench.sampling.feedback`): K_safe from BaS-iLQG gives SA-RMPPI (assumptions §10.3),
plain iLQG tracking gains give RMPPI (assumptions §9.4). The selection threshold alpha comes from
:mod:`workbench.sampling.threshold`; the sampling settings are MPPI's
(:class:`~workbench.sampling.mppi.MPPIConfig`).

The controller holds only immutable configuration and external workspaces (compiled kernels,
iLQG passes); everything that changes between steps lives in the returned state.
``ctrl.record_samples(k)`` hands out the last SAIS batch's samples, real and nominal.

Moving circles (a scene with moving slots): the SAIS and candidate rollouts and the feedback
law predict them over the horizon; the candidate starts are states of the present time (the
old nominal propagated by one step reaches now), so their propagation and lifts use the present
scene.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Literal

import numpy as np

from workbench.codegen.fastcall import FastFunction
from workbench.sampling.deadline import (
    DeadlineHistory,
    DeadlineReport,
    JoinBuffers,
    StepClock,
    deadline_step,
    kernel_threads,
    new_arrays,
    sample_within,
)
from workbench.sampling.feedback.base import FeedbackLaw, Gains
from workbench.sampling.feedback.effect import differs
from workbench.sampling.feedback.ilqg import ILQGFeedback
from workbench.sampling.kernels.constants import SamplerConstants
from workbench.sampling.mppi import MPPI, MPPIConfig, savgol_matrix
from workbench.sampling.planning import check_plan, full_state, shift_plan
from workbench.sampling.problem import SamplingProblem
from workbench.sampling.robust_step import CandidateStarts, candidate_free_energies
from workbench.sampling.sampler import SAISBatch
from workbench.sampling.samples import RecordsSamples, SampleTrajectories
from workbench.sampling.step_stats import StepStats
from workbench.sampling.threshold import ConstantThreshold, Threshold
from workbench.sampling.weights import free_energy, importance_weights, weighted_controls
from workbench.validation import MAX_BATCH, at_most, fail, flag, integer, one_of, real_or_inf

MAX_CANDIDATES = 1001  # RMPPI candidate nominal states
MAX_CANDIDATE_ROLLOUTS = 2**24  # RMPPI candidate rollouts per step


@dataclass(frozen=True)
class RMPPIConfig:
    """Robust MPPI settings (assumptions §9, §10; defaults [A] from assumptions §15).

    ``alpha`` is a fixed selection threshold, used when no calibrated
    :class:`~workbench.sampling.threshold.Threshold` is given to :class:`RobustMPPI` (the
    navigation set-up calibrates one by default, see ``NavigationSetup.controller``). The
    default +inf never binds, so :class:`RobustMPPI` refuses it unless a threshold is given
    (``wb.calibrate(...)``, or ``ConstantThreshold.selection_off()`` to opt out explicitly).
    Bounds: ``n_candidates <= 1001``, ``n_candidates * candidate_samples <= 2**24``; with the
    MPPI settings, ``n_candidates * candidate_samples * horizon * nu <= 2**31`` (checked by
    :class:`RobustMPPI`).
    """

    alpha: float = np.inf
    n_candidates: int = 9
    candidate_samples: int = 64
    fallback: Literal["propagated", "keep_previous"] = "propagated"
    applied: Literal["nominal_feedback", "real"] = "nominal_feedback"
    clip_in_cost: bool = True  # assumptions §10.1: clipped noise/feedback in the SAIS costs
    # assumptions §11.2: hand out the first SAIS batch of each step with trajectories and pure state
    # costs (RMPPIInfo.batch, a SAISDiagBatch); same costs and controls, so the same behaviour
    diagnostics: bool = False

    def __post_init__(self) -> None:
        real_or_inf("RMPPIConfig.alpha", self.alpha)
        integer("RMPPIConfig.n_candidates", self.n_candidates, 3, MAX_CANDIDATES)
        integer("RMPPIConfig.candidate_samples", self.candidate_samples, 1,
                MAX_CANDIDATE_ROLLOUTS)
        at_most("RMPPIConfig.candidate_samples", self.candidate_samples,
                self.n_candidates * self.candidate_samples, MAX_CANDIDATE_ROLLOUTS,
                "n_candidates * candidate_samples (candidate rollouts per step)")
        if self.n_candidates % 2 == 0:
            raise fail("RMPPIConfig.n_candidates", self.n_candidates, "must be odd and >= 3")
        one_of("RMPPIConfig.fallback", self.fallback, ("propagated", "keep_previous"))
        one_of("RMPPIConfig.applied", self.applied, ("nominal_feedback", "real"))
        flag("RMPPIConfig.clip_in_cost", self.clip_in_cost)
        flag("RMPPIConfig.diagnostics", self.diagnostics)


@dataclass(frozen=True)
class RMPPIState:
    U: np.ndarray  # (T, nu) nominal control sequence u*
    x_nom: np.ndarray | None  # nominal state x*_0 (full), None before the first call
    index: int  # previously chosen candidate
    gains: Gains | None = None  # last feedback gains (shifted when a computation fails)


@dataclass(frozen=True, kw_only=True)
class Selection:
    """Outcome of the nominal-state selection (assumptions §9.3)."""

    x_nom: np.ndarray  # chosen nominal state x*_0 (full)
    U: np.ndarray  # nominal controls slid by the chosen stride
    index: int  # chosen candidate (n_candidates - 1 is the real state)
    stride: int
    free_energy: np.ndarray  # (n_candidates,) candidate free energies (empty on the first call)
    alpha: np.ndarray  # (n_candidates,) thresholds at the candidates
    fallback: bool  # no candidate was admissible
    alpha_nominal: float  # threshold at the chosen nominal state (the SAIS clamp's alpha)


@dataclass(frozen=True, kw_only=True)
class RMPPIInfo:
    candidate: int
    candidate_free_energy: np.ndarray
    candidate_alpha: np.ndarray
    fallback_used: bool  # alpha fallback: no candidate admissible
    # x*_0 differs from the measured state after selection (effect.differs)
    nominal_differs: bool
    alpha: float  # threshold used in the SAIS clamp (at the chosen nominal state)
    # some threshold of this step is finite: the selection could bind. False with the explicit
    # opt-out (alpha = +inf everywhere): the real state is taken and the robust part is inert
    alpha_finite: bool
    free_energy_nom: float
    free_energy_real: float
    ess_nom: float
    ess_real: float
    n_crashed_real: int
    n_crashed_nom: int
    ksafe_fallback: str | None  # feedback fallback reason (feedback.FALLBACK_REASONS) or None
    nominal_unsafe: bool  # the nominal rollout used for the gains left the safe set
    timing: dict[str, float] = field(default_factory=dict)
    x_nom: np.ndarray | None = None
    batch: SAISBatch | None = None  # first SAIS batch with diagnostics (RMPPIConfig.diagnostics)
    n_samples: int = 0  # samples of the last SAIS batch
    gains_activity: dict[str, float] = field(default_factory=dict)  # Gains.activity
    # the last SAIS batch's samples, real and nominal (RobustMPPI.record_samples), else None
    samples: SampleTrajectories | None = None
    deadline: DeadlineReport | None = None  # with MPPIConfig.deadline_s, else None

    @property
    def feedback_ok(self) -> bool:
        return self.ksafe_fallback is None

    @property
    def stats(self) -> StepStats:
        """The real samples (with feedback: the system the plan is for) of the last SAIS
        batch, and the ESS of the nominal weights (the ones that make the update). Activity
        (effects, :mod:`workbench.sampling.feedback.effect`): the nominal state differs from
        the measured one, and the feedback law's own mechanism activity
        (:attr:`Gains.activity`) on such a step only: with x*_0 = x every sample's real and
        nominal rollouts coincide and the applied control's K_0 (x - x*_0) is 0, so no gain
        reaches the plant and the law's activity is 0. Events: the feedback law fell back,
        the selection found no admissible candidate."""
        gate = 1.0 if self.nominal_differs else 0.0
        act = {"nominal_differs": gate,
               "feedback_fallback": float(self.ksafe_fallback is not None),
               "selection_fallback": float(self.fallback_used),
               **{k: gate * v for k, v in self.gains_activity.items()}}
        return StepStats(n_samples=self.n_samples,
                         n_collision_free=self.n_samples - self.n_crashed_real,
                         ess=self.ess_nom, activity=act)


def join_sais(parts: list[SAISBatch], cat: Callable[..., np.ndarray] = new_arrays) -> SAISBatch:
    """One SAIS batch of the samples of several (the chunks of a step with a deadline): new
    arrays, or views of a controller's buffers (``cat=JoinBuffers.cat``)."""
    per_sample = {f: cat(f, [getattr(b, f) for b in parts])
                  for f in ("S_nom", "S_real", "S_state_nom", "S_hat", "LR", "crashed_real",
                            "crashed_nom")}
    return SAISBatch(**per_sample, v_nom=cat("v_nom", [b.v_nom for b in parts], -1),
                     v_real=cat("v_real", [b.v_real for b in parts], -1))


def strides(n_candidates: int, s: int = 1) -> np.ndarray:
    """Candidate strides round(W_i1 s + W_i2 s), rounding half away from zero (assumptions §9.3)."""
    hc = n_candidates // 2
    w = np.array([i / hc for i in range(hc + 1)] + [1.0] * hc) * s
    return np.floor(w + 0.5).astype(int)


def candidate_weights(n_candidates: int) -> np.ndarray:
    """(n_candidates, 3) weights on (old nominal, propagated nominal, real) (assumptions §9.3)."""
    hc = n_candidates // 2
    W = [(1 - i / hc, i / hc, 0.0) for i in range(hc + 1)]
    W += [(0.0, 1 - i / hc, i / hc) for i in range(1, hc + 1)]
    return np.array(W)


class RobustMPPI(RecordsSamples):
    """Robust MPPI with the SAIS sampler: SA-RMPPI with K_safe (the default feedback, BaS-iLQG
    gains on the embedded model), RMPPI with plain iLQG gains, or any :class:`FeedbackLaw`.
    :meth:`record_samples` hands out the last SAIS batch's samples: ``real`` from the measured
    state with feedback, ``nominal`` from x*_0 without; ``weights`` the nominal weights (the
    update of u*), ``weights_real`` the real ones.

    ``fast`` (default): the gains come from the law's compiled fast path when it has one
    (``fast_gains``, e.g. :meth:`ILQGFeedback.fast_gains`: K_safe in one call) and the step's
    arithmetic around the sampler batches runs vectorised
    (:mod:`workbench.sampling.robust_step`): candidate starts compiled, all candidate free
    energies in one pass, the real system's weighted controls only when they are applied.
    ``fast=False`` runs :meth:`step_twin`, the step-by-step twin (``feedback.gains``);
    both return the same numbers, bit for bit."""

    def __init__(self, sp: SamplingProblem, goal, config: MPPIConfig = MPPIConfig(),
                 robust: RMPPIConfig = RMPPIConfig(), feedback: FeedbackLaw | None = None,
                 threshold: Threshold | None = None, fast: bool = True):
        if sp.nx == sp.model.n_physical:
            raise fail("sp.model", sp.model.name, "RMPPI here runs on a barrier-embedded model")
        if config.deadline_s is not None and (robust.diagnostics or not fast):
            raise fail("MPPIConfig.deadline_s", config.deadline_s, "a deadline runs on the "
                       "fast step without diagnostics; leave it None with "
                       "RMPPIConfig.diagnostics or fast=False")
        at_most("RMPPIConfig.candidate_samples", robust.candidate_samples,
                robust.n_candidates * robust.candidate_samples * config.horizon * sp.nu,
                MAX_BATCH, "n_candidates * candidate_samples * horizon * nu (entries of the "
                "candidate batch)")
        self.mppi = MPPI(sp, goal, config)
        self.goal = self.mppi.goal  # read-only, as given
        self.sp, self.cfg, self.rcfg = sp, config, robust
        self.sampler = self.mppi.sampler
        self._deadline_history = DeadlineHistory()  # recent chunk and tail times
        self._joined = JoinBuffers(config.n_samples)  # where a deadline step joins its chunks
        self.consts = replace(self.mppi.consts, alpha=robust.alpha,
                              clip_in_cost=bool(robust.clip_in_cost))
        self.feedback = feedback or ILQGFeedback(sp.model, config.horizon, sp.nx)
        if threshold is None:
            if not np.isfinite(robust.alpha):
                raise fail("threshold", None, "RobustMPPI needs a selection threshold that can "
                           f"bind; RMPPIConfig.alpha = {robust.alpha} never does (the real "
                           "state would always be taken and the robust part would never act). "
                           "Calibrate one with wb.calibrate(rule, problem, goal, plant, x0, "
                           "mppi, feedback, robust) (or nav.threshold(...)), give a finite "
                           "RMPPIConfig(alpha=...), or pass threshold=ConstantThreshold("
                           "float('inf')) (ConstantThreshold.selection_off()) to switch the "
                           "selection off on purpose")
            threshold = ConstantThreshold(value=robust.alpha)
        self.threshold = threshold
        self._dyn = FastFunction(sp.functions()["dyn"])
        self._lift_all = FastFunction(sp.model.lift_function, robust.n_candidates, shared=(1,))
        self._W = candidate_weights(robust.n_candidates)
        self._strides = strides(robust.n_candidates)
        self.fast = flag("RobustMPPI.fast", fast)
        self._consts_cache: tuple | None = None
        self._starts = CandidateStarts(sp, self._W)
        # the candidate batch's per-sample strides, fixed for the controller
        self._stride_rep = np.repeat(self._strides.astype(float), robust.candidate_samples)
        self._stride_rep.setflags(write=False)
        self._smooth = (None if config.smoothing is None
                        else savgol_matrix(config.horizon, *config.smoothing))
        if self.fast and hasattr(self.feedback, "fast_gains"):
            getattr(self.feedback, "compiled", None)  # build the law's compiled fast path now
        self.set_scene(None)

    @property
    def scene(self) -> np.ndarray:
        """The current scene vector."""
        return self.consts.scene

    def set_scene(self, scene) -> None:
        """Plan, select and compute the feedback gains in ``scene`` from the next step on (see
        :meth:`MPPI.set_scene`); no recompilation."""
        self.mppi.set_scene(scene)
        self.consts = replace(self.consts, scene=self.mppi.consts.scene, p=self.mppi.consts.p)
        set_fb = getattr(self.feedback, "set_scene", None)
        if set_fb is not None:
            set_fb(self.consts.scene)

    def initial_state(self, x0=None) -> RMPPIState:
        return RMPPIState(U=np.zeros((self.cfg.horizon, self.sp.nu)), x_nom=None, index=0)

    def select_nominal(self, state: RMPPIState, xb, rng) -> Selection:
        """Nominal-state selection (assumptions §9.3) with s = 1 plant step since the last call
        (:meth:`select_nominal_twin` with ``fast=False``)."""
        if not self.fast:
            return self.select_nominal_twin(state, xb, rng)
        nc = self.rcfg.n_candidates
        if state.x_nom is None:
            return self._first_selection(state, xb)
        r, cfg, n = self.rcfg, self.cfg, self.sp.model.n_physical
        starts = self._starts(state.x_nom, state.U[0], xb, self.consts.scene)
        alpha = self.threshold(starts[:, :n])  # before the batch: its caches are still warm
        S = self.sampler.candidates(np.repeat(starts, r.candidate_samples, axis=0), state.U,
                                    self._stride_rep, self.consts,
                                    int(rng.integers(0, 2**63)))
        return self._choose(state, starts, candidate_free_energies(S, nc, cfg.lam), alpha)

    def _first_selection(self, state: RMPPIState, xb) -> Selection:
        n = self.sp.model.n_physical
        return Selection(x_nom=xb, U=state.U, index=self.rcfg.n_candidates - 1, stride=0,
                         free_energy=np.zeros(0), alpha=np.zeros(0), fallback=False,
                         alpha_nominal=float(self.threshold(xb[None, :n])[0]))

    def _choose(self, state: RMPPIState, starts, F, alpha) -> Selection:
        nc, r = self.rcfg.n_candidates, self.rcfg
        ok = np.flatnonzero(F < alpha)
        fallback = ok.size == 0
        if fallback:
            i_star = nc // 2 if r.fallback == "propagated" else state.index
        else:
            i_star = int(ok.max())
        s = int(self._strides[i_star])
        return Selection(x_nom=starts[i_star], U=shift_plan(state.U, s, self.cfg.tail),
                         index=i_star, stride=s, free_energy=F, alpha=alpha,
                         fallback=fallback, alpha_nominal=float(alpha[i_star]))

    def select_nominal_twin(self, state: RMPPIState, xb, rng) -> Selection:
        """:meth:`select_nominal` step by step (its twin: per-candidate free energies in a
        Python loop, the mixture, lift and propagation as separate calls)."""
        nc = self.rcfg.n_candidates
        if state.x_nom is None:
            return self._first_selection(state, xb)
        r, cfg, sp = self.rcfg, self.cfg, self.sp
        a0 = state.x_nom
        a1 = self._dyn(a0, state.U[0], self.consts.scene)[0]
        n = sp.model.n_physical
        mixed = self._W @ np.stack([a0, a1, xb])
        # beta of an interpolated state is recomputed from its position (assumptions §4.4)
        starts = self._lift_all(mixed[:, :n], self.consts.scene)[0].reshape(nc, sp.nx)
        starts[-1] = xb  # the real candidate is the measured state itself
        M = r.candidate_samples
        # controls u*_{min(t+s, T-1)}, no noise before the stride (MPPI-G)
        S = self.sampler.candidates(np.repeat(starts, M, axis=0), state.U,
                                    np.repeat(self._strides.astype(float), M), self.consts,
                                    int(rng.integers(0, 2**63)))
        # per-candidate free energy; the shift (assumptions §9.3: min over all samples) cancels
        # exactly,
        # a per-candidate shift only avoids underflow
        F = np.array([free_energy(S_i, cfg.lam) for S_i in S.reshape(nc, M)])
        return self._choose(state, starts, F, self.threshold(starts[:, :n]))

    @deadline_step
    def step(self, state: RMPPIState, x, rng: np.random.Generator):
        """One control step: selection, gains, SAIS batch(es), update (``fast``: the
        vectorised step, else :meth:`step_twin`)."""
        if not self.fast:
            return self.step_twin(state, x, rng)
        t0 = time.perf_counter()
        sp, cfg = self.sp, self.cfg
        xb = full_state(sp, x, self.consts.scene)
        check_plan(state.U, cfg.horizon, sp.nu)
        sel = self.select_nominal(state, xb, rng)
        x_nom, U = sel.x_nom, sel.U
        t1 = time.perf_counter()
        fb = self.feedback
        # a law's compiled fast path of gains(...) when it has one (ILQGFeedback.fast_gains)
        gains = getattr(fb, "fast_gains", fb.gains)(x_nom, U, state.gains, sel.stride)
        K = gains.K
        t2 = time.perf_counter()
        alpha = sel.alpha_nominal
        consts = self._consts_at(alpha)
        real = self.rcfg.applied == "real"  # the real system's controls are applied
        U_real = U
        first = None
        lam, M = cfg.lam, self._smooth
        clock = (None if cfg.deadline_s is None
                 else StepClock(cfg.deadline_s, t0, self._deadline_history,
                                 kernel_threads(cfg.horizon)))
        for it in range(cfg.iterations):
            diag = self.rcfg.diagnostics and it == 0
            if clock is None:
                b = self.sampler.sais(xb, x_nom, U, K, cfg.n_samples, consts,
                                      int(rng.integers(0, 2**63)), diagnostics=diag)
            else:
                def draw(n: int, seed: int, U: np.ndarray = U) -> SAISBatch:
                    return self.sampler.sais(xb, x_nom, U, K, n, consts, seed)

                got = sample_within(clock, cfg.n_samples, cfg.chunks, draw, rng,
                                    partial(join_sais, cat=self._joined.cat))
                if got is None:
                    break
                b = got
            first = b if diag else first
            t3 = time.perf_counter()
            Wn = importance_weights(b.S_nom, lam)
            Wr = importance_weights(b.S_real, lam)
            if Wn.valid:
                U = weighted_controls(b.v_nom, Wn.w)
                U = U if M is None else M @ U
            if real and Wr.valid:
                U_real = weighted_controls(b.v_real, Wr.w)
        if self.rcfg.applied == "nominal_feedback":
            m = sp.model
            u = np.clip(U[0] + K[0] @ (xb - x_nom), m.u_min, m.u_max)
        else:
            u = U_real[0].copy()
        t4 = time.perf_counter()
        return self._finish(state, sel, gains, b, Wn, Wr, U, u, xb, consts, first,
                            (t0, t1, t2, t3, t4), clock)

    def _consts_at(self, alpha: float) -> SamplerConstants:
        """The controller's constants with the SAIS threshold ``alpha`` (kept while the
        threshold and the constants stay the same)."""
        cached = self._consts_cache
        if cached is not None and cached[0] is self.consts and cached[1] == alpha:
            return cached[2]
        c = replace(self.consts, alpha=alpha)
        self._consts_cache = (self.consts, alpha, c)
        return c

    def _finish(self, state, sel, gains, b, Wn, Wr, U, u, xb, consts, first, t, clock=None):
        t0, t1, t2, t3, t4 = t
        x_nom, alpha = sel.x_nom, sel.alpha_nominal
        timing = {"selection": t1 - t0, "k_safe": t2 - t1, "sais": t3 - t2, "update": t4 - t3,
                  "total": t4 - t0}
        rec = self.sample_recorder
        samples = None if rec is None else rec.record(
            x0=xb, v=b.v_real, crashed=b.crashed_real, weights=Wn.w, scene=consts.scene,
            x0_nominal=x_nom, v_nominal=b.v_nom, crashed_nominal=b.crashed_nom,
            weights_real=Wr.w)
        info = RMPPIInfo(
            candidate=sel.index, candidate_free_energy=sel.free_energy,
            candidate_alpha=sel.alpha, fallback_used=sel.fallback,
            nominal_differs=bool(differs(x_nom, xb)), alpha=alpha,
            alpha_finite=math.isfinite(alpha) or bool(np.isfinite(sel.alpha).any()),
            free_energy_nom=Wn.free_energy, free_energy_real=Wr.free_energy, ess_nom=Wn.ess,
            ess_real=Wr.ess, n_crashed_real=int(np.count_nonzero(b.crashed_real)),
            n_crashed_nom=int(np.count_nonzero(b.crashed_nom)), ksafe_fallback=gains.fallback,
            nominal_unsafe=gains.nominal_unsafe, timing=timing, x_nom=x_nom, batch=first,
            n_samples=int(b.S_nom.size), gains_activity=dict(gains.activity),
            samples=samples, deadline=None if clock is None else clock.report(self.cfg.n_samples))
        return RMPPIState(U=U, x_nom=x_nom, index=sel.index, gains=gains), u, info

    def step_twin(self, state: RMPPIState, x, rng: np.random.Generator):
        """:meth:`step` step by step (its twin; ``fast=False``)."""
        t0 = time.perf_counter()
        xb = full_state(self.sp, x, self.consts.scene)
        check_plan(state.U, self.cfg.horizon, self.sp.nu)
        sel = self.select_nominal_twin(state, xb, rng)
        x_nom, U = sel.x_nom, sel.U
        t1 = time.perf_counter()
        gains = self.feedback.gains(x_nom, U, state.gains, sel.stride)
        K = gains.K
        t2 = time.perf_counter()
        alpha = sel.alpha_nominal
        consts = replace(self.consts, alpha=alpha)
        U_real = U
        first = None
        for it in range(self.cfg.iterations):
            b = self.sampler.sais(xb, x_nom, U, K, self.cfg.n_samples, consts,
                                  int(rng.integers(0, 2**63)),
                                  diagnostics=self.rcfg.diagnostics and it == 0)
            first = b if it == 0 and self.rcfg.diagnostics else first
            t3 = time.perf_counter()
            Wn = importance_weights(b.S_nom, self.cfg.lam)
            Wr = importance_weights(b.S_real, self.cfg.lam)
            U_new = self.cfg.smooth(weighted_controls(b.v_nom, Wn.w)) if Wn.valid else U
            U_real = weighted_controls(b.v_real, Wr.w) if Wr.valid else U_real
            U = U_new
        if self.rcfg.applied == "nominal_feedback":
            u = np.clip(U[0] + K[0] @ (xb - x_nom), self.sp.model.u_min, self.sp.model.u_max)
        else:
            u = U_real[0].copy()
        t4 = time.perf_counter()
        return self._finish(state, sel, gains, b, Wn, Wr, U, u, xb, consts, first,
                            (t0, t1, t2, t3, t4))



"""MPPI with explicit state: ``state, u, info = ctrl.step(state, x, rng)`` (assumptions §8.1);
BaS-MPPI is MPPI on a barrier-embedded problem (assumptions §8.2).

The controller holds only immutable configuration and external workspaces (compiled kernels);
everything that changes between steps lives in the returned state.

Seeing the samples: ``ctrl.record_samples(k)`` makes every later step's info carry
``info.samples``, k of the last batch's sample trajectories with their weights and crash flags
(:class:`~workbench.sampling.samples.SampleTrajectories`; ``nominal`` is None). Off by default
(``info.samples`` is None, no extra work); the same call exists on
:class:`~workbench.sampling.robust.RobustMPPI` and every method of
:mod:`workbench.sampling.methods`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache, partial
from typing import Literal

import numpy as np
from scipy.signal import savgol_filter

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
from workbench.sampling.kernels.constants import FLOAT32_MAX, check_scales32
from workbench.sampling.planning import (
    PlansToGoal,
    check_plan,
    full_state,
    shift_plan,
)
from workbench.sampling.problem import SamplingProblem
from workbench.sampling.sampler import Backend, MPPIBatch, Precision, Sampler
from workbench.sampling.samples import RecordsSamples, SampleTrajectories
from workbench.sampling.step_stats import StepStats
from workbench.sampling.weights import importance_weights, weighted_controls
from workbench.validation import (
    MAX_BATCH,
    at_most,
    fail,
    integer,
    one_of,
    real,
    scale,
)

MAX_ITERATIONS = 1000  # MPPI iterations per step


@cache
def savgol_matrix(T: int, window: int, order: int) -> np.ndarray:
    """scipy's Savitzky-Golay filter along time (mode "interp": polynomial fits at both ends) as
    the (T, T) matrix it applies: the filter is linear, so U_smooth = M @ U equals
    ``savgol_filter(U, window, order, axis=0)`` to rounding, ~100x faster than calling scipy,
    which refits the polynomial coefficients on every call (0.3 ms at T = 100)."""
    M = savgol_filter(np.eye(T), window, order, axis=0)
    M.setflags(write=False)
    return M


@dataclass(frozen=True)
class MPPIConfig:
    """Sampling settings (assumptions §8.2, 15 defaults [A]).

    Bounds checked here: every ``sigma`` in [1.5e-154, 6.7e153] and ``lam`` in
    [2.2e-308, 4.5e307] (their squares, resp. values, and reciprocals are normal float64
    numbers); ``n_samples * horizon * len(sigma) <= 2**31``; ``iterations <= 1000``.

    ``deadline_s`` (None or a time > 0 in seconds) bounds each step's time, ``deadline_chunks``
    (1 .. n_samples, only with a deadline; default min(16, n_samples)) sets the granularity of
    the cut (:mod:`workbench.sampling.deadline`):
    results with a deadline depend on timing and are not reproducible bit for bit. MPPI,
    BaS-MPPI and the robust controllers apply it; the controllers with their own sampling
    loops (Tube-MPPI, Shield-MPPI, CBF projection) refuse it."""

    n_samples: int = 1024
    horizon: int = 100
    lam: float = 1.0
    sigma: tuple[float, ...] = (2.0, 2.0)  # per-axis std; Sigma = diag(sigma^2)
    nu_mix: float = 0.0
    iterations: int = 1
    crash_cost: float = 1e6
    tail: Literal["hold", "zero"] = "hold"
    # Savitzky-Golay (window, order), assumptions §8.1 [A] (9, 2)
    smoothing: tuple[int, int] | None = None
    backend: Backend = "auto"
    # sampler kernels: "float32" = twice the SIMD lanes; samples near the crash margin and
    # batches without a crash-free sample are recomputed in float64 (workbench.sampling.sampler)
    precision: Precision = "float64"
    # a step returns within deadline_s seconds (plus about one chunk of samples), drawing its
    # samples in deadline_chunks chunks and stopping when the next would not fit
    # (workbench.sampling.deadline); None: no deadline, results exactly reproducible
    deadline_s: float | None = None
    deadline_chunks: int | None = None

    def __post_init__(self) -> None:
        for name in ("n_samples", "horizon"):  # the kernels take them as a C int
            integer(f"MPPIConfig.{name}", getattr(self, name), 1, MAX_BATCH - 1)
        integer("MPPIConfig.iterations", self.iterations, 1, MAX_ITERATIONS)
        scale("MPPIConfig.lam", self.lam)  # the weights divide by lambda
        if isinstance(self.sigma, str) or not hasattr(self.sigma, "__len__") or any(
                isinstance(v, bool | np.bool_) for v in self.sigma):
            raise fail("MPPIConfig.sigma", self.sigma, "must be a list of standard deviations, "
                       "one per control, each in [1.492e-154, 6.704e+153]")
        s = np.asarray(self.sigma, dtype=float)
        if s.ndim != 1 or s.size == 0 or not np.all(np.isfinite(s)) or np.any(s <= 0):
            raise fail("MPPIConfig.sigma", s, "Sigma = diag(sigma^2) must be positive definite: "
                       "every sigma must be finite and > 0")
        for i, v in enumerate(s):  # sigma^2 and 1/sigma^2 enter the sampler and the costs
            scale(f"MPPIConfig.sigma[{i}]", float(v), power=2)
        object.__setattr__(self, "sigma", tuple(float(v) for v in s))
        at_most("MPPIConfig.n_samples", self.n_samples, self.n_samples * self.horizon * s.size,
                MAX_BATCH, "n_samples * horizon * nu (entries of a sampled batch)")
        if not 0.0 <= real("MPPIConfig.nu_mix", self.nu_mix) < 1.0:
            raise fail("MPPIConfig.nu_mix", self.nu_mix, "must lie in [0, 1)")
        real("MPPIConfig.crash_cost", self.crash_cost, 0.0)
        one_of("MPPIConfig.tail", self.tail, ("hold", "zero"))
        if self.smoothing is not None:
            ok = isinstance(self.smoothing, tuple | list) and len(self.smoothing) == 2
            if ok:
                w, o = (integer("MPPIConfig.smoothing", v) for v in self.smoothing)
                ok = w % 2 == 1 and 0 <= o < w <= self.horizon
            if not ok:
                raise fail("MPPIConfig.smoothing", self.smoothing,
                           "need (window, order) with an odd window <= horizon and order < window")
        one_of("MPPIConfig.precision", self.precision, ("float64", "float32"))
        if self.deadline_s is not None:
            real("MPPIConfig.deadline_s", self.deadline_s, 0.0, strict=True)
        if self.deadline_chunks is not None:
            if self.deadline_s is None:
                raise fail("MPPIConfig.deadline_chunks", self.deadline_chunks,
                           "is only used with a deadline: set deadline_s too, or leave it unset")
            integer("MPPIConfig.deadline_chunks", self.deadline_chunks, 1, self.n_samples)
        if self.precision == "float32":  # the kernels' own float32 rules, checked at once
            check_scales32("MPPIConfig", self.sigma, self.lam, self.nu_mix)
            if self.crash_cost > FLOAT32_MAX:
                raise fail("MPPIConfig.crash_cost", self.crash_cost,
                           f"must be at most {FLOAT32_MAX:.4g} for precision 'float32'")

    @property
    def chunks(self) -> int:
        """The number of chunks a step with a deadline draws its samples in."""
        return self.deadline_chunks or min(16, self.n_samples)

    def smooth(self, U: np.ndarray) -> np.ndarray:
        """Savitzky-Golay smoothing of a control sequence along time (or U unchanged): one
        product with the filter's (T, T) matrix (:func:`savgol_matrix`)."""
        if self.smoothing is None:
            return U
        return savgol_matrix(U.shape[0], *self.smoothing) @ U

    @classmethod
    def with_covariance(cls, Sigma, **kw) -> MPPIConfig:
        """Build from a covariance matrix; it must be positive definite (and diagonal)."""
        S = np.asarray(Sigma, dtype=float)
        if S.ndim != 2 or S.shape[0] != S.shape[1] or not np.allclose(S, S.T):
            raise fail("Sigma", S, "must be a symmetric square matrix")
        if not np.all(np.isfinite(S)) or np.min(np.linalg.eigvalsh(S)) <= 0:
            raise fail("Sigma", S, "must be positive definite")
        if np.any(S[~np.eye(S.shape[0], dtype=bool)] != 0):
            raise fail("Sigma", S, "only diagonal covariances are supported by the kernels")
        return cls(sigma=tuple(np.sqrt(np.diag(S))), **kw)


def join_mppi(parts: list[MPPIBatch], cat: Callable[..., np.ndarray] = new_arrays) -> MPPIBatch:
    """One batch of the samples of several (the chunks of a step with a deadline): new
    arrays, or views of a controller's buffers (``cat=JoinBuffers.cat``)."""
    return MPPIBatch(S=cat("S", [b.S for b in parts]),
                     crashed=cat("crashed", [b.crashed for b in parts]),
                     v=cat("v", [b.v for b in parts], -1))


@dataclass(frozen=True)
class MPPIState:
    U: np.ndarray  # (T, nu) importance-sampling sequence


@dataclass(frozen=True, kw_only=True)
class MPPIInfo:
    free_energy: float
    ess: float
    n_crashed: int
    valid_weights: bool
    time_s: float
    n_samples: int = 0  # samples of the last batch (the one the update was weighted over)
    samples: SampleTrajectories | None = None  # with MPPI.record_samples, else None
    deadline: DeadlineReport | None = None  # with MPPIConfig.deadline_s, else None

    @property
    def stats(self) -> StepStats:
        """The last batch's samples: crash-free count and ESS (no safety mechanism)."""
        return StepStats(n_samples=self.n_samples,
                         n_collision_free=self.n_samples - self.n_crashed, ess=self.ess)


class MPPI(RecordsSamples, PlansToGoal):
    """MPPI on a sampling problem (BaS-MPPI when the problem's model is barrier-embedded).

    The obstacles are the model's own scene until :meth:`set_scene` gives another (a new map
    or a moved obstacle: no recompilation, the kernels take the scene as an input).
    :meth:`record_samples` hands out the last batch's samples (``nominal`` None)."""

    def __init__(self, sp: SamplingProblem, goal, config: MPPIConfig = MPPIConfig()):
        if len(config.sigma) != sp.nu:
            raise fail("MPPIConfig.sigma", config.sigma, f"need {sp.nu} entries")
        self.sp, self.cfg = sp, config
        self.sampler = Sampler(sp, config.backend, config.precision)
        self._deadline_history = DeadlineHistory()  # recent chunk and tail times
        self._joined = JoinBuffers(config.n_samples)  # where a deadline step joins its chunks
        self._plan_to(goal, config)

    def initial_state(self, x0=None) -> MPPIState:
        return MPPIState(U=np.zeros((self.cfg.horizon, self.sp.nu)))

    @deadline_step
    def step(self, state: MPPIState, x, rng: np.random.Generator):
        t0 = time.perf_counter()
        xb = full_state(self.sp, x, self.consts.scene)
        U = state.U
        check_plan(U, self.cfg.horizon, self.sp.nu)
        cfg = self.cfg
        clock = (None if cfg.deadline_s is None
                 else StepClock(cfg.deadline_s, t0, self._deadline_history,
                                 kernel_threads(cfg.horizon)))
        for _ in range(cfg.iterations):
            if clock is None:
                batch = self.sampler.mppi(xb, U, cfg.n_samples, self.consts,
                                          int(rng.integers(0, 2**63)))
            else:
                def draw(n: int, seed: int, U: np.ndarray = U) -> MPPIBatch:
                    return self.sampler.mppi(xb, U, n, self.consts, seed)

                got = sample_within(clock, cfg.n_samples, cfg.chunks, draw, rng,
                                    partial(join_mppi, cat=self._joined.cat))
                if got is None:
                    break
                batch = got
            W = importance_weights(batch.S, cfg.lam)
            if W.valid:
                U = cfg.smooth(weighted_controls(batch.v, W.w))
        u = U[0].copy()
        dt = time.perf_counter() - t0
        rec = self.sample_recorder
        samples = None if rec is None else rec.record(
            x0=xb, v=batch.v, crashed=batch.crashed, weights=W.w, scene=self.consts.scene)
        info = MPPIInfo(free_energy=W.free_energy, ess=W.ess, n_crashed=int(batch.crashed.sum()),
                        valid_weights=W.valid, time_s=dt, n_samples=int(batch.S.size),
                        samples=samples,
                        deadline=None if clock is None else clock.report(cfg.n_samples))
        return MPPIState(U=shift_plan(U, 1, self.cfg.tail)), u, info


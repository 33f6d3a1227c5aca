"""Safe-MPPI batches: MPPI samples projected onto the discrete CBF constraints and/or scored with
the DCBF violation cost (:mod:`workbench.sampling.kernels.safe`), on the compiled kernel or its
NumPy twin (:mod:`workbench.sampling.methods.twin`).

Like :class:`~workbench.sampling.sampler.Sampler`: every call takes an explicit seed; the
compiled backend draws its noise in the kernel from it, the NumPy backend with
``numpy.random.default_rng(seed)`` (tests feed the twin the kernel's noise,
``SafeSampler.lib.normals``). Sample outputs are lane-major: v (T, nu, N).

:class:`SafeMPPIPlanner` is MPPI's planning loop (goal, constants, scene, iterations, update)
on a :class:`SafeSampler`; the safe controllers of :mod:`workbench.sampling.methods` build on it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workbench.problem.dcbf import DEFAULT_GAMMA, check_gamma
from workbench.sampling.feedback.effect import differs
from workbench.sampling.kernels.constants import SamplerConstants
from workbench.sampling.kernels.safe import safe_library
from workbench.sampling.kernels.vocabulary import step_times
from workbench.sampling.methods.twin import safe_twin
from workbench.sampling.mppi import MPPIConfig
from workbench.sampling.planning import (
    PlansToGoal,
    check_plan,
    full_state,
)
from workbench.sampling.problem import SamplingProblem
from workbench.sampling.sampler import Backend, check_batch
from workbench.sampling.twin import lane_major
from workbench.sampling.weights import Weights, importance_weights, weighted_controls
from workbench.validation import as_array, fail, flag, one_of, real


@dataclass(frozen=True)
class SafeOptions:
    """What the safe kernel does to the samples: ``project`` each sample control onto the
    most restrictive discrete CBF constraint (when violated), add ``w_dcbf`` (>= 0) times the
    DCBF violation to each step's cost, with the class-K rate ``gamma`` in (0, 1]. With
    project False and w_dcbf 0 the batch is plain MPPI's."""

    project: bool = False
    w_dcbf: float = 0.0
    gamma: float = DEFAULT_GAMMA

    def __post_init__(self) -> None:
        flag("SafeOptions.project", self.project)
        real("SafeOptions.w_dcbf", self.w_dcbf, 0.0)
        check_gamma("SafeOptions.gamma", self.gamma)

    def kernel_consts(self) -> dict[str, np.ndarray]:
        return {"project": np.array([float(self.project)]),
                "w_dcbf": np.array([float(self.w_dcbf)]),
                "gamma": np.array([float(self.gamma)])}


@dataclass(frozen=True, kw_only=True)
class SafeBatch:
    S: np.ndarray  # (N,) sample costs
    crashed: np.ndarray  # (N,) bool
    v: np.ndarray  # (T, nu, N) applied sample controls (clipped, projected)
    projected: np.ndarray  # (N,) int: steps where the linearised constraint was violated
    # (N,) int: steps where the projection moved the sample's control (effect.differs from
    # clip(u + sigma z)); zeros without projection
    moved: np.ndarray
    infeasible: np.ndarray  # (N,) int: projected steps still violating a constraint
    dcbf: np.ndarray  # (N,) DCBF violation sum (without the weight)


class SafeSampler:
    """Safe-MPPI batches for one sampling problem. ``lib`` is the compiled
    :class:`~workbench.sampling.kernels.safe.SafeLibrary` (None on the NumPy backend)."""

    def __init__(self, sp: SamplingProblem, backend: Backend = "auto"):
        one_of("backend", backend, ("auto", "compiled", "numpy"))
        self.sp = sp
        self.lib = None if backend == "numpy" else safe_library(sp)
        if backend == "compiled" and self.lib is None:
            raise fail("backend", backend, "no compiled safe-MPPI kernel for this problem (no C "
                       "compiler, or an operation the C back end cannot compile: see the "
                       "warning); use 'numpy' or 'auto'")
        self.backend = "compiled" if self.lib is not None else "numpy"

    def _noise(self, N: int, T: int, seed: int) -> np.ndarray:
        return np.random.default_rng(seed).standard_normal((N, T, self.sp.nu))

    def batch(self, x0, U, N: int, consts: SamplerConstants, options: SafeOptions,
              seed: int) -> SafeBatch:
        """N samples from the full state x0 around the plan U (T, nu); an empty
        ``consts.scene`` means the model's own."""
        sp = self.sp
        if not isinstance(options, SafeOptions):
            raise fail("options", options, "must be a SafeOptions")
        U, consts = check_batch(sp, N, U, consts)
        x0 = as_array("x0", x0, (sp.nx,))
        T = U.shape[0]
        if self.lib is not None:
            k = self.lib.safe
            out = k(k.carry.pack(N, x=x0), consts={**consts.kernel_consts(),
                                                   **options.kernel_consts()},
                    time_in={"u": U, **step_times(sp, T)}, seed=seed)
            r = k.result.unpack(out.result)
            v = out.lane_out[0]
            return SafeBatch(S=r["S"].copy(), crashed=r["crashed"] > 0, v=v,
                             projected=np.rint(r["projected"]).astype(int),
                             moved=self._moved(v, U, consts, options, seed),
                             infeasible=np.rint(r["infeasible"]).astype(int),
                             dcbf=r["dcbf"].copy())
        ref = safe_twin(sp, np.tile(x0, (N, 1)), U, self._noise(N, T, seed), consts,
                        options.project, options.w_dcbf, options.gamma)
        v = np.ascontiguousarray(lane_major(ref["v"]))
        return SafeBatch(S=ref["S"], crashed=ref["crashed"], v=v, projected=ref["projected"],
                         moved=self._moved(v, U, consts, options, seed),
                         infeasible=ref["infeasible"], dcbf=ref["dcbf"])

    def _moved(self, v: np.ndarray, U: np.ndarray, consts: SamplerConstants,
               options: SafeOptions, seed: int) -> np.ndarray:
        """(N,) the steps where the projection moved each sample's control v (T, nu, N) away
        from its sampled control clip(u + sigma z) (the same seed's normals z)."""
        T, nu, N = v.shape
        if not options.project:
            return np.zeros(N, int)
        Z = (self.lib.normals(N, T, nu, seed) if self.lib is not None
             else self._noise(N, T, seed).transpose(1, 2, 0))
        v0 = np.clip(U[:, :, None] + consts.sigma[None, :, None] * Z,
                     consts.u_min[None, :, None], consts.u_max[None, :, None])
        return differs(v, v0, axis=1).sum(axis=0)


@dataclass(frozen=True)
class SafeMPPIState:
    U: np.ndarray  # (T, nu) importance-sampling sequence


class SafeMPPIPlanner(PlansToGoal):
    """MPPI's planning loop on a :class:`SafeSampler` with fixed :class:`SafeOptions`: goal
    (a physical goal of a barrier-embedded problem is lifted in the current scene, like
    :class:`~workbench.sampling.mppi.MPPI`), constants, scene, ``iterations`` batches
    per step, each updating the plan to the weighted average of the applied sample controls
    (smoothed when the config asks)."""

    def __init__(self, sp: SamplingProblem, goal, config: MPPIConfig, options: SafeOptions):
        if not isinstance(config, MPPIConfig):
            raise fail("config", config, "must be an MPPIConfig")
        if len(config.sigma) != sp.nu:
            raise fail("MPPIConfig.sigma", config.sigma, f"need {sp.nu} entries")
        if config.deadline_s is not None:
            raise fail("MPPIConfig.deadline_s", config.deadline_s, "Shield-MPPI and the CBF "
                       "projection have no deadline; leave it None (MPPI, BaS-MPPI and the "
                       "robust controllers apply one)")
        self.sp, self.cfg, self.options = sp, config, options
        self.sampler = SafeSampler(sp, config.backend)
        self._plan_to(goal, config)

    def initial_state(self, x0=None) -> SafeMPPIState:
        return SafeMPPIState(U=np.zeros((self.cfg.horizon, self.sp.nu)))

    def full_state(self, x) -> np.ndarray:
        """The measured state as the problem's full state (lifted in the current scene)."""
        return full_state(self.sp, x, self.consts.scene)

    def plan(self, state: SafeMPPIState, xb: np.ndarray,
             rng: np.random.Generator) -> tuple[np.ndarray, Weights, SafeBatch]:
        """(updated plan, weights and batch of the last iteration) from the full state xb; one
        seed ``rng.integers(0, 2**63)`` per iteration."""
        if not isinstance(state, SafeMPPIState):
            raise fail("state", type(state).__name__, "must be a SafeMPPIState "
                       "(from initial_state)")
        U = state.U
        check_plan(U, self.cfg.horizon, self.sp.nu)
        for _ in range(self.cfg.iterations):
            batch = self.sampler.batch(xb, U, self.cfg.n_samples, self.consts, self.options,
                                       int(rng.integers(0, 2**63)))
            W = importance_weights(batch.S, self.cfg.lam)
            if W.valid:
                U = self.cfg.smooth(weighted_controls(batch.v, W.w))
        return U, W, batch


class SafeMPPIController:
    """The scene, constants and state of a controller planned by a :class:`SafeMPPIPlanner`
    (its ``planner``): shared by the CBF-projection and Shield-MPPI controllers."""

    planner: SafeMPPIPlanner

    @property
    def goal(self) -> np.ndarray:
        """The planner's goal (read-only)."""
        return self.planner.goal

    @property
    def consts(self) -> SamplerConstants:
        return self.planner.consts

    @property
    def scene(self) -> np.ndarray:
        """The current scene vector."""
        return self.planner.scene

    def set_scene(self, scene) -> None:
        """Sample, plan and act in ``scene`` from the next step on (no recompilation)."""
        self.planner.set_scene(scene)

    def initial_state(self, x0=None) -> SafeMPPIState:
        return self.planner.initial_state(x0)


__all__ = ["SafeBatch", "SafeMPPIController", "SafeMPPIPlanner", "SafeMPPIState", "SafeOptions",
           "SafeSampler"]

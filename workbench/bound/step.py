"""Per-step Lemma-1 record (assumptions §11.2) from the first SAIS batch of an SA-RMPPI step.

Use::

    ctrl = nav.controller("sa_rmppi", robust=RMPPIConfig(diagnostics=True))
    est = BoundEstimator(ctrl, Disturbance(10.0))
    state, u, info = ctrl.step(state, x, rng)          # info.batch: the first SAIS batch
    rec = est.step(info.batch, info, x, u)             # BoundStep
    checks = step_checks(prev) + transition_checks(prev, rec)   (workbench.bound.checks)

or, for a controller without the hook, :func:`first_batch` replays a step on a copy of the
generator (the caller's generator is not advanced).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
from scipy.special import logsumexp

from workbench.bound.disturbance import d_f, disturbance_bound
from workbench.bound.free_energy import (
    FreeEnergy,
    Method,
    bootstrap_free_energy,
    check_costs,
    free_energy_estimate,
    free_energy_lse,
)
from workbench.bound.lipschitz import CostGradients, Lipschitz, LipschitzGrid, Segments
from workbench.bound.tube import Tube, check_trajectories, tube_radius
from workbench.codegen.fastcall import FastFunction
from workbench.sampling.planning import physical_model
from workbench.sampling.robust import RMPPIInfo, RobustMPPI
from workbench.sampling.sampler import SAISDiagBatch
from workbench.sim import Disturbance
from workbench.validation import fail, integer, one_of, real

Constants = Literal["local", "global", "sampled"]
CONSTANTS: tuple[Constants, ...] = ("local", "global", "sampled")


@dataclass(frozen=True)
class BoundConfig:
    """Estimator settings (assumptions §11.2; defaults [A])."""

    z: float = 3.0  # E = z sd + bias
    method: Method = "delta"  # or "mppig" (MPPI-G computeFreeEnergy)
    n_q: Literal["T", "T-1"] = "T"  # running terms in delta: T summed in Alg. 1, T-1 in [P]
    bootstrap: int = 0  # resamples for E_bootstrap (0: off; 200 to validate)
    quantile: float = 0.99  # tube radius quantile
    disturbance_prob: float = 0.999  # D = quantile of ‖w‖
    # norm of R, L and D_F: the physical state with q̃ = q∘lift, or x̄ = [x; β] (lipschitz.py)
    space: Literal["physical", "augmented"] = "physical"

    def __post_init__(self) -> None:
        one_of("BoundConfig.method", self.method, ("delta", "mppig"))
        one_of("BoundConfig.space", self.space, ("physical", "augmented"))
        one_of("BoundConfig.n_q", self.n_q, ("T", "T-1"))
        real("BoundConfig.z", self.z, 0.0, strict=True)
        bootstrap = integer("BoundConfig.bootstrap", self.bootstrap)
        if bootstrap < 0 or bootstrap == 1:
            raise fail("BoundConfig.bootstrap", self.bootstrap, "must be 0 (off) or >= 2")
        real("BoundConfig.quantile", self.quantile, 0.0, strict=True, maximum=1.0)
        if not 0.0 < real("BoundConfig.disturbance_prob", self.disturbance_prob) < 1.0:
            raise fail("BoundConfig.disturbance_prob", self.disturbance_prob, "must lie in (0, 1)")


@dataclass(frozen=True)
class BoundStep:
    """Everything Lemma 1's checks need from one control step (scalars; no trajectories)."""

    lam: float
    alpha: float  # threshold at the chosen nominal state (the SAIS clamp's alpha)
    F_real: FreeEnergy  # from pure state costs + LR (assumptions §11.2 item 3)
    F_nom: FreeEnergy
    F_real_code: float  # from S_real (Alg. 1 line 9)
    F_nom_code: float  # from S_nom (line 12)
    E: float  # max(E_real, E_nom)
    E_bootstrap: float  # max of the bootstrap E's (nan when off)
    tube: Tube
    local: Lipschitz
    global_: Lipschitz
    n_q: int
    D: float
    D_F: float
    t1_gap: float  # min_n (Sx_nom_n - Sx_real_n): T1 holds iff delta + t1_gap >= 0
    t1_gap_safe: float  # the same over samples whose real and nominal rollouts stayed safe
    n_samples: int
    n_crashed_real: int
    n_crashed_nom: int
    fallback_used: bool  # no candidate was admissible
    nominal_differs: bool  # x*_0 != measured state
    # the sampled-tube bound (assumptions §11.4): δ_λ, max_n δ_n, max_n δ_n over safe pairs
    delta_sampled: float
    delta_sampled_max: float
    delta_sampled_max_safe: float
    # from an independent batch of the same step (nan without one), for T2E
    F_real_ind: float = np.nan
    F_nom_ind: float = np.nan
    E_ind: float = np.nan

    @property
    def all_real_safe(self) -> bool:
        return self.n_crashed_real == 0

    @property
    def nominal_admissible(self) -> bool:
        """F̂_nom(t) <= alpha (the premise of T3d)."""
        return self.F_nom.value <= self.alpha

    def lipschitz(self, constants: Constants = "local") -> Lipschitz:
        one_of("constants", constants, ("local", "global"))
        return self.local if constants == "local" else self.global_

    def delta(self, constants: Constants = "local") -> float:
        """δ = (L_φ + n_q L_q) R for local or global constants; δ_λ for ``"sampled"``."""
        one_of("constants", constants, CONSTANTS)
        if constants == "sampled":
            return self.delta_sampled
        L = self.lipschitz(constants)
        return (L.L_phi + self.n_q * L.L_q) * self.tube.R

    def delta_per_sample(self, constants: Constants = "local", safe: bool = False) -> float:
        """The bound on max_n (S_n − S*_n) (T1; ``safe``: over the safe pairs, T1s): δ, or
        max_n δ_n for ``"sampled"``."""
        if constants == "sampled":
            return self.delta_sampled_max_safe if safe else self.delta_sampled_max
        return self.delta(constants)


def sampled_deltas(seg: Segments, S_nom, lam: float, safe=None) -> tuple[float, float, float]:
    """(δ_λ, max_n δ_n, max_n δ_n over ``safe``) of the sampled-tube bound (assumptions
    §11.4): δ_n = :meth:`Segments.products`, δ_λ = −λ log Σ_n w*_n exp(−δ_n/λ) with w*_n the
    nominal batch's weights ∝ exp(−S*_n/λ) (``S_nom``: the costs F̂_nom is computed from);
    ``safe`` a boolean mask of samples (default all; no safe sample: inf)."""
    lam = real("lam", lam, 0.0, strict=True)
    d = seg.products()
    S = check_costs("S_nom", S_nom, d.size)
    a = -S / lam
    soft = -lam * float(logsumexp(a - d / lam) - logsumexp(a))
    m = np.ones(d.size, bool) if safe is None else np.asarray(safe, bool)
    if m.shape != d.shape:
        raise fail("safe", m.shape, f"need one flag per sample {d.shape}")
    return max(soft, 0.0), float(d.max()), float(d[m].max()) if m.any() else np.inf


def check_batch(batch: SAISDiagBatch) -> None:
    """Shapes and finiteness of a diagnostic batch (ValueError naming the field)."""
    if not isinstance(batch, SAISDiagBatch):
        raise fail("batch", type(batch).__name__, "need a SAISDiagBatch (Sampler.sais(..., "
                   "diagnostics=True) or RMPPIConfig(diagnostics=True))")
    X, _ = check_trajectories(batch.X, batch.X_nom)
    N = X.shape[2]
    for name in ("Sx_real", "Sx_nom", "LR", "S_real", "S_nom"):
        check_costs(f"batch.{name}", getattr(batch, name), N)


class BoundEstimator:
    """Per-step estimators of one SA-RMPPI controller; the global constant is computed once."""

    def __init__(self, ctrl: RobustMPPI, disturbance: Disturbance,
                 config: BoundConfig = BoundConfig(), grid: LipschitzGrid | None = None,
                 global_constant: Lipschitz | None = None, backend: str = "auto"):
        self.ctrl, self.cfg, self.grid = ctrl, config, grid or LipschitzGrid()
        sp = ctrl.sp
        self.gradients = CostGradients(sp, backend, config.space)
        self.p = np.asarray(ctrl.consts.p, float)
        self.global_ = global_constant or self.gradients.global_constant(self.grid, self.p)
        self.D = disturbance_bound(disturbance, sp.model.dt, config.disturbance_prob,
                                   physical_model(sp.model))
        self._dyn = FastFunction(sp.functions()["dyn"])

    def step(self, batch: SAISDiagBatch, info: RMPPIInfo, x, u,
             rng: np.random.Generator | None = None,
             independent: SAISDiagBatch | None = None) -> BoundStep:
        """The record of one step: ``batch`` its first SAIS batch, ``info`` its info, ``x`` the
        measured state, ``u`` the applied control; ``rng`` for the bootstrap (if enabled);
        ``independent`` an optional second batch of the same step (:func:`independent_batch`)
        for T2E."""
        check_batch(batch)
        cfg, lam = self.cfg, float(self.ctrl.cfg.lam)
        sp = self.ctrl.sp
        n = sp.model.n_physical
        nr = self.gradients.n  # coordinates in the norm of R, L and D_F
        T = batch.X.shape[0] - 1
        Sr = batch.Sx_real + batch.LR
        Sn = batch.Sx_nom + batch.LR
        Fr = free_energy_estimate(Sr, lam, cfg.z, cfg.method)
        Fn = free_energy_estimate(Sn, lam, cfg.z, cfg.method)
        Eb = np.nan
        if cfg.bootstrap:
            if rng is None:
                raise fail("rng", None, "BoundConfig.bootstrap > 0 needs a generator")
            Eb = max(bootstrap_free_energy(S, lam, rng, cfg.bootstrap, cfg.z).E for S in (Sr, Sn))
        # per-sample radii dropped: a record is kept per step over whole studies
        tube = replace(tube_radius(batch.X, batch.X_nom, nr, sp.model.position, cfg.quantile),
                       per_sample=None)
        seg = self.gradients.segments(batch.X, batch.X_nom, self.p)
        local = seg.lipschitz()
        xb = np.asarray(x, float).ravel()
        scene = self.ctrl.consts.scene
        if xb.size == n and sp.nx != n:
            xb = sp.model.lift(xb, scene)
        if xb.shape != (sp.nx,) or not np.all(np.isfinite(xb)):
            raise fail("x", x, f"the measured state must be {n} or {sp.nx} finite numbers")
        if info.x_nom is None:
            raise fail("info.x_nom", None, "the step's info must carry the nominal state")
        xn = self._dyn(xb, np.asarray(u, float), scene)[0]
        gap = batch.Sx_nom - batch.Sx_real
        safe = ~(np.asarray(batch.crashed_real) | np.asarray(batch.crashed_nom))
        gap_safe = float(np.min(gap[safe])) if safe.any() else np.inf
        soft, dmax, dmax_safe = sampled_deltas(seg, Sn, lam, safe)
        DF = d_f(xb, xn, info.x_nom, self.D, nr)
        return BoundStep(
            lam=lam, alpha=float(info.alpha), F_real=Fr, F_nom=Fn,
            F_real_code=free_energy_lse(batch.S_real, lam),
            F_nom_code=free_energy_lse(batch.S_nom, lam), E=max(Fr.E, Fn.E), E_bootstrap=Eb,
            tube=tube, local=local, global_=self.global_, n_q=T if cfg.n_q == "T" else T - 1,
            D=self.D, D_F=DF, t1_gap=float(np.min(gap)), t1_gap_safe=gap_safe,
            n_samples=int(batch.Sx_real.size), n_crashed_real=int(batch.crashed_real.sum()),
            n_crashed_nom=int(batch.crashed_nom.sum()), fallback_used=bool(info.fallback_used),
            nominal_differs=bool(info.nominal_differs), delta_sampled=soft,
            delta_sampled_max=dmax, delta_sampled_max_safe=dmax_safe,
            **self._independent(independent, lam))

    def _independent(self, b: SAISDiagBatch | None, lam: float) -> dict[str, float]:
        if b is None:
            return {}
        check_batch(b)
        cfg = self.cfg
        Fr = free_energy_estimate(b.Sx_real + b.LR, lam, cfg.z, cfg.method)
        Fn = free_energy_estimate(b.Sx_nom + b.LR, lam, cfg.z, cfg.method)
        return {"F_real_ind": Fr.value, "F_nom_ind": Fn.value, "E_ind": max(Fr.E, Fn.E)}


def independent_batch(ctrl: RobustMPPI, batch: SAISDiagBatch, seed: int) -> SAISDiagBatch:
    """A second batch of the same step: same starts, plan, gains and constants, another seed."""
    check_batch(batch)
    if int(seed) == batch.seed:
        raise fail("seed", seed, "an independent batch needs a seed other than the batch's")
    out = ctrl.sampler.sais(batch.X[0, :, 0], batch.X_nom[0, :, 0], batch.U, batch.K,
                            batch.X.shape[2], batch.consts, int(seed), diagnostics=True)
    if not isinstance(out, SAISDiagBatch):  # the sampler's annotation omits diagnostics=True
        raise TypeError(f"the sampler returned {type(out).__name__} for diagnostics=True")
    return out


def with_diagnostics(ctrl: RobustMPPI) -> RobustMPPI:
    """A shallow copy of the controller whose steps hand out their first SAIS batch."""
    if ctrl.rcfg.diagnostics:
        return ctrl
    twin = copy.copy(ctrl)
    twin.rcfg = replace(ctrl.rcfg, diagnostics=True)
    return twin


def first_batch(ctrl: RobustMPPI, state, x, rng: np.random.Generator):
    """Replay one control step on a copy of ``rng`` with diagnostics: returns
    (batch, info, u, new_state) exactly as ``ctrl.step`` would (same selection, gains, noise);
    ``rng`` itself is not advanced."""
    new_state, u, info = with_diagnostics(ctrl).step(state, x, copy.deepcopy(rng))
    return info.batch, info, u, new_state

"""The per-step arithmetic of Robust MPPI's nominal-state selection, vectorised: the candidate
start states compiled and all candidate free energies in one pass.

Each function computes the numbers of its step-by-step twin in
:mod:`workbench.sampling.robust` and :mod:`workbench.sampling.weights` bit for bit (the
same operations in the same order): the closed loop amplifies last-bit differences (a control
sum rounded differently moved the states of a 30-step disturbed navigation episode by about
1e-11 relative). The update's weights and control sums are the twin's own functions
(:func:`~workbench.sampling.weights.importance_weights`,
:func:`~workbench.sampling.weights.weighted_controls`). ``RobustMPPI(..., fast=False)`` runs
the twins.
"""

from __future__ import annotations

import math

import numpy as np

from workbench.codegen.fastcall import FastFunction
from workbench.sampling.kernels.robust import StartsKernel, starts_library
from workbench.sampling.problem import SamplingProblem


class CandidateStarts:
    """The candidate start states of the nominal-state selection (assumptions §9.3): the
    weights ``W`` (n_candidates, 3) mix the old nominal state a0, its propagation
    a1 = F(a0, u*_0) and the measured state xb; each mixture's barrier state is recomputed
    from its physical part (the model's lift), and the last candidate is xb itself. The
    propagation and the lifts are compiled
    (:func:`~workbench.sampling.kernels.robust.starts_library`; CasADi's virtual machine
    without a compiler); the mixture is the same NumPy product as the step-by-step
    selection's (its rounding is the BLAS's)."""

    def __init__(self, sp: SamplingProblem, W: np.ndarray, compiled: bool = True):
        m = sp.model
        self.nc, self.nx, self.n = W.shape[0], sp.nx, m.n_physical
        self._mix = np.ascontiguousarray(W, dtype=float)
        lib = (starts_library(sp.functions()["dyn"], m.lift_function, sp.nx, m.n_physical,
                              sp.fingerprint()) if compiled else None)
        self._k = None if lib is None else StartsKernel(lib, sp.nx, sp.nu, m.n_physical,
                                                        self.nc, m.n_scene)
        if self._k is None:
            self._a1 = FastFunction(sp.functions()["dyn"])
            self._lift = FastFunction(m.lift_function, self.nc, shared=(1,))

    @property
    def compiled(self) -> bool:
        return self._k is not None

    def __call__(self, a0: np.ndarray, u0: np.ndarray, xb: np.ndarray,
                 scene: np.ndarray) -> np.ndarray:
        """(n_candidates, nx) start states."""
        k = self._k
        if k is not None:
            a1 = k.propagate(a0, u0, scene)
            starts = k.lift((self._mix @ np.stack([a0, a1, xb]))[:, : self.n])
        else:
            a1 = self._a1(a0, u0, scene)[0]
            mixed = self._mix @ np.stack([a0, a1, xb])
            starts = self._lift(mixed[:, : self.n], scene)[0].reshape(self.nc, self.nx)
        starts[-1] = xb
        return starts


def candidate_free_energies(S: np.ndarray, n_candidates: int, lam: float) -> np.ndarray:
    """Free energy of each candidate's M = S.size / n_candidates costs (consecutive blocks of
    S): F_i = -lam log(mean_j exp(-(S_ij - rho_i) / lam)) + rho_i, rho_i the smallest finite
    cost of block i, non-finite costs weighing nothing; +inf for a block without a finite
    cost. Equals :func:`~workbench.sampling.weights.free_energy` per block."""
    S = S.reshape(n_candidates, -1)
    M = S.shape[1]
    if math.isfinite(S.sum()):  # every cost finite (else, or on overflow, the general path)
        rho = S.min(axis=1)
        e = np.subtract(rho[:, None], S)  # -(S - rho), exactly
        e /= lam
        total = np.exp(e, out=e).sum(axis=1)
        return -lam * np.log(total / M) + rho
    finite = np.isfinite(S)
    any_finite = finite.any(axis=1)
    rho = np.where(finite, S, np.inf).min(axis=1)
    rho_safe = np.where(any_finite, rho, 0.0)
    with np.errstate(invalid="ignore"):
        e = np.where(finite, np.exp(-(np.where(finite, S, 0.0) - rho_safe[:, None]) / lam),
                     0.0)
    total = e.sum(axis=1)
    F = np.full(n_candidates, np.inf)
    ok = any_finite
    F[ok] = -lam * np.log(total[ok] / M) + rho[ok]
    return F

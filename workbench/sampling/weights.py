"""Importance weights, free energy and effective sample size (assumptions §8.1, §11.2).

Non-finite costs (NaN or inf) are treated as +inf: they get zero weight and never reach the
normalisation. All computations shift by the minimum finite cost (the max-shift).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workbench.validation import real


@dataclass(frozen=True)
class Weights:
    """Normalised weights w (N,), the shift rho = min finite cost, and the free energy."""

    w: np.ndarray
    rho: float
    free_energy: float
    ess: float
    n_finite: int

    @property
    def valid(self) -> bool:
        return self.n_finite > 0


def importance_weights(S, lam: float) -> Weights:
    """w_n = exp(-(S_n - rho)/lam) / sum_j exp(-(S_j - rho)/lam), F = -lam log(mean exp) + rho.

    If no cost is finite, w is all zeros, F = +inf and ``valid`` is False (callers keep U).
    """
    real("lambda", lam, 0.0, strict=True)
    S = np.asarray(S, dtype=float)
    finite = np.isfinite(S)
    n = int(np.count_nonzero(finite))
    if n == 0:
        return Weights(w=np.zeros_like(S), rho=np.inf, free_energy=np.inf, ess=0.0, n_finite=0)
    if n == S.size:  # the common case, in place: the same operations as below, fewer passes
        rho = float(S.min())
        e = np.subtract(S, rho)
        np.negative(e, out=e)
        np.divide(e, lam, out=e)
        np.exp(e, out=e)
    else:
        rho = float(S[finite].min())
        e = np.zeros_like(S)
        e[finite] = np.exp(-(S[finite] - rho) / lam)
    total = float(e.sum())
    w = np.divide(e, total, out=e)
    F = -lam * np.log(total / S.size) + rho
    return Weights(w=w, rho=rho, free_energy=float(F), ess=float(1.0 / np.dot(w, w)),
                   n_finite=n)


def free_energy(S, lam: float) -> float:
    """Monte Carlo free-energy estimate of a batch of costs (the paper's free-energy definition,
    assumptions §11.2)."""
    return importance_weights(S, lam).free_energy


def weighted_controls(v_lane_major: np.ndarray, w: np.ndarray) -> np.ndarray:
    """sum_n w_n v_n for lane-major samples v (T, nu, N): the MPPI update, (T, nu). One BLAS
    matrix-vector product over the (T nu, N) rows (measured 3.5x faster than a 3-d matmul)."""
    v = np.asarray(v_lane_major)
    return np.dot(v.reshape(-1, v.shape[-1]), w).reshape(v.shape[:-1])

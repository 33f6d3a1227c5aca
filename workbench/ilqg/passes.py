"""Named results of the iLQG passes, the same for both backends (compiled C and NumPy).

Shapes: X (T+1, nx), U (T, nu), k (T, nu), K (T, nu, nx).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False, kw_only=True, slots=True)
class ForwardResult:
    """A rollout: its states, its (clipped) controls and its cost, crash penalty included."""

    X: np.ndarray
    U: np.ndarray
    cost: float


@dataclass(frozen=True, eq=False, kw_only=True, slots=True)
class BackwardResult:
    """A backward pass. ``status`` is 0 on success, t+1 when Quu (or the box QP) failed at
    step t; ``dV`` = (sum k'Qu, sum ½ k'Quu k), the expected-decrease coefficients."""

    status: int
    k: np.ndarray
    K: np.ndarray
    dV: np.ndarray


@dataclass(frozen=True, eq=False, kw_only=True, slots=True)
class LineSearchResult:
    """The first accepted step of a line search, or (when not ``accepted``) the unchanged
    trajectory with ``alpha`` = ``expected`` = 0."""

    accepted: bool
    X: np.ndarray
    U: np.ndarray
    cost: float
    alpha: float
    expected: float  # expected decrease -alpha (dV[0] + alpha dV[1])


@dataclass(frozen=True, eq=False, kw_only=True, slots=True)
class SolveResult:
    """The whole outer loop run in C. ``stop`` is the index of the stop reason in
    ``solver._STOPS``; ``history`` rows (n, 8): cost, cost change, expected change, alpha, mu,
    gradient norm, accepted (0/1), step (index in ``solver.STEPS``)."""

    X: np.ndarray
    U: np.ndarray
    k: np.ndarray
    K: np.ndarray
    cost: float
    stop: int
    converged: bool
    history: np.ndarray
    mu: float  # final regularisation


@dataclass(frozen=True, eq=False, kw_only=True, slots=True)
class BoxQPResult:
    """A box QP solution. ``result`` codes as in core.c's ``wb_box_qp`` (>= 1: solved);
    ``free`` marks the unclamped coordinates; ``L`` is the Cholesky factor of H[free, free]
    (NumPy twin only, None from the compiled QP)."""

    x: np.ndarray
    result: int
    free: np.ndarray
    L: np.ndarray | None = None

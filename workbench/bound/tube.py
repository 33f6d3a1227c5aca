"""Tube radius R of the real samples about the nominal ones (assumptions §11.2 item 5).

Trajectories are lane-major (T+1, nx, N), k = 0..T, as :class:`SAISDiagBatch` holds them. Norms
are Euclidean on the physical state (p, v) — the state whose norm the Lipschitz constants of
:mod:`workbench.bound.lipschitz` use (β is a function of p on every sample, see there).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workbench.validation import fail, integer


@dataclass(frozen=True)
class Tube:
    R: float  # max_{n,k} ‖x^n_k − x*^n_k‖ (the proof's e_k, pairwise)
    R99: float  # 99 % quantile over samples of max_k ‖x^n_k − x*^n_k‖
    R_position: float  # pairwise, position coordinates only
    R_mean_nominal: float  # max_{n,k} ‖x^n_k − mean_m x*^m_k‖ (tube about the mean nominal)
    per_sample: np.ndarray | None  # (N,) max_k ‖x^n_k − x*^n_k‖ (None in a BoundStep)


def check_trajectories(X, X_nom) -> tuple[np.ndarray, np.ndarray]:
    """Both (T+1, nx, N), finite, same shape, N >= 1."""
    out = []
    for name, a in (("X", X), ("X_nom", X_nom)):
        a = np.asarray(a, dtype=float)
        if a.ndim != 3:
            raise fail(name, a.shape, "expected lane-major trajectories (T+1, nx, N)")
        if a.shape[0] < 2 or a.shape[2] < 1:
            raise fail(name, a.shape, "the batch is empty: need T >= 1 and N >= 1")
        if not np.all(np.isfinite(a)):
            raise fail(name, "non-finite entries", "trajectories must be finite")
        out.append(a)
    if out[0].shape != out[1].shape:
        raise fail("X_nom", out[1].shape, f"must match X {out[0].shape}")
    return out[0], out[1]


def tube_radius(X, X_nom, physical: int, position=(0, 1), quantile: float = 0.99) -> Tube:
    """Radii of the real samples X about the nominal samples X_nom (module docstring); the
    norm uses the ``physical`` leading coordinates (nx for the augmented reading)."""
    X, X_nom = check_trajectories(X, X_nom)
    integer("physical", physical, 1, X.shape[1])
    pos = set(position)
    d2, dp2, dm2 = (np.zeros((X.shape[0], X.shape[2])) for _ in range(3))
    for i in range(physical):  # per coordinate: (T+1, N) planes, no strided temporaries
        e = X[:, i] - X_nom[:, i]
        e *= e
        d2 += e
        if i in pos:
            dp2 += e
        m = X[:, i] - X_nom[:, i].mean(axis=1, keepdims=True)
        m *= m
        dm2 += m
    per = np.sqrt(d2.max(axis=0))
    return Tube(R=float(per.max()), R99=float(np.quantile(per, quantile)),
                R_position=float(np.sqrt(dp2.max())), R_mean_nominal=float(np.sqrt(dm2.max())),
                per_sample=per)

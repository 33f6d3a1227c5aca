"""Run-time constants of the sampler kernels, shared by the kernels and their NumPy twin."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class SamplerConstants:
    """Run-time constants shared by all samples (see kernels.py)."""

    sigma: np.ndarray  # (nu,) sampling std
    lam: float  # temperature lambda
    nu_mix: float  # MPPI-G's alpha, the base-distribution mixing (SPEC nu), default 0
    u_min: np.ndarray
    u_max: np.ndarray
    crash_cost: float
    p: np.ndarray  # cost parameters (the goal state)
    alpha: float = np.inf  # RMPPI threshold (SAIS only)
    clip_in_cost: bool = True  # SPEC 10.1: clipped noise and feedback in lines 8, 9, 12
    # the obstacles (flat, model.n_scene; empty when the model has no run-time scene)
    scene: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def kernel_consts(self) -> dict[str, np.ndarray]:
        return {"sigma": np.asarray(self.sigma, float),
                "lr": np.array([self.lam * (1.0 - self.nu_mix)]),
                "u_min": np.asarray(self.u_min, float), "u_max": np.asarray(self.u_max, float),
                "crash": np.array([self.crash_cost]),
                "p": np.asarray(self.p, float), "alpha": np.array([self.alpha]),
                "clip_cost": np.array([float(self.clip_in_cost)]),
                "scene": np.asarray(self.scene, float)}

"""Disturbance bound D and D_F of Lemma 1 (assumptions §11.2 items 7-8).

The plant disturbance is Gaussian, so ‖w‖ < D holds only with a probability: D is the
``prob`` quantile of ‖w‖. For w = c ξ on the two velocities, ξ ~ N(0, I₂), ‖w‖² / c² is χ²₂, so
D = c √(χ²_{2,prob}); with prob = 0.999, √(χ²_{2,0.999}) = √(−2 ln 0.001) = 3.717. For the
default model (velocity variance σ², c = Δt σ) this is the D = 3.717 Δt σ.
"""

from __future__ import annotations

import numpy as np
from scipy.stats import chi2

from workbench.sim import Disturbance
from workbench.validation import as_array, fail, integer, real


def chi_radius(prob: float = 0.999, dof: int = 2) -> float:
    """√(χ²_{dof, prob}): the prob-quantile of ‖ξ‖ for ξ ~ N(0, I_dof)."""
    if not 0.0 < real("prob", prob) < 1.0:
        raise fail("prob", prob, "must lie in (0, 1)")
    integer("dof", dof, 1)
    return float(np.sqrt(chi2.ppf(prob, dof)))


def disturbance_scale(disturbance: Disturbance, dt: float) -> float:
    """c with w = c ξ on the velocities (:class:`workbench.sim.Disturbance`)."""
    real("dt", dt, 0.0, strict=True)
    lvl = float(disturbance.level)
    return {"velocity_variance": dt * np.sqrt(lvl), "velocity_std": dt * lvl,
            "white_noise": np.sqrt(dt) * np.sqrt(lvl), "kick": np.sqrt(lvl)}[disturbance.model]


def disturbance_bound(disturbance: Disturbance, dt: float, prob: float = 0.999,
                      plant=None) -> float:
    """D̂ = c √(χ²_{n,prob}) with n disturbed states: the disturbance's own indices, else the
    plant's (:meth:`Disturbance.indices`), else 2 (the planar velocity)."""
    if disturbance.named is not None:
        n = len(disturbance.named)
    else:
        n = len(disturbance.indices(plant)) if plant is not None else 2
    return disturbance_scale(disturbance, dt) * chi_radius(prob, n)


def d_f(x, x_next_model, x_nom0, D: float, physical: int) -> float:
    """D̂_F = ‖F(x_t, u_t) − x_t‖ + ‖x*_0 − x_t‖ + D̂ on the physical state (assumptions §11.2 item
    8);
    ``x_next_model`` = F(x_t, u_t), the model step without disturbance; the norm uses the
    ``physical`` leading coordinates (nx for the augmented reading)."""
    integer("physical", physical, 1)
    x = as_array("x", np.ravel(x)[:physical], (physical,))
    xn = as_array("x_next_model", np.ravel(x_next_model)[:physical], (physical,))
    xs = as_array("x_nom0", np.ravel(x_nom0)[:physical], (physical,))
    real("D", D, 0.0)
    return float(np.linalg.norm(xn - x) + np.linalg.norm(xs - x) + D)

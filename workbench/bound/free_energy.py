"""Monte Carlo free energy and its uncertainty E_M^V (assumptions §11.2 items 3-4).

F̂ = -λ log (1/N Σ_n exp(-S_n/λ)), by log-sum-exp with the max-shift ρ = min_n S_n.

E_M^V is not defined in the paper. With w_n = exp(-(S_n - ρ)/λ), mean w̄ and sample std s_w:

* ``"delta"`` (default): F̂ = -λ log w̄ + ρ, so sd(F̂) ≈ λ s_w / (w̄ √N) and, to second
  order, bias(F̂) ≈ λ s_w² / (2 N w̄²) (−log is convex: F̂ is biased upwards);
  Ê = z sd + bias, z = 3.
* ``"mppig"``: MPPI-G ``computeFreeEnergy``: var = λ (mean(w²) − w̄²), t = var / (w̄ √N),
  Ê = λ (t + t²/2) (shift-dependent and not scale-consistent; kept for code fidelity).
* :func:`bootstrap_free_energy`: 200 resamples of the batch, Ê_boot = z sd_boot + |bias_boot|.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from workbench.validation import fail, integer, one_of, real

Method = Literal["delta", "mppig"]


def check_costs(name: str, S, n: int | None = None) -> np.ndarray:
    """Per-sample costs as a finite 1-D float array of at least one entry (and ``n`` if given)."""
    try:
        a = np.asarray(S, dtype=float)
    except (TypeError, ValueError) as exc:
        raise fail(name, S, "expected a numeric array of per-sample costs") from exc
    if a.ndim != 1:
        raise fail(name, a.shape, "expected a 1-D array of per-sample costs (N,)")
    if a.size == 0:
        raise fail(name, a.shape, "the batch is empty: need at least one sample")
    if n is not None and a.size != n:
        raise fail(name, a.shape, f"expected ({n},) to match the other per-sample arrays")
    bad = np.flatnonzero(~np.isfinite(a))
    if bad.size:
        raise fail(name, a[bad[:5]], f"{bad.size} non-finite costs (first at sample "
                   f"{int(bad[0])}); every cost must be finite")
    return a


def _lam(lam: float) -> float:
    return real("lam", lam, 0.0, strict=True)


def free_energy_lse(S, lam: float) -> float:
    """F̂ = -λ log mean exp(-S/λ), computed as ρ - λ log mean exp(-(S-ρ)/λ)."""
    S, lam = check_costs("S", S), _lam(lam)
    rho = float(S.min())
    return rho - lam * float(np.log(np.mean(np.exp(-(S - rho) / lam))))


@dataclass(frozen=True)
class FreeEnergy:
    """One free-energy estimate with its Monte Carlo uncertainty."""

    value: float  # F̂
    E: float  # the uncertainty bound used (method below)
    sd: float  # delta-method standard deviation
    bias: float  # delta-method bias (F̂ - F, to second order)
    ess: float  # effective sample size 1/Σ w̃²
    n: int
    method: str
    z: float

    @property
    def interval(self) -> tuple[float, float]:
        return self.value - self.E, self.value + self.E


def free_energy_estimate(S, lam: float, z: float = 3.0, method: Method = "delta") -> FreeEnergy:
    """F̂ and Ê of a batch of costs (module docstring); needs N >= 2."""
    S, lam = check_costs("S", S), _lam(lam)
    one_of("method", method, ("delta", "mppig"))
    real("z", z, 0.0, strict=True)
    N = S.size
    if N < 2:
        raise fail("S", S.shape, "the uncertainty needs at least 2 samples")
    rho = float(S.min())
    w = np.exp(-(S - rho) / lam)
    wbar = float(w.mean())
    value = rho - lam * float(np.log(wbar))
    s_w = float(w.std(ddof=1))
    sd = lam * s_w / (wbar * np.sqrt(N))
    bias = lam * s_w**2 / (2.0 * N * wbar**2)
    if method == "delta":
        E = z * sd + bias
    else:
        var = lam * (float(np.mean(w * w)) - wbar**2)
        t = var / (wbar * np.sqrt(N))
        E = lam * (t + 0.5 * t * t)
    wn = w / w.sum()
    return FreeEnergy(value=value, E=float(E), sd=float(sd), bias=float(bias),
                      ess=float(1.0 / np.sum(wn * wn)), n=N, method=method, z=float(z))


@dataclass(frozen=True)
class Bootstrap:
    """Bootstrap of F̂: resampled estimates, their sd and bias, and Ê_boot = z sd + |bias|."""

    value: float
    sd: float
    bias: float
    E: float
    n_resamples: int


def bootstrap_free_energy(S, lam: float, rng: np.random.Generator, n_resamples: int = 200,
                          z: float = 3.0) -> Bootstrap:
    """Nonparametric bootstrap (resampling the batch with replacement) of F̂."""
    S, lam = check_costs("S", S), _lam(lam)
    integer("n_resamples", n_resamples, 2)
    rho = float(S.min())
    w = np.exp(-(S - rho) / lam)
    idx = rng.integers(0, S.size, size=(int(n_resamples), S.size))
    Fb = rho - lam * np.log(w[idx].mean(axis=1))
    value = rho - lam * float(np.log(w.mean()))
    sd, bias = float(Fb.std(ddof=1)), float(Fb.mean() - value)
    return Bootstrap(value=value, sd=sd, bias=bias, E=z * sd + abs(bias),
                     n_resamples=int(n_resamples))

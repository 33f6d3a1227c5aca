"""Run-time constants of the sampler kernels, shared by the kernels and their NumPy twin."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from workbench.validation import fail, real, scale

# The float32 kernels' guard band (margin units, m^2 for squared-distance margins): a sample
# whose smallest margin comes within it of the crash margin eps_h (at or before its crash) is
# recomputed in double. Float32 rollouts of the navigation double integrator (T = 100 steps,
# random controls, positions up to ~20 m) drift from float64 by at most 2.2e-5 m^2 in the
# smallest margin (1.1e-5 near the obstacles); 2.5e-4 leaves a factor 11. The share of samples
# recomputed grows with the band: in closed loop on the navigation map about 1% (3.7% at 1e-3).
# Scale it with the square of the workspace size for much longer horizons (the float32
# kernels run relative to the start state, so the map's own size and place do not count).
GUARD_BAND = 2.5e-4
_TINY32 = float(np.finfo(np.float32).tiny)  # 1.18e-38
_MAX32 = float(np.finfo(np.float32).max)  # 3.40e38
_BOUNDED = ("u_min", "u_max", "crash_cost", "p", "scene")  # finite in float32


FLOAT32_MAX = _MAX32


def check_scales32(prefix: str, sigma, lam: float, nu_mix: float) -> None:
    """Refuse sampling scales a float32 kernel cannot use: sigma^2, lambda and
    lambda (1 - nu_mix) and their reciprocals must be normal float32 numbers."""
    for i, v in enumerate(np.ravel(np.asarray(sigma, dtype=float))):
        scale32(f"{prefix}.sigma[{i}]", v, power=2)
    scale32(f"{prefix}.lam", lam)
    lr = float(lam) * (1.0 - float(nu_mix))
    if lr != 0.0:
        scale32(f"{prefix}.lam * (1 - nu_mix)", lr)


def scale32(name: str, value: float, power: int = 1) -> float:
    """:func:`workbench.validation.scale` for float32: ``value**power`` and its reciprocal are
    normal float32 numbers (value in [tiny^(1/power), tiny^(-1/power)], tiny = 1.18e-38)."""
    v = float(value)
    p = v**power if np.isfinite(v) else np.inf
    ok = np.isfinite(p) and _TINY32 <= p <= 1.0 / _TINY32
    if not ok:
        lo, hi = _TINY32 ** (1.0 / power), _TINY32 ** (-1.0 / power)
        what = "the value" if power == 1 else "its square" if power == 2 else f"value^{power}"
        raise fail(name, value, f"must lie in [{lo:.4g}, {hi:.4g}] for precision 'float32' "
                   f"({what} and its reciprocal must be normal float32 numbers)")
    return v


@dataclass(frozen=True)
class SamplerConstants:
    """Run-time constants shared by all samples (see kernels.py).

    Checked here: every ``sigma`` in [1.5e-154, 6.7e153] and ``lam`` in [2.2e-308, 4.5e307]
    (sigma^2 and 1/sigma^2, lambda and 1/lambda are normal float64 numbers, as
    :class:`~workbench.sampling.mppi.MPPIConfig` requires); ``guard_band`` >= 0.
    :meth:`check_float32` adds the float32 kernels' ranges."""

    sigma: np.ndarray  # (nu,) sampling std
    lam: float  # temperature lambda
    nu_mix: float  # MPPI-G's alpha, the base-distribution mixing (SPEC nu), default 0
    u_min: np.ndarray
    u_max: np.ndarray
    crash_cost: float
    p: np.ndarray  # cost parameters (the goal state)
    alpha: float = np.inf  # RMPPI threshold (SAIS only)
    clip_in_cost: bool = True  # assumptions §10.1: clipped noise and feedback in lines 8, 9, 12
    # the obstacles (flat, model.n_scene; empty when the model has no run-time scene)
    scene: np.ndarray = field(default_factory=lambda: np.zeros(0))
    guard_band: float = GUARD_BAND  # float32 kernels only (see GUARD_BAND)

    def __post_init__(self) -> None:
        for i, v in enumerate(np.ravel(np.asarray(self.sigma, dtype=float))):
            scale(f"SamplerConstants.sigma[{i}]", float(v), power=2)
        scale("SamplerConstants.lam", self.lam)
        real("SamplerConstants.guard_band", self.guard_band, 0.0)

    def check_float32(self) -> None:
        """Refuse constants a float32 kernel cannot represent: sigma^2, lambda and
        lambda (1 - nu_mix) outside float32's normal range, or any other constant (crash cost,
        limits, goal, scene) beyond float32's largest finite value (it would become inf, and
        inf * 0 a NaN cost). alpha may be +inf (the kernels use it in double)."""
        if self.__dict__.get("_float32_ok"):
            return
        sig = np.ravel(np.asarray(self.sigma, dtype=float))
        lam, lr = float(self.lam), float(self.lam) * (1.0 - float(self.nu_mix))
        big = [np.asarray(getattr(self, n), dtype=float) for n in _BOUNDED]
        with np.errstate(over="ignore", invalid="ignore"):
            sq = sig * sig
            fine = (bool(np.all((sq >= _TINY32) & (sq <= 1.0 / _TINY32)))
                    and _TINY32 <= lam <= 1.0 / _TINY32
                    and (lr == 0.0 or _TINY32 <= lr <= 1.0 / _TINY32)
                    and all(a.size == 0 or float(np.max(np.abs(a))) <= _MAX32 for a in big)
                    and self.guard_band <= _MAX32)
        if not fine:  # name the first offending field
            check_scales32("SamplerConstants", sig, lam, self.nu_mix)
            for name, arr in zip(_BOUNDED, big, strict=True):
                if arr.size and not np.all(np.abs(arr) <= _MAX32):
                    raise fail(f"SamplerConstants.{name}", arr, "must be finite and at most "
                               f"{_MAX32:.4g} in magnitude for precision 'float32'")
            raise fail("SamplerConstants.guard_band", self.guard_band,
                       f"must be at most {_MAX32:.4g} for precision 'float32'")
        self.__dict__["_float32_ok"] = True  # checked once per (immutable) instance

    def kernel_consts(self) -> dict[str, np.ndarray]:
        """The kernels' const inputs by name (a new dict of read-only arrays, built once per
        instance: the constants are immutable, and kernels reuse the C pointers of arrays they
        saw before)."""
        cached = self.__dict__.get("_kernel_consts")
        if cached is None:
            cached = {"sigma": self.sigma, "lr": [self.lam * (1.0 - self.nu_mix)],
                      "u_min": self.u_min, "u_max": self.u_max, "crash": [self.crash_cost],
                      "p": self.p, "alpha": [self.alpha], "clip_cost": [float(self.clip_in_cost)],
                      "scene": self.scene, "guard": [float(self.guard_band)]}
            sig = np.asarray(self.sigma, dtype=float)
            cached["inv_var"] = 1.0 / (sig * sig)
            cached = {k: np.array(v, dtype=float) for k, v in cached.items()}  # copies
            for a in cached.values():
                a.flags.writeable = False
            self.__dict__["_kernel_consts"] = cached
        return dict(cached)

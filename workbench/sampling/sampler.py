"""One interface over the compiled kernels and the NumPy twin.

Every call takes an explicit seed drawn from the caller's ``numpy.random.Generator``. The
compiled backend draws its noise inside the kernel from that seed; the NumPy backend draws it
with ``numpy.random.default_rng(seed)`` (the two backends therefore differ in noise, not in
algorithm; tests feed both the same noise). Sample outputs are lane-major: v (T, nu, N).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from workbench.sampling.constants import SamplerConstants
from workbench.sampling.kernels import sampler_library
from workbench.sampling.problem import SamplingProblem
from workbench.sampling.reference import mppi_reference, sais_reference
from workbench.validation import fail, one_of

Backend = Literal["auto", "compiled", "numpy"]


@dataclass(frozen=True)
class MPPIBatch:
    S: np.ndarray  # (N,)
    crashed: np.ndarray  # (N,) bool
    v: np.ndarray  # (T, nu, N) applied (clipped) sample controls


@dataclass(frozen=True)
class SAISBatch:
    S_nom: np.ndarray
    S_real: np.ndarray
    S_state_nom: np.ndarray
    S_hat: np.ndarray
    LR: np.ndarray
    crashed_real: np.ndarray
    crashed_nom: np.ndarray
    v_nom: np.ndarray  # (T, nu, N)
    v_real: np.ndarray  # (T, nu, N)


class Sampler:
    """MPPI, SAIS and candidate batches for one sampling problem."""

    def __init__(self, sp: SamplingProblem, backend: Backend = "auto"):
        one_of("backend", backend, ("auto", "compiled", "numpy"))
        self.sp = sp
        self.lib = None if backend == "numpy" else sampler_library(sp)
        if backend == "compiled" and self.lib is None:
            raise fail("backend", backend, "no C compiler is available; use 'numpy' or 'auto'")
        self.backend = "compiled" if self.lib is not None else "numpy"

    def _noise(self, N: int, T: int, seed: int) -> np.ndarray:
        return np.random.default_rng(seed).standard_normal((N, T, self.sp.nu))

    def mppi(self, x0, U, N: int, c: SamplerConstants, seed: int) -> MPPIBatch:
        T = U.shape[0]
        if self.lib is not None:
            carry = np.zeros((N, self.sp.nx + 2))
            carry[:, : self.sp.nx] = x0
            out = self.lib.mppi(carry, consts=c.kernel_consts(), time_in={"u": U}, seed=seed)
            return MPPIBatch(out.result[:, 0], out.result[:, 1] > 0, out.lane_out[0])
        ref = mppi_reference(self.sp, np.tile(x0, (N, 1)), U, self._noise(N, T, seed), c)
        return MPPIBatch(ref["S"], ref["crashed"], np.transpose(ref["v"], (1, 2, 0)))

    def sais(self, x0, xs0, U, K, N: int, c: SamplerConstants, seed: int) -> SAISBatch:
        T, nx = U.shape[0], self.sp.nx
        if self.lib is not None:
            carry = np.zeros((N, 2 * nx + 6))
            carry[:, :nx], carry[:, nx : 2 * nx] = x0, xs0
            out = self.lib.sais(carry, consts=c.kernel_consts(),
                                time_in={"u": U, "K": K.reshape(T, -1)}, seed=seed)
            r = out.result
            return SAISBatch(r[:, 0], r[:, 1], r[:, 2], r[:, 3], r[:, 4], r[:, 5] > 0,
                             r[:, 6] > 0, out.lane_out[0], out.lane_out[1])
        ref = sais_reference(self.sp, np.tile(x0, (N, 1)), np.tile(xs0, (N, 1)), U, K,
                             self._noise(N, T, seed), c)
        return SAISBatch(ref["S_nom"], ref["S_real"], ref["S_state_nom"], ref["S_hat"],
                         ref["LR"], ref["crashed_real"], ref["crashed_nom"],
                         np.transpose(ref["v_nom"], (1, 2, 0)),
                         np.transpose(ref["v_real"], (1, 2, 0)))

    def candidates(self, starts, U, stride, c: SamplerConstants, seed: int) -> np.ndarray:
        """Costs (N,) of rollouts from per-sample starts (N, nx) following U shifted by the
        per-sample stride s in {0, 1} (u_{min(t+s, T-1)}), with no noise for t < s."""
        N, T = starts.shape[0], U.shape[0]
        stride = np.asarray(stride, dtype=float)
        if np.any((stride != 0) & (stride != 1)):
            raise fail("stride", stride, "candidate strides must be 0 or 1")
        U_next = np.vstack([U[1:], U[-1:]])
        if self.lib is not None:
            carry = np.column_stack([starts, np.zeros((N, 2)), stride, stride])
            out = self.lib.candidates(carry, consts=c.kernel_consts(),
                                      time_in={"u": U, "u_next": U_next}, seed=seed)
            return out.result[:, 0]
        U_lane = np.where(stride[:, None, None] > 0, U_next[None], U[None])
        return mppi_reference(self.sp, starts, U_lane, self._noise(N, T, seed), c,
                              delay=stride)["S"]

"""One interface over the compiled kernels and the NumPy twin.

Every call takes an explicit seed drawn from the caller's ``numpy.random.Generator``. The
compiled backend draws its noise inside the kernel from that seed; the NumPy backend draws it
with ``numpy.random.default_rng(seed)`` (the two backends therefore differ in noise, not in
algorithm; tests feed both the same noise). Sample outputs are lane-major: v (T, nu, N).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from workbench.sampling.kernels.build import sampler_library
from workbench.sampling.kernels.constants import SamplerConstants
from workbench.sampling.kernels.diagnostics import diagnostics_library
from workbench.sampling.kernels.emit import LANES
from workbench.sampling.problem import SamplingProblem
from workbench.sampling.reference import mppi_reference, sais_reference
from workbench.validation import as_array, fail, integer, one_of

Backend = Literal["auto", "compiled", "numpy"]


@dataclass(frozen=True, kw_only=True)
class MPPIBatch:
    S: np.ndarray  # (N,)
    crashed: np.ndarray  # (N,) bool
    v: np.ndarray  # (T, nu, N) applied (clipped) sample controls


@dataclass(frozen=True, kw_only=True)
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


@dataclass(frozen=True, kw_only=True)
class SAISDiagBatch(SAISBatch):
    """A SAIS batch with the diagnostics of SPEC 11.2: both systems' state trajectories
    (T+1, nx, N), k = 0..T (lane-major like v), and the pure state costs
    Sx = sum_{k=1}^T q(x_k) + phi(x_T) (no crash, control or feedback cost), real and nominal."""

    X: np.ndarray  # (T+1, nx, N) real samples (with feedback)
    X_nom: np.ndarray  # (T+1, nx, N) nominal samples
    Sx_real: np.ndarray  # (N,)
    Sx_nom: np.ndarray  # (N,)
    # the call's inputs, so that an independent batch can be drawn (SPEC 11.2, 11.3 T2)
    U: np.ndarray  # (T, nu) importance-sampling sequence
    K: np.ndarray  # (T, nu, nx) feedback gains
    consts: SamplerConstants
    seed: int


class Sampler:
    """MPPI, SAIS and candidate batches for one sampling problem."""

    def __init__(self, sp: SamplingProblem, backend: Backend = "auto"):
        one_of("backend", backend, ("auto", "compiled", "numpy"))
        self.sp = sp
        self.lib = None if backend == "numpy" else sampler_library(sp)
        if backend == "compiled" and self.lib is None:
            raise fail("backend", backend, "no compiled kernels for this problem (no C compiler, "
                       "or an operation the C back end cannot compile: see the warning); use "
                       "'numpy' or 'auto'")
        self.backend = "compiled" if self.lib is not None else "numpy"

    def _noise(self, N: int, T: int, seed: int) -> np.ndarray:
        return np.random.default_rng(seed).standard_normal((N, T, self.sp.nu))

    def _check(self, N: int, U, c: SamplerConstants) -> tuple[np.ndarray, SamplerConstants]:
        return check_batch(self.sp, N, U, c)

    def mppi(self, x0, U, N: int, c: SamplerConstants, seed: int) -> MPPIBatch:
        U, c = self._check(N, U, c)
        x0 = as_array("x0", x0, (self.sp.nx,))
        T = U.shape[0]
        if self.lib is not None:
            k = self.lib.mppi
            out = k(k.carry.pack(N, x=x0), consts=c.kernel_consts(), time_in={"u": U},
                    seed=seed)
            r = k.result.unpack(out.result)
            return MPPIBatch(S=r["S"], crashed=r["crashed"] > 0, v=out.lane_out[0])
        ref = mppi_reference(self.sp, np.tile(x0, (N, 1)), U, self._noise(N, T, seed), c)
        return MPPIBatch(S=ref["S"], crashed=ref["crashed"], v=np.transpose(ref["v"], (1, 2, 0)))

    def sais(self, x0, xs0, U, K, N: int, c: SamplerConstants, seed: int,
             diagnostics: bool = False) -> SAISBatch:
        """SAIS batch (Algorithm 1). ``diagnostics=True`` returns a :class:`SAISDiagBatch`
        (same costs, bitwise, for the same seed; plus trajectories and pure state costs)."""
        U, c = self._check(N, U, c)
        T = U.shape[0]
        K = as_array("K", K, (T, self.sp.nu, self.sp.nx))  # shape and finiteness
        x0, xs0 = as_array("x0", x0, (self.sp.nx,)), as_array("xs0", xs0, (self.sp.nx,))
        if diagnostics:
            return self._sais_diag(x0, xs0, U, K, N, c, seed)
        if self.lib is not None:
            k = self.lib.sais
            out = k(k.carry.pack(N, x=x0, x_nom=xs0), consts=c.kernel_consts(),
                    time_in={"u": U, "K": K.reshape(T, -1)}, seed=seed)
            r = k.result.unpack(out.result)
            return SAISBatch(S_nom=r["S_nom"], S_real=r["S_real"], S_state_nom=r["S_state_nom"],
                             S_hat=r["S_hat"], LR=r["LR"], crashed_real=r["crashed_real"] > 0,
                             crashed_nom=r["crashed_nom"] > 0, v_nom=out.lane_out[0],
                             v_real=out.lane_out[1])
        ref = sais_reference(self.sp, np.tile(x0, (N, 1)), np.tile(xs0, (N, 1)), U, K,
                             self._noise(N, T, seed), c)
        return SAISBatch(S_nom=ref["S_nom"], S_real=ref["S_real"],
                         S_state_nom=ref["S_state_nom"], S_hat=ref["S_hat"], LR=ref["LR"],
                         crashed_real=ref["crashed_real"], crashed_nom=ref["crashed_nom"],
                         v_nom=np.transpose(ref["v_nom"], (1, 2, 0)),
                         v_real=np.transpose(ref["v_real"], (1, 2, 0)))

    def _sais_diag(self, x0, xs0, U, K, N, c, seed) -> SAISDiagBatch:
        T, nx = U.shape[0], self.sp.nx
        lib = diagnostics_library(self.sp) if self.lib is not None else None
        if lib is not None:
            k = lib.sais_diag
            Np = -(-N // LANES) * LANES
            # the kernel writes the post-step states straight into rows 1..T (no copy)
            X, Xs = np.empty((T + 1, nx, Np)), np.empty((T + 1, nx, Np))
            X[0], Xs[0] = x0[:, None], xs0[:, None]
            bufs = [np.empty((T, self.sp.nu, Np)), np.empty((T, self.sp.nu, Np)), X[1:], Xs[1:]]
            out = k(k.carry.pack(N, x=x0, x_nom=xs0), consts=c.kernel_consts(),
                    time_in={"u": U, "K": K.reshape(T, -1)}, seed=seed, lane_out=bufs)
            r = k.result.unpack(out.result)
            X, Xs = X[..., :N], Xs[..., :N]
            return SAISDiagBatch(
                S_nom=r["S_nom"], S_real=r["S_real"], S_state_nom=r["S_state_nom"],
                S_hat=r["S_hat"], LR=r["LR"], crashed_real=r["crashed_real"] > 0,
                crashed_nom=r["crashed_nom"] > 0, v_nom=out.lane_out[0], v_real=out.lane_out[1],
                X=X, X_nom=Xs, Sx_real=r["Sx_real"].copy(), Sx_nom=r["Sx_nom"].copy(), U=U, K=K,
                consts=c, seed=int(seed))
        ref = sais_reference(self.sp, np.tile(x0, (N, 1)), np.tile(xs0, (N, 1)), U, K,
                             self._noise(N, T, seed), c, pure_costs=True)

        def lm(a):
            return np.ascontiguousarray(np.transpose(a, (1, 2, 0)))

        return SAISDiagBatch(
            S_nom=ref["S_nom"], S_real=ref["S_real"], S_state_nom=ref["S_state_nom"],
            S_hat=ref["S_hat"], LR=ref["LR"], crashed_real=ref["crashed_real"],
            crashed_nom=ref["crashed_nom"], v_nom=lm(ref["v_nom"]), v_real=lm(ref["v_real"]),
            X=lm(ref["X"]), X_nom=lm(ref["X_nom"]), Sx_real=ref["Sx_real"], Sx_nom=ref["Sx_nom"],
            U=U, K=K, consts=c, seed=int(seed))

    def candidates(self, starts, U, stride, c: SamplerConstants, seed: int) -> np.ndarray:
        """Costs (N,) of rollouts from per-sample starts (N, nx) following U shifted by the
        per-sample stride s in {0, 1} (u_{min(t+s, T-1)}), with no noise for t < s."""
        starts = np.asarray(starts, dtype=float)
        if starts.ndim != 2 or starts.shape[1] != self.sp.nx:
            raise fail("starts", starts.shape, f"expected (N, {self.sp.nx})")
        N = starts.shape[0]
        U, c = self._check(N, U, c)
        T = U.shape[0]
        stride = as_array("stride", stride, (N,))
        if np.any((stride != 0) & (stride != 1)):
            raise fail("stride", stride, "candidate strides must be 0 or 1")
        U_next = np.vstack([U[1:], U[-1:]])
        if self.lib is not None:
            k = self.lib.candidates
            carry = k.carry.pack(N, x=starts, delay=stride, stride=stride)
            out = k(carry, consts=c.kernel_consts(), time_in={"u": U, "u_next": U_next},
                    seed=seed)
            return k.result.unpack(out.result)["S"]
        U_lane = np.where(stride[:, None, None] > 0, U_next[None], U[None])
        return mppi_reference(self.sp, starts, U_lane, self._noise(N, T, seed), c,
                              delay=stride)["S"]


def check_batch(sp: SamplingProblem, N: int, U,
                c: SamplerConstants) -> tuple[np.ndarray, SamplerConstants]:
    """The validated plan and constants of a batch (any sampler of ``sp``); an empty
    ``c.scene`` means the model's own."""
    integer("N", N, 1)
    U = np.asarray(U, dtype=float)
    if U.ndim != 2 or U.shape[1] != sp.nu or U.shape[0] < 1:
        raise fail("U", U.shape, f"the plan must have shape (T >= 1, {sp.nu})")
    if not np.all(np.isfinite(U)):
        raise fail("U", U, "the plan must be finite")
    for name, val, n in (("sigma", c.sigma, sp.nu), ("u_min", c.u_min, sp.nu),
                         ("u_max", c.u_max, sp.nu), ("p", c.p, sp.n_p)):
        if np.shape(val) != (n,):
            raise fail(f"SamplerConstants.{name}", np.shape(val), f"expected ({n},)")
    ns = sp.model.n_scene
    if np.size(c.scene) == 0 and ns:
        c = replace(c, scene=sp.model.scene_value)
    elif np.shape(c.scene) != (ns,):
        raise fail("SamplerConstants.scene", np.shape(c.scene),
                   f"expected ({ns},) (the model's scene size) or empty (its own scene)")
    return U, c

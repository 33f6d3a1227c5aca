"""One interface over the compiled kernels and the NumPy twin.

Every call takes an explicit seed drawn from the caller's ``numpy.random.Generator``. The
compiled backend draws its noise inside the kernel from that seed; the NumPy backend draws it
with ``numpy.random.default_rng(seed)`` (the two backends therefore differ in noise, not in
algorithm; tests feed both the same noise). Sample outputs are lane-major: v (T, nu, N).

Batches own their arrays: per-sample results are fresh copies; the lane outputs (v) are views of
buffers the kernels reuse for a later batch only once nothing refers to them any more
(:class:`~workbench.sampling.kernels.compiled.OutputPool`), so a batch a caller keeps is never
overwritten, and a dropped one costs no new allocation (a fresh 1.6 MB buffer costs a page fault
per 4 KiB on first write: measured 0.2-1.4 ms per SAIS batch, N = 1024, T = 100).

Precision (``Sampler(sp, precision="float32")``): the rollouts run in float32 kernels (twice
the SIMD lanes) on the float64 kernels' noise rounded to float, with the cost sums in double;
results are returned as float64 and weighted in float64. Where float32 is unsafe:

* **near the crash margin** — the crash test min_i h_i <= eps_h and the barrier 1/h are
  sensitive to rounding when h is small. A sample whose smallest margin comes within
  ``SamplerConstants.guard_band`` (default 2.5e-4, ten times the float32 drift of the margins
  measured on the navigation map) of eps_h at its crash step or before it is recomputed by the
  float64 kernel on its own noise: its costs, crash flags and controls are exactly float64's,
  and every other sample's crash flag and crash step are float64's too. Costs of samples that
  pass close to an obstacle without entering the band keep a relative error of about
  1e-6 / h_min (h_min their smallest margin, m^2: 2e-5 at 0.05); such samples carry large
  barrier costs and little weight. A crashed sample's cost after its crash step is float32's.
* **no crash-free sample** — when every sample (MPPI), every real or every nominal sample
  (SAIS) crashed, the weights compare crashed costs of order beta_max^2, which float32 cannot
  resolve: the whole batch is recomputed in float64 (the same batch a float64 sampler draws).
  Candidate batches skip this (their free energies are only compared with the threshold).
* **large coordinates** — float32 spacing grows with magnitude (0.008 m at 1e5 m, 0.25 m at
  4e6 m). The rollouts run in a local frame whose origin is the start state's position
  (:mod:`workbench.sampling.frame`): positions, the goal's position and the circle centres are
  translated before the float32 kernel runs, so crash decisions do not depend on where the map
  lies. A goal beyond :data:`~workbench.sampling.frame.GOAL_LIMIT32` (1e5 m) from the start
  is refused (float32 cannot tell the samples' costs apart there). A problem that is not
  translation invariant has no such frame; its float32 batches are refused when a start
  position or circle centre exceeds :data:`~workbench.sampling.frame.COORDINATE_LIMIT32`
  (100 m).
* **overflow** — a float32 cost beyond float32's range (3.4e38: large cost weights) is inf;
  every sample with a non-finite float32 result is recomputed by the float64 kernel on its own
  noise (counted in :attr:`GuardCounts.overflowed`), as for the guard band.
* **constants** — sigma^2, lambda and lambda (1 - nu_mix) must be normal float32 numbers and
  every other constant finite in float32 (:meth:`SamplerConstants.check_float32`).

:attr:`Sampler.guard` counts how often the guards acted. Diagnostics batches (``sais(...,
diagnostics=True)``) are always float64. The NumPy backend computes in float64.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from workbench.problem.obstacles import check_slots
from workbench.sampling.frame import (
    FrameConsts,
    LocalFrame,
    check_coordinates,
    check_goal,
    local_frame,
)
from workbench.sampling.kernels.constants import SamplerConstants
from workbench.sampling.kernels.diagnostics import diagnostics_library
from workbench.sampling.kernels.flags import PRECISIONS
from workbench.sampling.kernels.library import SamplerLibrary, sampler_library
from workbench.sampling.kernels.vocabulary import step_times
from workbench.sampling.problem import SamplingProblem
from workbench.sampling.twin import lane_major, mppi_twin, sais_twin
from workbench.validation import as_array, fail, integer, one_of

Backend = Literal["auto", "compiled", "numpy"]
Precision = Literal["float64", "float32"]


@dataclass
class GuardCounts:
    """How often the float32 guards acted (all zero for float64): ``batches`` and ``samples``
    computed by float32 kernels, ``rechecked`` samples recomputed in float64 (near the crash
    margin), ``overflowed`` samples recomputed in float64 because a float32 result was not
    finite (a cost beyond float32's range; a sample can count in both), ``reruns`` whole
    batches recomputed in float64 (no crash-free sample)."""

    batches: int = 0
    samples: int = 0
    rechecked: int = 0
    reruns: int = 0
    overflowed: int = 0

    def fractions(self) -> dict[str, float]:
        """rechecked / samples, overflowed / samples and reruns / batches (0 when nothing
        ran)."""
        n = self.samples
        return {"rechecked": self.rechecked / n if n else 0.0,
                "overflowed": self.overflowed / n if n else 0.0,
                "reruns": self.reruns / self.batches if self.batches else 0.0}


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
    """A SAIS batch with the diagnostics of assumptions §11.2: both systems' state trajectories
    (T+1, nx, N), k = 0..T (lane-major like v), and the pure state costs
    Sx = sum_{k=1}^T q(x_k) + phi(x_T) (no crash, control or feedback cost), real and nominal."""

    X: np.ndarray  # (T+1, nx, N) real samples (with feedback)
    X_nom: np.ndarray  # (T+1, nx, N) nominal samples
    Sx_real: np.ndarray  # (N,)
    Sx_nom: np.ndarray  # (N,)
    # the call's inputs, so that an independent batch can be drawn (assumptions §11.2, 11.3 T2)
    U: np.ndarray  # (T, nu) importance-sampling sequence
    K: np.ndarray  # (T, nu, nx) feedback gains
    consts: SamplerConstants
    seed: int


class Sampler:
    """MPPI, SAIS and candidate batches for one sampling problem.

    ``precision`` ``"float64"`` (default) or ``"float32"`` (module docstring): ``lib`` is the
    float64 library (noise, thread count, guard recomputations), ``lib32`` the float32 one
    (None unless float32 kernels run), ``precision`` the precision that runs, ``frame`` the
    float32 kernels' :class:`~workbench.sampling.frame.LocalFrame` (None for float64, or for a
    problem that is not translation invariant)."""

    def __init__(self, sp: SamplingProblem, backend: Backend = "auto",
                 precision: Precision = "float64"):
        one_of("backend", backend, ("auto", "compiled", "numpy"))
        one_of("precision", precision, PRECISIONS)
        self.sp = sp
        self.lib = None if backend == "numpy" else sampler_library(sp)
        if backend == "compiled" and self.lib is None:
            raise fail("backend", backend, "no compiled kernels for this problem (no C compiler, "
                       "or an operation the C back end cannot compile: see the warning); use "
                       "'numpy' or 'auto'")
        self.backend = "compiled" if self.lib is not None else "numpy"
        self.lib32: SamplerLibrary | None = (
            sampler_library(sp, "float32") if precision == "float32" and self.lib is not None
            else None)
        self.precision: Precision = "float32" if self.lib32 is not None else "float64"
        self.guard = GuardCounts()
        self.frame: LocalFrame | None = local_frame(sp) if self.lib32 is not None else None
        self._frame_consts = FrameConsts(self.frame) if self.frame is not None else None
        self._scene_checked: np.ndarray | None = None  # the last scene check_coordinates passed
        self._filled: tuple[SamplerConstants, SamplerConstants] | None = None

    def _noise(self, N: int, T: int, seed: int) -> np.ndarray:
        return np.random.default_rng(seed).standard_normal((N, T, self.sp.nu))

    def _check(self, N: int, U, c: SamplerConstants) -> tuple[np.ndarray, SamplerConstants]:
        given = c
        last = self._filled
        if last is not None and last[0] is c:
            c = last[1]  # the same constants as last time, the model's scene filled in
        U, c = check_batch(self.sp, N, U, c)
        if self.lib32 is not None:
            c.check_float32()
        self._filled = (given, c)
        return U, c

    def _run(self, name: str, N: int, carry: dict, rows: tuple[str, ...], time_in: dict,
             c: SamplerConstants, seed: int, float32: bool):
        """(results by field, lane outputs) of kernel ``name``: float64, or float32 in the
        local frame with the samples near the crash margin or with a non-finite result
        recomputed in float64 (original frame) on their own noise. ``rows``: the
        carry fields given per sample (N rows; none: every sample starts from the same carry).
        Results are contiguous copies; lane outputs are the kernel's (:class:`~workbench.
        sampling.kernels.compiled.KernelOutput`: never overwritten while referenced)."""
        lib = self.lib
        if lib is None:
            raise RuntimeError(f"kernel {name} run on the numpy backend (no sampler library)")
        k = getattr(lib, name)
        consts = c.kernel_consts()
        if not float32:
            out = k(k.carry.pack(N if rows else 1, **carry), n=N, consts=consts,
                    time_in=time_in, seed=seed)
            return {f: np.array(v) for f, v in k.result.unpack(out.result).items()}, out.lane_out
        k32 = getattr(self.lib32, name)
        frame, shift = self.frame, self._frame_consts
        if frame is None or shift is None:
            scene = consts["scene"]  # (the same array for the same constants: checked once)
            check_coordinates(self.sp, carry, None if scene is self._scene_checked else scene)
            self._scene_checked = scene
            carry32, consts32 = carry, consts
        else:
            o = frame.origin(carry)
            carry32, consts32 = frame.carry(carry, o), shift(consts, o)
            check_goal(frame, consts32)
        out = k32(k32.carry.pack(N if rows else 1, **carry32), n=N, consts=consts32,
                  time_in=time_in, seed=seed)
        res = out.result  # (N, fields), float64: the rechecked rows are written into it
        fields = k32.result.unpack(res)  # views: they show the rows written below
        # a finite sum means every entry is finite (an inf or a NaN makes it inf or NaN); a sum
        # that overflows only sends the batch to the entry by entry check
        bad = None if np.isfinite(res.sum()) else ~np.isfinite(res).all(axis=1)
        near = fields["guard"] > 0
        idx = np.flatnonzero(near if bad is None else near | bad)
        g = self.guard
        g.batches, g.samples = g.batches + 1, g.samples + N
        g.rechecked += int(near.sum())
        g.overflowed += 0 if bad is None else int(bad.sum())
        if idx.size:
            T = next(iter(time_in.values())).shape[0]
            z = lib.normals_at(idx, T, k.spec.n_noise, seed)
            sub = {f: (np.asarray(v)[idx] if f in rows else v) for f, v in carry.items()}
            o = k(k.carry.pack(idx.size if rows else 1, **sub), n=idx.size, consts=consts,
                  time_in=time_in, noise=z)
            res[idx, :o.result.shape[1]] = o.result  # the float32 layout adds "guard" last
            for mine, theirs in zip(out.lane_out, o.lane_out, strict=True):
                mine[..., idx] = theirs
        return {f: np.array(v) for f, v in fields.items()}, out.lane_out

    def _rerun(self) -> None:
        self.guard.reruns += 1

    def mppi(self, x0, U, N: int, c: SamplerConstants, seed: int) -> MPPIBatch:
        U, c = self._check(N, U, c)
        x0 = as_array("x0", x0, (self.sp.nx,))
        T = U.shape[0]
        if self.lib is not None:
            f32 = self.lib32 is not None
            ts = step_times(self.sp, T)
            r, lane = self._run("mppi", N, {"x": x0}, (), {"u": U, **ts}, c, seed, f32)
            if f32 and np.all(r["crashed"] > 0):  # no crash-free sample: float64's batch
                self._rerun()
                r, lane = self._run("mppi", N, {"x": x0}, (), {"u": U, **ts}, c, seed, False)
            return MPPIBatch(S=r["S"], crashed=r["crashed"] > 0, v=lane[0])
        ref = mppi_twin(self.sp, np.tile(x0, (N, 1)), U, self._noise(N, T, seed), c)
        return MPPIBatch(S=ref["S"], crashed=ref["crashed"], v=lane_major(ref["v"]))

    def sais(self, x0, xs0, U, K, N: int, c: SamplerConstants, seed: int,
             diagnostics: bool = False) -> SAISBatch:
        """SAIS batch (Algorithm 1). ``diagnostics=True`` returns a :class:`SAISDiagBatch`
        (same costs, bitwise, for the same seed as a float64 sampler; plus trajectories and
        pure state costs; always computed in float64)."""
        U, c = self._check(N, U, c)
        T = U.shape[0]
        K = as_array("K", K, (T, self.sp.nu, self.sp.nx))  # shape and finiteness
        x0, xs0 = as_array("x0", x0, (self.sp.nx,)), as_array("xs0", xs0, (self.sp.nx,))
        if diagnostics:
            return self._sais_diag(x0, xs0, U, K, N, c, seed)
        if self.lib is not None:
            f32 = self.lib32 is not None
            args = ("sais", N, {"x": x0, "x_nom": xs0}, (), {"u": U, "K": K.reshape(T, -1),
                                                    **step_times(self.sp, T)}, c, seed)
            r, lane = self._run(*args, f32)
            if f32 and (np.all(r["crashed_real"] > 0) or np.all(r["crashed_nom"] > 0)):
                self._rerun()  # no crash-free real (or nominal) sample: float64's batch
                r, lane = self._run(*args, False)
            return SAISBatch(S_nom=r["S_nom"], S_real=r["S_real"], S_state_nom=r["S_state_nom"],
                             S_hat=r["S_hat"], LR=r["LR"], crashed_real=r["crashed_real"] > 0,
                             crashed_nom=r["crashed_nom"] > 0, v_nom=lane[0], v_real=lane[1])
        ref = sais_twin(self.sp, np.tile(x0, (N, 1)), np.tile(xs0, (N, 1)), U, K,
                        self._noise(N, T, seed), c)
        return SAISBatch(S_nom=ref["S_nom"], S_real=ref["S_real"],
                         S_state_nom=ref["S_state_nom"], S_hat=ref["S_hat"], LR=ref["LR"],
                         crashed_real=ref["crashed_real"], crashed_nom=ref["crashed_nom"],
                         v_nom=lane_major(ref["v_nom"]),
                         v_real=lane_major(ref["v_real"]))

    def _sais_diag(self, x0, xs0, U, K, N, c, seed) -> SAISDiagBatch:
        T, nx = U.shape[0], self.sp.nx
        lib = diagnostics_library(self.sp) if self.lib is not None else None
        if lib is not None:
            k = lib.sais_diag
            Np = -(-N // k.spec.lanes) * k.spec.lanes
            # the kernel writes the post-step states straight into rows 1..T (no copy)
            X, Xs = np.empty((T + 1, nx, Np)), np.empty((T + 1, nx, Np))
            X[0], Xs[0] = x0[:, None], xs0[:, None]
            bufs = [np.empty((T, self.sp.nu, Np)), np.empty((T, self.sp.nu, Np)), X[1:], Xs[1:]]
            out = k(k.carry.pack(N, x=x0, x_nom=xs0), consts=c.kernel_consts(),
                    time_in={"u": U, "K": K.reshape(T, -1), **step_times(self.sp, T)},
                    seed=seed, lane_out=bufs)
            r = k.result.unpack(out.result)
            X, Xs = X[..., :N], Xs[..., :N]
            return SAISDiagBatch(
                S_nom=r["S_nom"], S_real=r["S_real"], S_state_nom=r["S_state_nom"],
                S_hat=r["S_hat"], LR=r["LR"], crashed_real=r["crashed_real"] > 0,
                crashed_nom=r["crashed_nom"] > 0, v_nom=out.lane_out[0], v_real=out.lane_out[1],
                X=X, X_nom=Xs, Sx_real=r["Sx_real"].copy(), Sx_nom=r["Sx_nom"].copy(), U=U, K=K,
                consts=c, seed=int(seed))
        ref = sais_twin(self.sp, np.tile(x0, (N, 1)), np.tile(xs0, (N, 1)), U, K,
                        self._noise(N, T, seed), c, pure_costs=True)

        def lm(a):
            return np.ascontiguousarray(lane_major(a))

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
            # float32: no whole-batch rerun (candidate free energies are only compared with
            # the threshold; a candidate whose samples all crash is refused in both precisions)
            r, _ = self._run("candidates", N, {"x": starts, "delay": stride, "stride": stride},
                             ("x", "delay", "stride"),
                             {"u": U, "u_next": U_next, **step_times(self.sp, T)}, c, seed,
                             self.lib32 is not None)
            return r["S"]
        U_lane = np.where(stride[:, None, None] > 0, U_next[None], U[None])
        return mppi_twin(self.sp, starts, U_lane, self._noise(N, T, seed), c,
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
    elif ns and not c.__dict__.get("_scene_ok"):  # checked once per (immutable) instance
        s = as_array("SamplerConstants.scene", c.scene, (ns,))
        if sp.model.scene_capacity:
            check_slots("SamplerConstants.scene", s)
        elif sp.model.scene_layout is not None:
            sp.model.scene_layout.check("SamplerConstants.scene", s)
        c.__dict__["_scene_ok"] = True
    return U, c

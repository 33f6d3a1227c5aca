"""Generated sampler kernels: MPPI rollouts, the SAIS dual rollout of
Algorithm 1 and the RMPPI candidate evaluation, emitted by :mod:`workbench.sampling.kernels.emit`.

Run-time constants (``const`` role, shared by all samples):
  sigma (nu) sampling std, lr (1) = lambda (1 - nu_mix), u_min, u_max (nu), crash (1) =
  C_crash, p (n_p) cost parameters, scene (n_scene, when the model has a run-time scene) the
  obstacles, alpha (1) the RMPPI threshold and inv_var (nu) = 1 / sigma^2 (SAIS only: its
  likelihood-ratio terms multiply by it instead of dividing by sigma^2 per sample, four
  divisions fewer per sample and step, measured 5% of the navigation SAIS rollout).
Per-time inputs: u (nu) the importance-sampling sequence; SAIS also K (nu*nx, row-major K_k).
Carries and results are named by :func:`layouts` (one :class:`Layout` per kernel and role).

Float32 kernels (``precision="float32"``, their own library ``sampler_<model>_f32``) compute the
same rollouts in float with the cost sums in double (:mod:`.emit`: a step's cost is formed in
float and added to a double sum; 0/1 crash flags are exact in float), and add a
per-sample ``guard`` flag and the const input ``guard`` (the band g): the flag is 1 when, at its
crash step or before it (a system that has not crashed yet), the smallest margin lies within g
of the crash margin, |min_i h_i - eps_h| <= g, where the float crash decision may differ from
the double one; :class:`~workbench.sampling.sampler.Sampler` recomputes those samples in
double. Outside the band, float and double decide every step's crash test alike whenever their
margins differ by less than g, so crash flags and crash steps agree.
"""

from __future__ import annotations

import ctypes
import sys
import threading
import warnings
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from typing import TypeVar

import casadi as ca
import numpy as np

import workbench.sampling.kernels.slots as slots
import workbench.sampling.kernels.threads as threads
from workbench.codegen import CompileError, build_library
from workbench.sampling.kernels.emit import (  # noqa: F401  (LANES: re-exported)
    LANES,
    PRECISIONS,
    EmitError,
    KernelSpec,
    emit_kernel,
    lane_count,
    rng_source,
)
from workbench.sampling.kernels.layout import Layout
from workbench.sampling.kernels.vector_math import prelude
from workbench.sampling.kernels.verify import KernelMismatch, verify_kernel
from workbench.sampling.kernels.vocabulary import (
    clip,
    crashed_flag,
    kernel_symbols,
    model_parts,
    near_crash_flag,
)
from workbench.sampling.problem import SamplingProblem
from workbench.validation import fail

L = TypeVar("L")

_OPTS = {"cse": True}
# -fsched-pressure -fschedule-insns: register-pressure-aware scheduling of the long
# straight-line step; measured 1.5x faster (fewer spills), results unchanged (no FP reordering).
# -fno-math-errno: libm calls do not set errno (results unchanged), so gcc may call the SIMD
# variants of the trigonometric functions inside the lane loop (vector_math.py);
# -fno-builtin-sin/cos: else gcc merges sin(a) and cos(a) into one sincos call, which it cannot
# vectorise (every heading-driven model has both).
KERNEL_FLAGS = ("-fopenmp", "-march=native", "-fsched-pressure", "-fschedule-insns",
                "-fno-math-errno", "-fno-builtin-sin", "-fno-builtin-cos")
KERNEL_FLAGS_F32 = ("-fno-builtin-sinf", "-fno-builtin-cosf")  # added for float32 kernels


def _f32(precision: str) -> bool:
    if precision not in PRECISIONS:
        raise fail("precision", precision, f"allowed values are {PRECISIONS}")
    return precision == "float32"


def layouts(sp: SamplingProblem, kernel: str,
            precision: str = "float64") -> tuple[Layout, Layout]:
    """(carry, result) layouts of a kernel ("mppi", "sais" or "candidates"); the specs below
    index their carries in this order. Float32 kernels add a ``guard`` field to both."""
    nx = sp.nx
    if kernel == "sais":
        carry = (("x", nx), ("x_nom", nx), ("S_state_nom", 1), ("S_hat", 1), ("S_real", 1),
                 ("LR", 1), ("crashed_real", 1), ("crashed_nom", 1))
        result = (("S_nom", 1), ("S_real", 1), ("S_state_nom", 1), ("S_hat", 1), ("LR", 1),
                  ("crashed_real", 1), ("crashed_nom", 1))
    else:
        carry = (("x", nx), ("S", 1), ("crashed", 1))
        if kernel == "candidates":
            carry += (("delay", 1), ("stride", 1))
        result = (("S", 1), ("crashed", 1))
    if _f32(precision):
        carry, result = (*carry, ("guard", 1)), (*result, ("guard", 1))
    tag = " (float32)" if precision == "float32" else ""
    return (Layout(name=f"{kernel} carry{tag}", fields=carry),
            Layout(name=f"{kernel} result{tag}", fields=result))


def mppi_spec(sp: SamplingProblem, name: str = "wb_mppi", strided: bool = False,
              precision: str = "float64") -> KernelSpec:
    """MPPI rollout (assumptions §8.1 with the crash rule of 4.6).

    ``strided`` (RMPPI candidates, assumptions §9.3) adds per-sample ``delay`` and ``stride`` s in
    {0, 1} as carry entries after the crash flag: the sample follows u_{min(t+s, T-1)} (time
    input ``u_next`` holds the shifted sequence) and draws no noise while delay > 0. A float32
    kernel (named ``<name>_f32``) ends its carry with the guard flag.
    """
    nx, nu, nh = sp.nx, sp.nu, sp.model.nh
    f32 = _f32(precision)
    c = kernel_symbols(sp)
    if f32:
        c["guard"] = ca.SX.sym("guard")
    dyn, margins, q, phi = model_parts(sp, c)
    carry = ca.SX.sym("carry", nx + 2 + 2 * int(strided) + int(f32))
    z, u_in, u_next = ca.SX.sym("z", nu), ca.SX.sym("u", nu), ca.SX.sym("u_next", nu)
    x, S, cr = carry[:nx], carry[nx], carry[nx + 1]
    noise, u = c["sigma"] * z, u_in
    if strided:
        delay, stride = carry[nx + 2], carry[nx + 3]
        # arithmetic blends, exact for 0/1 weights: a select here makes gcc turn the time-input
        # loads into masked loads, which stops it vectorising the lane loop
        noise = noise * (delay <= 0)
        u = (1.0 - stride) * u_in + stride * u_next
    v = clip(u + noise, c["u_min"], c["u_max"])
    eps = v - u
    xn = dyn(x, v)
    crn = ca.fmax(cr, crashed_flag(margins, xn, sp.eps_h, nh))
    inv = 1.0 / (c["sigma"] * c["sigma"])
    lr = 0.5 * c["lr"] * (ca.dot(u * inv, u) + 2.0 * ca.dot(u * inv, eps))
    Sn = S + (q(xn, c["p"]) + c["crash"][0] * crn) + lr
    ins = {"carry": carry, "z": z, "u": u_in, **({"u_next": u_next} if strided else {}), **c}
    new = [xn, Sn, crn] + ([carry[nx + 2] - 1, carry[nx + 3]] if strided else [])
    res = [S + phi(x, c["p"]), cr]
    if f32:
        g = carry[carry.numel() - 1]
        # the crash step and the steps before it (a crashed sample's flag no longer changes)
        near = near_crash_flag(margins, xn, sp.eps_h, nh, c["guard"])
        new.append(ca.fmax(g, (1.0 - cr) * near))
        res.append(g)
        name += "_f32"
    step = ca.Function(name + "_step", list(ins.values()), [ca.vertcat(*new), v],
                       list(ins), ["carry_next", "v"], _OPTS)
    final = ca.Function(name + "_final", [carry, c["p"]],
                        [ca.vertcat(*res)], ["carry", "p"], ["result"], _OPTS)
    roles = {"carry": "carry", "z": "noise", "u": "time", "u_next": "time",
             **{k: "const" for k in c}}
    return KernelSpec(name=name, step=step, final=final, roles=roles, precision=precision,
                      wide=(nx,) if f32 else ())  # the cost sum


def candidate_spec(sp: SamplingProblem, precision: str = "float64") -> KernelSpec:
    """RMPPI candidate evaluation (assumptions §9.3): strided MPPI rollouts, no feedback."""
    return mppi_spec(sp, "wb_candidates", strided=True, precision=precision)


def sais_spec(sp: SamplingProblem, name: str = "wb_sais", precision: str = "float64") -> KernelSpec:
    """The SAIS dual rollout of Algorithm 1 (assumptions §10.1); clip_in_cost is a run-time input. A
    float32 kernel (``<name>_f32``) ends its carry with the guard flag of both systems."""
    nx, nu, nh = sp.nx, sp.nu, sp.model.nh
    f32 = _f32(precision)
    c = kernel_symbols(sp)
    if f32:
        c["guard"] = ca.SX.sym("guard")
    c["inv_var"] = ca.SX.sym("inv_var", nu)  # 1 / sigma^2, computed once per batch
    dyn, margins, q, phi = model_parts(sp, c)
    alpha, clip_cost = ca.SX.sym("alpha"), ca.SX.sym("clip_cost")
    carry = ca.SX.sym("carry", 2 * nx + 6 + int(f32))
    z, u, Kv = ca.SX.sym("z", nu), ca.SX.sym("u", nu), ca.SX.sym("K", nu * nx)
    x, xs = carry[:nx], carry[nx : 2 * nx]
    Sn, Sh, Sr, LR, cr, cn = (carry[2 * nx + i] for i in range(6))
    K = ca.reshape(Kv, nx, nu).T
    eps = c["sigma"] * z
    kfb = ca.mtimes(K, x - xs)
    vr = clip(u + eps + kfb, c["u_min"], c["u_max"])
    vn = clip(u + eps, c["u_min"], c["u_max"])
    # clip_in_cost (assumptions §10.1): effective (clipped) noise and feedback in lines 8, 9 and 12
    # when 1, the raw ones when 0 (exact 0/1 blends)
    et = clip_cost * (vn - u) + (1.0 - clip_cost) * eps
    kt = clip_cost * (vr - u - (vn - u)) + (1.0 - clip_cost) * kfb
    xn, xsn = dyn(x, vr), dyn(xs, vn)
    crn = ca.fmax(cr, crashed_flag(margins, xn, sp.eps_h, nh))
    cnn = ca.fmax(cn, crashed_flag(margins, xsn, sp.eps_h, nh))
    qr = q(xn, c["p"]) + c["crash"][0] * crn
    qn = q(xsn, c["p"]) + c["crash"][0] * cnn
    inv = c["inv_var"]  # a product with 1 / (sigma sigma) would become a division in CasADi
    half = 0.5 * c["lr"]
    Sh = Sh + (qr + half * ca.dot(kt * inv, kt))
    Sn = Sn + qn
    Sr = Sr + (qr + half * ca.dot((u + kt) * inv, u + 2.0 * et + kt))
    LR = LR + half * (ca.dot(u * inv, u) + 2.0 * ca.dot(u * inv, et))
    ins = {"carry": carry, "z": z, "u": u, "K": Kv, **c, "alpha": alpha, "clip_cost": clip_cost}
    new = [xn, xsn, Sn, Sh, Sr, LR, crn, cnn]
    fx, fxs = phi(x, c["p"]), phi(xs, c["p"])
    Shf, Snf, Srf = carry[2 * nx + 1] + fx, carry[2 * nx] + fxs, carry[2 * nx + 2] + fx
    S_nom = 0.5 * Snf + 0.5 * ca.fmax(ca.fmin(Shf, alpha), Snf) + carry[2 * nx + 3]
    res = [S_nom, Srf, Snf, Shf, carry[2 * nx + 3], carry[2 * nx + 4], carry[2 * nx + 5]]
    if f32:
        g = carry[2 * nx + 6]
        near = ca.fmax((1.0 - cr) * near_crash_flag(margins, xn, sp.eps_h, nh, c["guard"]),
                       (1.0 - cn) * near_crash_flag(margins, xsn, sp.eps_h, nh, c["guard"]))
        new.append(ca.fmax(g, near))
        res.append(g)
        name += "_f32"
    step = ca.Function(name + "_step", list(ins.values()),
                       [ca.vertcat(*new), vn, vr],
                       list(ins), ["carry_next", "v_nom", "v_real"], _OPTS)
    final = ca.Function(name + "_final", [carry, c["p"], alpha],
                        [ca.vertcat(*res)], ["carry", "p", "alpha"], ["result"], _OPTS)
    roles = {"carry": "carry", "z": "noise", "u": "time", "K": "time", "alpha": "const",
             "clip_cost": "const",
             **{k: "const" for k in c}}
    return KernelSpec(name=name, step=step, final=final, roles=roles, precision=precision,
                      wide=tuple(range(2 * nx, 2 * nx + 4)) if f32 else ())  # cost sums


@dataclass(frozen=True, eq=False)
class KernelOutput:
    """Kernel outputs; lane outputs are (T, m, N) views, results (N, nr), noise (T, nz, N).

    They are views of buffers the kernel reuses for a later call only once nothing refers to
    them any more (:class:`OutputPool`): an output stays valid as long as the caller keeps it
    (or any view of it)."""

    lane_out: list[np.ndarray]
    result: np.ndarray
    noise: np.ndarray | None


def _addr(a: np.ndarray) -> int:
    try:  # 3x faster than the array interface (kernel calls pass a dozen arrays)
        return ctypes.addressof(ctypes.c_char.from_buffer(a))
    except (TypeError, ValueError):  # read-only or empty
        return a.__array_interface__["data"][0]


def _empty(shape: tuple[int, ...]) -> np.ndarray:
    """np.empty aligned to 64 bytes (a cache line, one AVX-512 vector), so the kernels' blocks
    of samples start on vector boundaries (measured up to 5% faster than 32-byte offsets). A
    view: its ``base`` owns the memory, and every view of it refers to that owner."""
    n = int(np.prod(shape))
    raw = np.empty(n + 8)
    start = (-raw.__array_interface__["data"][0] % 64) // 8
    return raw[start:start + n].reshape(shape)


def _refs(group: tuple[np.ndarray, ...]) -> list[int]:
    """References to the memory owners of a group of :func:`_empty` arrays (NumPy points every
    view, of a view too, at the owner)."""
    return [sys.getrefcount(a.base) for a in group]


# the count of an owner referred to by its pool array only, measured with the same code (not
# assumed, so that a Python version counting differently stays safe)
_ALONE = _refs((_empty((1,)),))[0]


class OutputPool:
    """Output buffers of one call shape, reused once nothing outside the pool refers to them.

    A kernel call writes megabytes of lane outputs; freshly allocated, they cost a page fault
    per 4 KiB on first write (measured 0.2-1.4 ms for the two SAIS lane outputs, N = 1024,
    T = 100), reused, none. :meth:`get` hands out a group of buffers only when CPython's
    reference counts show that no array returned earlier (nor any view of one) is still alive,
    so a caller never sees its outputs overwritten; otherwise it allocates a new group (and
    forgets the oldest when it holds ``size``)."""

    def __init__(self, make: Callable[[], tuple[np.ndarray, ...]], size: int = 3):
        """``make()``: a new group of :func:`_empty` arrays (only views of them are handed
        out, never the arrays themselves)."""
        self._make, self._size = make, size
        self._groups: list[tuple[np.ndarray, ...]] = []

    def get(self) -> tuple[np.ndarray, ...]:
        for g in self._groups:
            if all(n == _ALONE for n in _refs(g)):
                return g
        g = self._make()
        self._groups.append(g)
        if len(self._groups) > self._size:
            self._groups.pop(0)
        return g


class _Plan:
    """What a kernel call of one shape (padded N, T, noise mode) reuses: the padded carry
    buffer, the C pointer arrays and the output pool."""

    def __init__(self, spec: KernelSpec, Np: int, T: int, nz_out: bool, own_out: bool):
        def arr(n: int):
            return (ctypes.c_void_p * max(1, n))()

        self.carry = _empty((Np, spec.n_carry))
        self.carry_p = _addr(self.carry)
        self.lane_p, self.time_p = arr(len(spec.inputs("lane"))), arr(len(spec.inputs("time")))
        self.const_p, self.out_p = arr(len(spec.inputs("const"))), arr(len(spec.lane_out_sizes()))
        # the caller's const arrays const_p was set for, and the arrays it points to (alive)
        self.consts: list[np.ndarray] = []
        self.const_keep: list[np.ndarray] = []
        sizes = spec.lane_out_sizes() if own_out else []
        nz = spec.n_noise
        self.n_out = len(sizes)

        def make() -> tuple[np.ndarray, ...]:
            outs = tuple(_empty((T, m, Np)) for m in sizes)
            noise = (_empty((T, nz, Np)),) if nz_out else ()
            return (*outs, _empty((Np, spec.n_result)), *noise)

        self.pool = OutputPool(make)


_PLANS_MAX = 8  # call shapes remembered per kernel (and calling thread)


class CompiledKernel:
    """A loaded kernel: call with arrays, get :class:`KernelOutput`."""

    def __init__(self, spec: KernelSpec, cdll: ctypes.CDLL, carry: Layout | None = None,
                 result: Layout | None = None):
        carry = carry or Layout(name=f"{spec.name} carry", fields=(("carry", spec.n_carry),))
        result = result or Layout(name=f"{spec.name} result",
                                  fields=(("result", spec.n_result),))
        if (carry.size, result.size) != (spec.n_carry, spec.n_result):
            raise ValueError(f"{spec.name}: layouts ({carry.size}, {result.size}) do not match "
                             f"the kernel ({spec.n_carry}, {spec.n_result})")
        self.spec, self.carry, self.result = spec, carry, result
        self._fn = getattr(cdll, spec.name)
        self._fn.restype = None
        self._fn.argtypes = [ctypes.c_int, ctypes.c_int] + [ctypes.c_void_p] * 7 + [
            ctypes.c_int, ctypes.c_ulonglong]
        st = spec.step
        self._sizes = {n: st.numel_in(i) for i, n in enumerate(st.name_in())}
        self._set_threads = cdll.wb_set_threads
        self._set_threads.argtypes = [ctypes.c_int]
        self._lanes = spec.lanes
        self._names = {r: spec.inputs(r) for r in ("lane", "time", "const")}
        self._plans: dict[tuple, _Plan] = {}

    def _plan(self, Np: int, T: int, nz_out: bool, own_out: bool) -> _Plan:
        # per calling thread: buffers are never shared between threads
        key = (threading.get_ident(), Np, T, nz_out, own_out)
        plan = self._plans.pop(key, None)  # re-inserted last: least recently used goes first
        if plan is None:
            if len(self._plans) >= _PLANS_MAX:
                self._plans.pop(next(iter(self._plans)))
            plan = _Plan(self.spec, Np, T, nz_out, own_out)
        self._plans[key] = plan
        return plan

    def _set_consts(self, plan: _Plan, consts: dict[str, np.ndarray]) -> None:
        """Point the plan at the const arrays (checked once per set of arrays)."""
        arrays = [consts[n] for n in self._names["const"]]
        if len(arrays) == len(plan.consts) and all(
                a is b for a, b in zip(arrays, plan.consts, strict=True)):
            return
        spec, kept = self.spec, []
        for j, (n, a) in enumerate(zip(self._names["const"], arrays, strict=True)):
            c = np.ascontiguousarray(a, dtype=float)
            if c.size != self._sizes[n]:  # the kernel reads exactly this many values
                raise ValueError(f"{spec.name}: const input {n!r} has {c.size} values, the "
                                 f"kernel reads {self._sizes[n]}")
            plan.const_p[j] = _addr(c)
            kept.append(c)
        # identity of the caller's arrays when they needed no conversion, else (converted per
        # call) never equal: a converted array is checked again next time
        plan.consts = [a if a is c else c for a, c in zip(arrays, kept, strict=True)]
        plan.const_keep = kept

    def __call__(self, carry0, *, consts: dict[str, np.ndarray], time_in=None, lane_in=None,
                 noise=None, seed: int | None = None, keep_noise: bool = False,
                 lane_out: list[np.ndarray] | None = None, n: int | None = None) -> KernelOutput:
        """carry0 (N, nc), or one row (1, nc) with ``n`` = N: every sample starts from it;
        time_in {name: (T, m)}; lane_in {name: (T, m, N)};
        noise (T, nz, N) standard normals, or seed (draws in the kernel; kept if keep_noise);
        lane_out: optional C-contiguous (T, m, N padded to the lane count) buffers to write the
        lane outputs into (else buffers of an :class:`OutputPool`). Runs on the thread count of
        :func:`~workbench.sampling.kernels.threads.threads_for` (N T sample-steps)."""
        spec = self.spec
        carry0 = np.asarray(carry0, dtype=float)
        if carry0.ndim != 2 or carry0.shape[1] != spec.n_carry:
            raise ValueError(f"{spec.name}: carry0 has shape {carry0.shape}, expected "
                             f"(N, {spec.n_carry})")
        N = carry0.shape[0] if n is None else int(n)
        if N < 1 or carry0.shape[0] not in (1, N):
            raise ValueError(f"{spec.name}: carry0 has {carry0.shape[0]} rows for N = {N} "
                             "samples (give N rows, or one row and n = N)")
        L = self._lanes
        Np = -(-N // L) * L
        time_in, lane_in = time_in or {}, lane_in or {}
        T = (next(iter(time_in.values())).shape[0] if time_in
             else next(iter(lane_in.values())).shape[0])
        nz = spec.n_noise
        gen = seed is not None
        plan = self._plan(Np, T, gen and keep_noise and nz > 0, lane_out is None)
        buf = plan.carry
        buf[:N] = carry0  # one row: broadcast
        if Np != N:
            buf[N:] = carry0[-1]
        self._set_consts(plan, consts)
        keep = []

        def pad(a) -> np.ndarray:
            """Lane-major (..., N) array padded to Np lanes by repeating the last one."""
            a = np.asarray(a, dtype=float)
            if Np != N:
                a = np.concatenate([a, np.repeat(a[..., -1:], Np - N, axis=-1)], axis=-1)
            return np.ascontiguousarray(a)

        for j, name in enumerate(self._names["time"]):
            a = np.ascontiguousarray(time_in[name], dtype=float)
            if a.shape[0] != T or a.size != T * self._sizes[name]:
                raise ValueError(f"{spec.name}: time input {name!r} has shape {a.shape}, "
                                 f"expected ({T}, {self._sizes[name]})")
            keep.append(a)
            plan.time_p[j] = _addr(a)
        for j, name in enumerate(self._names["lane"]):
            a = pad(lane_in[name])
            if a.shape != (T, self._sizes[name], Np):
                raise ValueError(f"{spec.name}: lane input {name!r} has shape "
                                 f"{np.shape(lane_in[name])}, expected "
                                 f"({T}, {self._sizes[name]}, {N})")
            keep.append(a)
            plan.lane_p[j] = _addr(a)
        group = plan.pool.get()
        n_out = plan.n_out
        outs, result = list(group[:n_out]), group[n_out]
        if lane_out is not None:
            outs = list(lane_out)
            want = [(T, m, Np) for m in spec.lane_out_sizes()]
            if [o.shape for o in outs] != want or not all(
                    o.dtype == np.float64 and o.flags.c_contiguous for o in outs):
                raise ValueError(f"{spec.name}: lane_out must be C-contiguous float64 arrays "
                                 f"of shapes {want}")
        for j, o in enumerate(outs):
            plan.out_p[j] = _addr(o)
        if gen:
            noise_buf = group[n_out + 1] if keep_noise and nz else None
        elif noise is not None:
            noise_buf = pad(noise)
            if noise_buf.shape != (T, nz, Np):
                raise ValueError(f"{spec.name}: noise has shape {np.shape(noise)}, expected "
                                 f"({T}, {nz}, {N})")
        elif nz:
            raise ValueError("noise = None is invalid: give a noise buffer or a seed")
        else:
            noise_buf = None
        threads.apply(self._set_threads, Np * T)
        self._fn(Np, T, plan.carry_p, plan.lane_p, plan.time_p, plan.const_p, plan.out_p,
                 _addr(result), _addr(noise_buf) if noise_buf is not None else None, int(gen),
                 int(seed or 0) & (2**64 - 1))
        del keep
        return KernelOutput(
            lane_out=[o[..., :N] for o in outs], result=result[:N],
            noise=noise_buf[..., :N] if noise_buf is not None else None)


@dataclass(frozen=True, eq=False)
class SamplerLibrary:
    """The three kernels of one sampling problem and precision, in one cached shared library."""

    mppi: CompiledKernel
    sais: CompiledKernel
    candidates: CompiledKernel
    cdll: ctypes.CDLL

    @property
    def precision(self) -> str:
        return self.mppi.spec.precision

    def normals(self, N: int, T: int, m: int, seed: int) -> np.ndarray:
        """The standard normals (T, m, N) a kernel draws with the same seed (double; a float32
        kernel computes with them rounded to float)."""
        out = np.empty((T, m, N))
        self.cdll.wb_normals(N, T, m, ctypes.c_ulonglong(int(seed) & (2**64 - 1)),
                             ctypes.c_void_p(_addr(out)))
        return out

    def normals_at(self, index, T: int, m: int, seed: int) -> np.ndarray:
        """The standard normals (T, m, n) of the samples ``index`` (n sample numbers of a
        batch) that a kernel draws with the same seed."""
        idx = np.ascontiguousarray(index, dtype=np.int64)
        out = np.empty((T, m, idx.size))
        self.cdll.wb_normals_at(idx.size, ctypes.c_void_p(_addr(idx)), T, m,
                                ctypes.c_ulonglong(int(seed) & (2**64 - 1)),
                                ctypes.c_void_p(_addr(out)))
        return out

    def set_threads(self, n: int) -> None:
        """:func:`set_threads` (the count applies to every kernel library of the process)."""
        set_threads(n)


_LIBS: dict[str, SamplerLibrary | None] = {}
_FALLBACK_WARNED: set[str] = set()


def set_threads(n: int | str, adaptive: bool = True) -> None:
    """At most ``n`` OpenMP threads per kernel call (``"auto"``: one per core), for every
    kernel library loaded so far (sampler, safe-MPPI, diagnostics) and every one loaded later
    (default: OpenMP's, one per core). With ``adaptive`` (the default) a call runs on 1 thread
    when its batch is small (N T < 8192 sample-steps) or when other processes keep the cores
    busy (the cores they leave free, measured from /proc/stat over the last 0.25 s: on 2 cores,
    others using more than half a core give 1 thread); ``adaptive=False`` uses exactly n.
    Idle threads sleep (OMP_WAIT_POLICY=passive, unless OMP_WAIT_POLICY or GOMP_SPINCOUNT is
    set before the first kernel library loads). Results never depend on the count. Applies to
    kernels called from the calling thread (OpenMP's setting is per thread); study workers
    run with 1. See :mod:`workbench.sampling.kernels.threads`."""
    threads.set_threads(n, adaptive)


def get_threads() -> int | None:
    """The count of the last :func:`set_threads` (None: never set; OpenMP's default)."""
    return threads.get_threads()


def _load(stem: str, source: str, flags: tuple[str, ...], rebuild: bool = False):
    threads.prepare_runtime()  # before the first library loads the OpenMP runtime
    lib = build_library(stem, [], source, extra_flags=flags, rebuild=rebuild)
    if lib is not None:
        lib.cdll.wb_set_threads.argtypes = [ctypes.c_int]
        lib.cdll.wb_get_threads.restype = ctypes.c_int
        threads.register(lib.cdll.wb_set_threads, lib.cdll.wb_get_threads())
    return lib


def load_verified(stem: str, source: str, build: Callable[[ctypes.CDLL], L],
                  kernels: Callable[[L], Iterable[CompiledKernel]],
                  flags: tuple[str, ...] = KERNEL_FLAGS) -> L | None:
    """Compile (or load from the cache) a kernel library, wrap it with ``build(cdll)``, and
    check each of its ``kernels(obj)`` against CasADi's evaluation of its step
    (:mod:`workbench.sampling.kernels.verify`) before first use. A mismatch (e.g. a cached library
    swapped with another problem's) rebuilds it once; a second mismatch raises. None without a
    compiler. Every kernel library (sampler, diagnostics) is loaded through here."""
    lib = _load(stem, source, flags)
    if lib is None:
        return None
    obj = build(lib.cdll)
    try:
        for k in kernels(obj):
            verify_kernel(k)
    except KernelMismatch as exc:
        warnings.warn(f"workbench: {exc}; rebuilding {stem}", RuntimeWarning, stacklevel=3)
        obj = build(_load(stem, source, flags, rebuild=True).cdll)
        for k in kernels(obj):
            verify_kernel(k)
    return obj


def _sampler_library(cdll: ctypes.CDLL, specs, lays) -> SamplerLibrary:
    cdll.wb_normals.restype = None
    cdll.wb_normals.argtypes = [ctypes.c_int] * 3 + [ctypes.c_ulonglong, ctypes.c_void_p]
    cdll.wb_normals_at.restype = None
    cdll.wb_normals_at.argtypes = [ctypes.c_int, ctypes.c_void_p, ctypes.c_int, ctypes.c_int,
                                   ctypes.c_ulonglong, ctypes.c_void_p]
    cdll.wb_set_threads.argtypes = [ctypes.c_int]
    cdll.wb_get_threads.restype = ctypes.c_int
    mppi, sais, candidates = (CompiledKernel(s, cdll, *lay)
                              for s, lay in zip(specs, lays, strict=True))
    return SamplerLibrary(mppi=mppi, sais=sais, candidates=candidates, cdll=cdll)


def kernel_flags(precision: str = "float64") -> tuple[str, ...]:
    """Compiler flags of a kernel library (float32: the float builtins sinf/cosf off too)."""
    return KERNEL_FLAGS + (KERNEL_FLAGS_F32 if _f32(precision) else ())


def kernel_source(specs: list[KernelSpec], vector_math: bool | None = None) -> str:
    """C source of a kernel library: the generator, the SIMD declarations of the trigonometric
    functions the kernels use (:mod:`workbench.sampling.kernels.vector_math`; ``vector_math`` None
    follows WORKBENCH_VECTOR_MATH), the kernels. The kernels share one precision."""
    fns = [f for s in specs for f in (s.step, s.final)]
    precision = specs[0].precision if specs else "float64"
    if any(s.precision != precision for s in specs):
        raise fail("specs", [s.name for s in specs], "kernels of one library share a precision")
    lanes = specs[0].lanes if specs else lane_count(precision)
    if any(s.lanes != lanes for s in specs):
        raise fail("specs", [s.name for s in specs], "kernels of one library share a block "
                   "width (KernelSpec.lanes)")
    return rng_source(lanes) + "\n" + prelude(fns, kernel_flags(precision), lanes, vector_math,
                                               precision) + "\n".join(
        emit_kernel(s) for s in specs)


def library_sources(sp: SamplingProblem, vector_math: bool | None = None,
                    precision: str = "float64", lanes: int | None = None,
                    slot_loop: bool | None = None) -> tuple[str, list[KernelSpec], str]:
    """(cache stem, kernel specs, C source) of a sampling problem's library; ``lanes`` samples
    per block (None: :func:`~workbench.sampling.kernels.emit.lane_count`). ``slot_loop``: emit
    the kernels with a loop over the scene's circle slots (:mod:`~workbench.sampling.kernels.slots`:
    the same results bit for bit, in code whose size does not grow with the number of circles);
    None chooses it when the model has at least ``slots.DEFAULT_MIN_SLOTS`` supported slots,
    True requires it (:class:`~workbench.sampling.kernels.slots.SlotLoopUnsupported` when it
    cannot), False keeps the straight-line kernels."""
    specs = [mppi_spec(sp, precision=precision), sais_spec(sp, precision=precision),
             candidate_spec(sp, precision)]
    if lanes is not None:
        specs = [replace(s, block=int(lanes)) for s in specs]
    tag = "_f32" if _f32(precision) else ""
    stem = f"sampler_{sp.model.name.replace('+', '_')}{tag}"
    if slot_loop is None:
        slot_loop = slots.use_slot_loop(sp, precision)
    if slot_loop:
        return stem + "_loop", specs, slots.slot_kernel_source(sp, specs, vector_math)
    return stem, specs, kernel_source(specs, vector_math)


def load_sampler_library(sp: SamplingProblem, vector_math: bool | None = None,
                         precision: str = "float64", lanes: int | None = None,
                         slot_loop: bool | None = None) -> SamplerLibrary | None:
    """Build (or load from the disk cache) and verify a problem's kernels, bypassing the
    per-process table of :func:`sampler_library` (e.g. to compare scalar and vector libm,
    block widths (``lanes`` samples per block) or loop and straight-line kernels
    (``slot_loop``, see :func:`library_sources`)). When the loop kernels were chosen
    automatically and fail their load-time check, one warning says so and the straight-line
    kernels are used."""
    stem, specs, source = library_sources(sp, vector_math, precision, lanes, slot_loop)
    lays = [layouts(sp, k, precision) for k in ("mppi", "sais", "candidates")]

    def load(stem: str, source: str) -> SamplerLibrary | None:
        return load_verified(stem, source, lambda c: _sampler_library(c, specs, lays),
                             lambda lib: (lib.mppi, lib.sais, lib.candidates),
                             flags=kernel_flags(precision))

    if slot_loop is None and stem.endswith("_loop"):
        try:
            return load(stem, source)
        except KernelMismatch as exc:
            warnings.warn(f"workbench: the loop-over-circles kernels of {sp.model.name} failed "
                          f"their check ({exc}); using the straight-line kernels",
                          RuntimeWarning, stacklevel=2)
            stem, specs, source = library_sources(sp, vector_math, precision, lanes, False)
    return load(stem, source)


def sampler_library(sp: SamplingProblem, precision: str = "float64") -> SamplerLibrary | None:
    """Build (or load from the cache) the kernels of a sampling problem in ``precision``,
    verified; None without a compiler, or, with one warning, when the model uses an operation
    the emitter or the C back end cannot compile (the sampler then uses the NumPy/CasADi twin:
    correct, slower)."""
    key = sp.fingerprint() + ("_f32" if _f32(precision) else "")
    if key not in _LIBS:
        try:
            _LIBS[key] = load_sampler_library(sp, precision=precision)
        except (EmitError, CompileError) as exc:
            if isinstance(exc, CompileError) and "no linked library provides" not in str(exc):
                raise
            if key not in _FALLBACK_WARNED:
                _FALLBACK_WARNED.add(key)
                warnings.warn(f"workbench: no compiled sampler kernels for {sp.model.name}: "
                              f"{str(exc).splitlines()[0]}; using the NumPy/CasADi evaluation "
                              "(correct, slower)", RuntimeWarning, stacklevel=2)
            _LIBS[key] = None
    return _LIBS[key]

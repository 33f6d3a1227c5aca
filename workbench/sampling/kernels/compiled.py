"""A compiled kernel called with NumPy arrays: the ctypes wrapper (:class:`CompiledKernel`), its
outputs (:class:`KernelOutput`) and the pool of output buffers it reuses (:class:`OutputPool`).
Every kernel library (sampler, safe-MPPI, diagnostics, the vector-maths probe) wraps its kernels
in these."""

from __future__ import annotations

import ctypes
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

import workbench.sampling.kernels.threads as threads
from workbench.sampling.kernels.emit import KernelSpec
from workbench.sampling.kernels.layout import Layout


@dataclass(frozen=True, eq=False)
class KernelOutput:
    """Kernel outputs; lane outputs are (T, m, N) views, results (N, nr), noise (T, nz, N).

    They are views of buffers the kernel reuses for a later call only once nothing refers to
    them any more (:class:`OutputPool`): an output stays valid as long as the caller keeps it
    (or any view of it)."""

    lane_out: list[np.ndarray]
    result: np.ndarray
    noise: np.ndarray | None


def address(a: np.ndarray) -> int:
    """The address of an array's first byte, for a C pointer argument."""
    try:  # 3x faster than the array interface (kernel calls pass a dozen arrays)
        # numpy's stubs declare ndarray.__buffer__ only for Python >= 3.12; it is a buffer
        return ctypes.addressof(ctypes.c_char.from_buffer(a))  # type: ignore[arg-type]
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
        self.carry_p = address(self.carry)
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
            plan.const_p[j] = address(c)
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
            plan.time_p[j] = address(a)
        for j, name in enumerate(self._names["lane"]):
            a = pad(lane_in[name])
            if a.shape != (T, self._sizes[name], Np):
                raise ValueError(f"{spec.name}: lane input {name!r} has shape "
                                 f"{np.shape(lane_in[name])}, expected "
                                 f"({T}, {self._sizes[name]}, {N})")
            keep.append(a)
            plan.lane_p[j] = address(a)
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
            plan.out_p[j] = address(o)
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
                 address(result), address(noise_buf) if noise_buf is not None else None, int(gen),
                 int(seed or 0) & (2**64 - 1))
        del keep
        return KernelOutput(
            lane_out=[o[..., :N] for o in outs], result=result[:N],
            noise=noise_buf[..., :N] if noise_buf is not None else None)

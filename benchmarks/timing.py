"""Timing helpers shared by the benchmarks: medians of calls timed in turn, and zero-argument
calls of a compiled sampler kernel on prepared buffers (no Python packing in the timed call)."""

from __future__ import annotations

import contextlib
import ctypes
import statistics
import time
from collections.abc import Callable, Iterator

import numpy as np

from workbench.sampling.kernels.compiled import CompiledKernel


def record(name, value, unit, baseline, baseline_value, params, **extra) -> dict:
    """A benchmark record; ratio = baseline_value / value (None without a baseline)."""
    ratio = baseline_value / value if (value and baseline_value is not None) else None
    return {"name": name, "value": value, "unit": unit, "baseline": baseline,
            "baseline_value": baseline_value, "ratio": ratio, "params": params, **extra}


def samples_in_turn(fns: dict[str, Callable[[int], object]], repeats: int, block: int = 1,
                    warmup: int = 1, warm: int = 0) -> dict[str, tuple[list[float], list[float]]]:
    """Wall and CPU (thread) seconds of every timed call of each ``fn(i)``, the functions
    timed in turn (``block`` calls of each per round, ``repeats`` rounds) so that load changes
    hit all of them alike. ``warmup`` untimed rounds first (first-call page faults, OpenMP
    start-up); ``warm`` untimed calls at the start of every block (the first calls after
    another function run with its data out of the caches: measured up to 1.5x slower for a
    2 ms kernel after the SAIS batch)."""
    out: dict[str, tuple[list[float], list[float]]] = {n: ([], []) for n in fns}
    i = 0
    for r in range(warmup + repeats):
        for name, fn in fns.items():
            for j in range(warm + block):
                t0, c0 = time.perf_counter(), time.thread_time()
                fn(i)
                dc, dw = time.thread_time() - c0, time.perf_counter() - t0
                if r >= warmup and j >= warm:
                    out[name][0].append(dw)
                    out[name][1].append(dc)
                i += 1
    return out


def round_robin(fns: dict[str, Callable[[int], object]], repeats: int, block: int = 1,
                warmup: int = 1, with_min: bool = False, warm: int = 0):
    """Median seconds of each ``fn(i)`` timed by :func:`samples_in_turn`. ``with_min``: also
    the minimum (the least disturbed call; returns (medians, minima))."""
    times = {n: w for n, (w, _) in samples_in_turn(fns, repeats, block, warmup, warm).items()}
    med = {n: statistics.median(t) for n, t in times.items()}
    return (med, {n: min(t) for n, t in times.items()}) if with_min else med


@contextlib.contextmanager
def pinned_threads(n: int, *setters: Callable[[int], object]) -> Iterator[None]:
    """Exactly ``n`` OpenMP threads for every kernel call in the block, the library's adaptive
    thread policy off (when the library has one), then the previous setting. ``setters``: more
    thread setters to call (e.g. the floor's; OpenMP's count is per calling thread and shared
    by every library of the process, so this only makes it explicit)."""
    try:
        from workbench.sampling.kernels.threads import using
    except ImportError:  # a library without the thread policy
        using = None
    if using is None:
        from workbench.sampling.kernels import library

        previous = library.get_threads()
        library.set_threads(n)
        for s in setters:
            s(n)
        try:
            yield
        finally:
            if previous is not None:
                library.set_threads(previous)
        return
    with using(n, adaptive=False):
        for s in setters:
            s(n)
        yield


def prepare_openmp() -> None:
    """The library's OpenMP runtime settings (its wait policy) before a benchmark library
    loads the runtime first, so that the floor and the kernels run under the same policy."""
    try:
        from workbench.sampling.kernels.threads import prepare_runtime
    except ImportError:
        return
    prepare_runtime()


def _addr(a: np.ndarray) -> int:
    return a.__array_interface__["data"][0]


def prepared_kernel(k: CompiledKernel, carry0: np.ndarray, consts: dict[str, np.ndarray],
                    time_in: dict[str, np.ndarray], *, noise: np.ndarray | None = None,
                    seed: int | None = None) -> tuple[Callable[[], None], list[np.ndarray],
                                                      np.ndarray]:
    """(call, lane outputs, results) of a kernel on prepared buffers: ``call()`` runs the C
    function only, reading the noise (T, nz, N) from ``noise`` or drawing it from ``seed``.
    Outputs are padded to the kernel's lane count (trim to N)."""
    spec = k.spec
    if spec.inputs("lane"):
        raise ValueError(f"{spec.name}: kernels with per-sample lane inputs are not supported")
    carry0 = np.ascontiguousarray(carry0, dtype=float)
    N = carry0.shape[0]
    Np = -(-N // spec.lanes) * spec.lanes
    if Np != N:
        carry0 = np.vstack([carry0, np.repeat(carry0[-1:], Np - N, axis=0)])
    T = next(iter(time_in.values())).shape[0]
    keep = [carry0]

    def ptr(a) -> int:
        a = np.ascontiguousarray(a, dtype=float)
        keep.append(a)
        return _addr(a)

    times = [ptr(time_in[n]) for n in spec.inputs("time")]
    consts_p = [ptr(consts[n]) for n in spec.inputs("const")]
    outs = [np.empty((T, m, Np)) for m in spec.lane_out_sizes()]
    result = np.empty((Np, spec.n_result))
    if (noise is None) == (seed is None):
        raise ValueError("give exactly one of noise and seed")
    if noise is not None:
        nb = np.asarray(noise, dtype=float)
        if Np != N:
            nb = np.concatenate([nb, np.repeat(nb[..., -1:], Np - N, axis=-1)], axis=-1)
        nb = np.ascontiguousarray(nb)
        keep.append(nb)
        noise_p, gen = _addr(nb), 0
    else:
        noise_p, gen = None, 1

    def arr(lst):
        return (ctypes.c_void_p * max(1, len(lst)))(*lst) if lst else None

    args = (Np, T, _addr(carry0), None, arr(times), arr(consts_p),
            arr([_addr(o) for o in outs]), _addr(result), noise_p, gen,
            int(seed or 0) & (2**64 - 1))
    fn = k._fn  # the kernel's C entry point, as CompiledKernel.__call__ calls it

    keep += [*outs, result]  # every buffer the C function touches lives as long as call

    def call(_keep=keep) -> None:
        fn(*args)

    return call, outs, result

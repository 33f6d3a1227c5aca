"""Sampler kernel libraries: the C source of a library (:func:`kernel_source`,
:func:`library_sources`), compiling, loading and verifying it (:func:`load_verified`, shared by
every kernel library), the per-process table of a problem's libraries (:func:`sampler_library`)
and the kernels' thread count (:func:`set_threads`)."""

from __future__ import annotations

import ctypes
import warnings
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from typing import TypeVar

import numpy as np

import workbench.sampling.kernels.slots as slots
import workbench.sampling.kernels.threads as threads
from workbench.codegen import CompileError, build_library
from workbench.sampling.kernels.compiled import CompiledKernel, address
from workbench.sampling.kernels.emit import EmitError, KernelSpec, emit_kernel, rng_source
from workbench.sampling.kernels.flags import KERNEL_FLAGS, is_float32, kernel_flags, lane_count
from workbench.sampling.kernels.specs import candidate_spec, layouts, mppi_spec, sais_spec
from workbench.sampling.kernels.vector_math import prelude
from workbench.sampling.kernels.verify import KernelMismatch, verify_kernel
from workbench.sampling.problem import SamplingProblem
from workbench.validation import fail

L = TypeVar("L")


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
                             ctypes.c_void_p(address(out)))
        return out

    def normals_at(self, index, T: int, m: int, seed: int) -> np.ndarray:
        """The standard normals (T, m, n) of the samples ``index`` (n sample numbers of a
        batch) that a kernel draws with the same seed."""
        idx = np.ascontiguousarray(index, dtype=np.int64)
        out = np.empty((T, m, idx.size))
        self.cdll.wb_normals_at(idx.size, ctypes.c_void_p(address(idx)), T, m,
                                ctypes.c_ulonglong(int(seed) & (2**64 - 1)),
                                ctypes.c_void_p(address(out)))
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
    tag = "_f32" if is_float32(precision) else ""
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


def compiled_or_twin(libs: dict[str, L | None], warned: set[str], key: str,
                     build: Callable[[], L | None], what: str, model: str) -> L | None:
    """``libs[key]``, built once by ``build``. When the model uses an operation the emitter or
    the C back end cannot compile (an EmitError, or a CompileError for an unlinkable
    operation) it is None, with one RuntimeWarning per key naming ``what`` and ``model``: the
    caller then runs its NumPy/CasADi twin. Any other compile error is raised."""
    if key not in libs:
        try:
            libs[key] = build()
        except (EmitError, CompileError) as exc:
            if isinstance(exc, CompileError) and "no linked library provides" not in str(exc):
                raise
            if key not in warned:
                warned.add(key)
                warnings.warn(f"workbench: no compiled {what} for {model}: "
                              f"{str(exc).splitlines()[0]}; using the NumPy/CasADi evaluation "
                              "(correct, slower)", RuntimeWarning, stacklevel=3)
            libs[key] = None
    return libs[key]


def sampler_library(sp: SamplingProblem, precision: str = "float64") -> SamplerLibrary | None:
    """Build (or load from the cache) the kernels of a sampling problem in ``precision``,
    verified; None without a compiler, or, with one warning, when the model uses an operation
    the emitter or the C back end cannot compile (the sampler then uses the NumPy/CasADi twin:
    correct, slower)."""
    key = sp.fingerprint() + ("_f32" if is_float32(precision) else "")
    return compiled_or_twin(_LIBS, _FALLBACK_WARNED, key,
                            lambda: load_sampler_library(sp, precision=precision),
                            "sampler kernels", sp.model.name)

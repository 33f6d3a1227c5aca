"""Generated sampler kernels: MPPI rollouts, the SAIS dual rollout of
Algorithm 1 and the RMPPI candidate evaluation, emitted by :mod:`workbench.sampling.kernels.emit`.

Run-time constants (``const`` role, shared by all samples):
  sigma (nu) sampling std, lr (1) = lambda (1 - nu_mix), u_min, u_max (nu), crash (1) =
  C_crash, p (n_p) cost parameters, scene (n_scene, when the model has a run-time scene) the
  obstacles, alpha (1) the RMPPI threshold (SAIS only).
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
import warnings
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import TypeVar

import casadi as ca
import numpy as np

import workbench.sampling.kernels.threads as threads
from workbench.codegen import CompileError, build_library
from workbench.problem.barrier import min_margin
from workbench.sampling.kernels.emit import (
    LANES,
    PRECISIONS,
    EmitError,
    KernelSpec,
    emit_kernel,
    rng_source,
)
from workbench.sampling.kernels.layout import Layout
from workbench.sampling.kernels.vector_math import prelude
from workbench.sampling.kernels.verify import KernelMismatch, verify_kernel
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


def _clip(v, lo, hi):
    return ca.fmin(ca.fmax(v, lo), hi)


def _symbols(sp: SamplingProblem):
    """The const inputs; ``scene`` only when the model has a run-time scene."""
    nu = sp.nu
    out = {
        "sigma": ca.SX.sym("sigma", nu), "lr": ca.SX.sym("lr"),
        "u_min": ca.SX.sym("u_min", nu), "u_max": ca.SX.sym("u_max", nu),
        "crash": ca.SX.sym("crash", 1), "p": ca.SX.sym("p", sp.n_p),
    }
    if sp.model.n_scene:
        out["scene"] = ca.SX.sym("scene", sp.model.n_scene)
    return out


def _model_parts(sp: SamplingProblem, c: dict):
    """dyn (x, v) and margins (x) in the kernel's scene input (or the empty scene)."""
    fns = sp.functions()
    s = c.get("scene", ca.SX(0, 1))
    return (lambda x, v: fns["dyn"](x, v, s)), (lambda x: fns["margins"](x, s)), \
        fns["q"], fns["phi"]


def _crashed(margins, x, eps_h: float, nh: int):
    """1 if any margin is <= eps_h; built like the barrier's crash rule so CSE shares it."""
    if nh == 0:
        return ca.SX(0)
    return min_margin(margins(x), range(nh)) <= eps_h


def _near(margins, x, eps_h: float, nh: int, band):
    """1 if the smallest margin is within ``band`` of eps_h (the float32 guard)."""
    if nh == 0:
        return ca.SX(0)
    return ca.fabs(min_margin(margins(x), range(nh)) - eps_h) <= band


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
    """MPPI rollout (SPEC 8.1 with the crash rule of 4.6).

    ``strided`` (RMPPI candidates, SPEC 9.3) adds per-sample ``delay`` and ``stride`` s in
    {0, 1} as carry entries after the crash flag: the sample follows u_{min(t+s, T-1)} (time
    input ``u_next`` holds the shifted sequence) and draws no noise while delay > 0. A float32
    kernel (named ``<name>_f32``) ends its carry with the guard flag.
    """
    nx, nu, nh = sp.nx, sp.nu, sp.model.nh
    f32 = _f32(precision)
    c = _symbols(sp)
    if f32:
        c["guard"] = ca.SX.sym("guard")
    dyn, margins, q, phi = _model_parts(sp, c)
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
    v = _clip(u + noise, c["u_min"], c["u_max"])
    eps = v - u
    xn = dyn(x, v)
    crn = ca.fmax(cr, _crashed(margins, xn, sp.eps_h, nh))
    inv = 1.0 / (c["sigma"] * c["sigma"])
    lr = 0.5 * c["lr"] * (ca.dot(u * inv, u) + 2.0 * ca.dot(u * inv, eps))
    Sn = S + (q(xn, c["p"]) + c["crash"][0] * crn) + lr
    ins = {"carry": carry, "z": z, "u": u_in, **({"u_next": u_next} if strided else {}), **c}
    new = [xn, Sn, crn] + ([carry[nx + 2] - 1, carry[nx + 3]] if strided else [])
    res = [S + phi(x, c["p"]), cr]
    if f32:
        g = carry[carry.numel() - 1]
        # the crash step and the steps before it (a crashed sample's flag no longer changes)
        new.append(ca.fmax(g, (1.0 - cr) * _near(margins, xn, sp.eps_h, nh, c["guard"])))
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
    """RMPPI candidate evaluation (SPEC 9.3): strided MPPI rollouts, no feedback."""
    return mppi_spec(sp, "wb_candidates", strided=True, precision=precision)


def sais_spec(sp: SamplingProblem, name: str = "wb_sais", precision: str = "float64") -> KernelSpec:
    """The SAIS dual rollout of Algorithm 1 (SPEC 10.1); clip_in_cost is a run-time input. A
    float32 kernel (``<name>_f32``) ends its carry with the guard flag of both systems."""
    nx, nu, nh = sp.nx, sp.nu, sp.model.nh
    f32 = _f32(precision)
    c = _symbols(sp)
    if f32:
        c["guard"] = ca.SX.sym("guard")
    dyn, margins, q, phi = _model_parts(sp, c)
    alpha, clip_cost = ca.SX.sym("alpha"), ca.SX.sym("clip_cost")
    carry = ca.SX.sym("carry", 2 * nx + 6 + int(f32))
    z, u, Kv = ca.SX.sym("z", nu), ca.SX.sym("u", nu), ca.SX.sym("K", nu * nx)
    x, xs = carry[:nx], carry[nx : 2 * nx]
    Sn, Sh, Sr, LR, cr, cn = (carry[2 * nx + i] for i in range(6))
    K = ca.reshape(Kv, nx, nu).T
    eps = c["sigma"] * z
    kfb = ca.mtimes(K, x - xs)
    vr = _clip(u + eps + kfb, c["u_min"], c["u_max"])
    vn = _clip(u + eps, c["u_min"], c["u_max"])
    # clip_in_cost (SPEC 10.1): effective (clipped) noise and feedback in lines 8, 9 and 12
    # when 1, the raw ones when 0 (exact 0/1 blends)
    et = clip_cost * (vn - u) + (1.0 - clip_cost) * eps
    kt = clip_cost * (vr - u - (vn - u)) + (1.0 - clip_cost) * kfb
    xn, xsn = dyn(x, vr), dyn(xs, vn)
    crn = ca.fmax(cr, _crashed(margins, xn, sp.eps_h, nh))
    cnn = ca.fmax(cn, _crashed(margins, xsn, sp.eps_h, nh))
    qr = q(xn, c["p"]) + c["crash"][0] * crn
    qn = q(xsn, c["p"]) + c["crash"][0] * cnn
    inv = 1.0 / (c["sigma"] * c["sigma"])
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
        near = ca.fmax((1.0 - cr) * _near(margins, xn, sp.eps_h, nh, c["guard"]),
                       (1.0 - cn) * _near(margins, xsn, sp.eps_h, nh, c["guard"]))
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
    """Kernel outputs; lane outputs are (T, m, N) views, results (N, nr), noise (T, nz, N)."""

    lane_out: list[np.ndarray]
    result: np.ndarray
    noise: np.ndarray | None


def _addr(a: np.ndarray) -> int:
    try:  # 3x faster than the array interface (kernel calls pass a dozen arrays)
        return ctypes.addressof(ctypes.c_char.from_buffer(a))
    except (TypeError, ValueError):  # read-only or empty
        return a.__array_interface__["data"][0]


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

    def __call__(self, carry0, *, consts: dict[str, np.ndarray], time_in=None, lane_in=None,
                 noise=None, seed: int | None = None, keep_noise: bool = False,
                 lane_out: list[np.ndarray] | None = None) -> KernelOutput:
        """carry0 (N, nc); time_in {name: (T, m)}; lane_in {name: (T, m, N)};
        noise (T, nz, N) standard normals, or seed (draws in the kernel; kept if keep_noise);
        lane_out: optional C-contiguous (T, m, N padded to the lane count) buffers to write the
        lane outputs into (allocated when None). Runs on the thread count of
        :func:`~workbench.sampling.kernels.threads.threads_for` (N T sample-steps)."""
        spec = self.spec
        carry0 = np.ascontiguousarray(carry0, dtype=float)
        N = carry0.shape[0]
        Np = -(-N // spec.lanes) * spec.lanes
        time_in, lane_in = time_in or {}, lane_in or {}
        T = (next(iter(time_in.values())).shape[0] if time_in
             else next(iter(lane_in.values())).shape[0])
        if Np != N:
            carry0 = np.vstack([carry0, np.repeat(carry0[-1:], Np - N, axis=0)])
        keep = []

        def pad(a) -> np.ndarray:
            """Lane-major (..., N) array padded to Np lanes by repeating the last one."""
            a = np.asarray(a, dtype=float)
            if Np != N:
                a = np.concatenate([a, np.repeat(a[..., -1:], Np - N, axis=-1)], axis=-1)
            return np.ascontiguousarray(a)

        def prep(a, pad_last=False):
            a = pad(a) if pad_last else np.ascontiguousarray(a, dtype=float)
            keep.append(a)
            return _addr(a)

        for n in spec.inputs("const"):  # the kernel reads exactly this many values
            if np.size(consts[n]) != self._sizes[n]:
                raise ValueError(f"{spec.name}: const input {n!r} has {np.size(consts[n])} "
                                 f"values, the kernel reads {self._sizes[n]}")

        ptrs = {
            "lane": [prep(lane_in[n], True) for n in spec.inputs("lane")],
            "time": [prep(time_in[n]) for n in spec.inputs("time")],
            "const": [prep(consts[n]) for n in spec.inputs("const")],
        }
        if lane_out is None:
            outs = [np.empty((T, m, Np)) for m in spec.lane_out_sizes()]
        else:
            outs = list(lane_out)
            want = [(T, m, Np) for m in spec.lane_out_sizes()]
            if [o.shape for o in outs] != want or not all(
                    o.dtype == np.float64 and o.flags.c_contiguous for o in outs):
                raise ValueError(f"{spec.name}: lane_out must be C-contiguous float64 arrays "
                                 f"of shapes {want}")
        result = np.empty((Np, spec.n_result))
        nz = spec.n_noise
        gen = seed is not None
        if gen:
            noise_buf = np.empty((T, nz, Np)) if keep_noise else None
        elif noise is not None:
            noise_buf = pad(noise)
        elif nz:
            raise ValueError("noise = None is invalid: give a noise buffer or a seed")
        else:
            noise_buf = None

        def arr(lst):
            return (ctypes.c_void_p * max(1, len(lst)))(*lst) if lst else None

        threads.apply(self._set_threads, Np * T)
        self._fn(Np, T, _addr(carry0), arr(ptrs["lane"]), arr(ptrs["time"]), arr(ptrs["const"]),
                 arr([_addr(o) for o in outs]), _addr(result),
                 _addr(noise_buf) if noise_buf is not None else None, int(gen),
                 int(seed or 0) & (2**64 - 1))
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
    lanes = specs[0].lanes if specs else LANES
    return rng_source(lanes) + "\n" + prelude(fns, kernel_flags(precision), lanes, vector_math,
                                               precision) + "\n".join(
        emit_kernel(s) for s in specs)


def library_sources(sp: SamplingProblem, vector_math: bool | None = None,
                    precision: str = "float64") -> tuple[str, list[KernelSpec], str]:
    """(cache stem, kernel specs, C source) of a sampling problem's library."""
    specs = [mppi_spec(sp, precision=precision), sais_spec(sp, precision=precision),
             candidate_spec(sp, precision)]
    tag = "_f32" if _f32(precision) else ""
    return (f"sampler_{sp.model.name.replace('+', '_')}{tag}", specs,
            kernel_source(specs, vector_math))


def load_sampler_library(sp: SamplingProblem, vector_math: bool | None = None,
                         precision: str = "float64") -> SamplerLibrary | None:
    """Build (or load from the disk cache) and verify a problem's kernels, bypassing the
    per-process table of :func:`sampler_library` (e.g. to compare scalar and vector libm)."""
    stem, specs, source = library_sources(sp, vector_math, precision)
    lays = [layouts(sp, k, precision) for k in ("mppi", "sais", "candidates")]
    return load_verified(stem, source, lambda c: _sampler_library(c, specs, lays),
                         lambda lib: (lib.mppi, lib.sais, lib.candidates),
                         flags=kernel_flags(precision))


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

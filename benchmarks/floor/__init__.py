"""The hand-written C floor of the sampler kernels (``sais_floor.c``): the SAIS dual rollout and
the MPPI rollout of the navigation problem with the noise given as an input array.

It is compiled like the generated kernels (the library's compiler discovery and flags, plus the
kernels' ``-fopenmp -march=native``) into the code cache, and it is the speed record every
sampler kernel is compared with in ``make bench``. Scope: the built-in navigation problem
(planar double integrator, Euler step, circles as a run-time scene, one summed inverse barrier
state with gamma = 0, :func:`~workbench.sampling.problem.navigation_costs`), clipped noise and
feedback in the costs (``clip_in_cost``).
"""

from __future__ import annotations

import ctypes
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from benchmarks.timing import prepare_openmp
from workbench.codegen import build_library
from workbench.sampling.kernels.constants import SamplerConstants
from workbench.sampling.kernels.emit import rng_source
from workbench.sampling.kernels.flags import KERNEL_FLAGS
from workbench.sampling.problem import SamplingProblem
from workbench.sampling.twin_model import numpy_navigation_twin
from workbench.validation import fail, integer

SOURCE = Path(__file__).with_name("sais_floor.c")
LANES = 8  # samples per block: one AVX-512 register of doubles
SAIS_RESULTS = ("S_nom", "S_real", "S_state_nom", "S_hat", "LR", "crashed_real", "crashed_nom")
MPPI_RESULTS = ("S", "crashed")


def cpu_flags() -> dict[str, bool]:
    """Which vector extensions this machine has (from /proc/cpuinfo)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        text = ""
    flags = set()
    for line in text.splitlines():
        if line.startswith(("flags", "Features")):
            flags |= set(line.split(":", 1)[1].split())
    return {f: f in flags for f in ("avx2", "avx512f", "avx512dq", "avx512vl", "fma")}


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return "unknown"


@dataclass(frozen=True)
class FloorProblem:
    """The numbers the floor needs: parameter vector (order of ``enum P_*`` in the C file)."""

    params: np.ndarray
    scene: np.ndarray  # (nc, 3) circles x, y, r (inert slots included)

    @property
    def n_circles(self) -> int:
        return int(self.scene.shape[0])

    @classmethod
    def of(cls, sp: SamplingProblem, c: SamplerConstants) -> FloorProblem:
        """From a navigation sampling problem and the sampler constants (``c.scene`` empty:
        the model's own scene). Raises ValueError for problems outside the floor's scope."""
        twin = numpy_navigation_twin(sp.model, sp.weights, sp.functions()) \
            if sp.weights is not None else None
        spec = sp.model.barrier
        if twin is None or twin.zoh or spec is None:
            raise fail("sp", sp.model.name, "the floor covers the barrier-embedded planar "
                       "double integrator (Euler) with the navigation costs only")
        o = spec.options
        if o.kind != "inverse" or len(spec.groups) != 1 or o.gamma != 0.0 or sp.nx != 5:
            raise fail("sp", sp.model.name, "the floor needs one summed inverse barrier state "
                       "with gamma = 0")
        if not c.clip_in_cost:
            raise fail("SamplerConstants.clip_in_cost", c.clip_in_cost, "the floor implements "
                       "clip_in_cost = True only")
        scene = sp.model.scene_vector(c.scene if np.size(c.scene) else None)
        w = sp.weights
        prm = np.concatenate([
            [sp.model.dt], np.asarray(c.sigma, float), [c.lam * (1.0 - c.nu_mix)],
            np.asarray(c.u_min, float), np.asarray(c.u_max, float), [c.crash_cost],
            np.asarray(c.p, float), np.asarray(w["Qp"], float), np.asarray(w["Qv"], float),
            [float(w["q_beta"])], np.asarray(w["S"], float), [c.alpha], [sp.eps_h],
            [o.beta_max], [o.eps_h]])
        return cls(params=np.ascontiguousarray(prm), scene=np.asarray(scene, float).reshape(-1, 3))


def _addr(a: np.ndarray) -> ctypes.c_void_p:
    return ctypes.c_void_p(a.__array_interface__["data"][0])


def _pad(a: np.ndarray, Np: int) -> np.ndarray:
    """Lane-major (..., N) padded to Np lanes by repeating the last lane."""
    a = np.asarray(a, dtype=float)
    N = a.shape[-1]
    if Np != N:
        a = np.concatenate([a, np.repeat(a[..., -1:], Np - N, axis=-1)], axis=-1)
    return np.ascontiguousarray(a)


class Floor:
    """The loaded floor library: :meth:`sais`, :meth:`mppi` (results as dicts of arrays, like the
    NumPy twin's) and zero-argument prepared calls for timing."""

    def __init__(self, cdll: ctypes.CDLL):
        self.cdll = cdll
        cdll.floor_set_threads.argtypes = [ctypes.c_int]
        cdll.floor_get_threads.restype = ctypes.c_int
        self.lanes = int(cdll.floor_lanes())
        self.n_params = int(cdll.floor_nprm())
        p, i = ctypes.c_void_p, ctypes.c_int
        cdll.floor_sais.restype = None
        cdll.floor_sais.argtypes = [i, i, i] + [p] * 10
        cdll.floor_mppi.restype = None
        cdll.floor_mppi.argtypes = [i, i, i] + [p] * 7
        cdll.floor_sais_seeded.restype = None
        cdll.floor_sais_seeded.argtypes = [i, i, i] + [p] * 6 + [ctypes.c_ulonglong] + [p] * 3
        cdll.floor_normals.restype = None
        cdll.floor_normals.argtypes = [i, i, i, ctypes.c_ulonglong, p]

    def set_threads(self, n: int) -> None:
        self.cdll.floor_set_threads(integer("threads", n, 1))

    def threads(self) -> int:
        return int(self.cdll.floor_get_threads())

    def _check(self, prob: FloorProblem) -> None:
        if prob.params.shape != (self.n_params,):
            raise fail("FloorProblem.params", prob.params.shape, f"expected ({self.n_params},)")

    def prepare_sais(self, prob: FloorProblem, x0, xs0, U, K, Z=None, *, N: int | None = None,
                     seed: int | None = None):
        """(call, outputs): ``call()`` runs the SAIS floor into preallocated buffers, on the
        given noise Z (T, 2, N) or, with ``seed`` (and ``N``), drawing the kernels' noise for
        that seed inside the rollout; ``outputs()`` returns them as a dict trimmed to N."""
        self._check(prob)
        U = np.ascontiguousarray(U, dtype=float)
        T = U.shape[0]
        K = np.ascontiguousarray(np.asarray(K, float).reshape(T, 2, 5))
        if (Z is None) == (seed is None):
            raise ValueError("give exactly one of Z and seed")
        N = Z.shape[-1] if Z is not None else integer("N", N, 1)
        Np = -(-N // self.lanes) * self.lanes
        x0, xs0 = (np.ascontiguousarray(a, dtype=float) for a in (x0, xs0))
        sc = np.ascontiguousarray(prob.scene)
        vn, vr = np.empty((T, 2, Np)), np.empty((T, 2, Np))
        res = np.empty((len(SAIS_RESULTS), Np))
        head = (Np, T, prob.n_circles, _addr(prob.params), _addr(sc), _addr(x0), _addr(xs0),
                _addr(U), _addr(K))
        if Z is not None:
            Zp = _pad(Z, Np)
            args = (*head, _addr(Zp), _addr(vn), _addr(vr), _addr(res))
            fn = self.cdll.floor_sais
        else:
            Zp = None
            args = (*head, ctypes.c_ulonglong(int(seed) & (2**64 - 1)), _addr(vn), _addr(vr),
                    _addr(res))
            fn = self.cdll.floor_sais_seeded
        keep = (U, K, Zp, x0, xs0, sc, vn, vr, res, prob.params)

        def call(_keep=keep) -> None:
            fn(*args)

        def outputs() -> dict[str, np.ndarray]:
            out = {n: res[i, :N].copy() for i, n in enumerate(SAIS_RESULTS)}
            for n in ("crashed_real", "crashed_nom"):
                out[n] = out[n] > 0
            out["v_nom"], out["v_real"] = vn[..., :N].copy(), vr[..., :N].copy()
            return out

        return call, outputs

    def normals(self, N: int, T: int, m: int, seed: int) -> np.ndarray:
        """The standard normals (T, m, N) the kernels draw for ``seed``, drawn FLOOR_LANES
        samples at a time."""
        Np = -(-integer("N", N, 1) // self.lanes) * self.lanes
        out = np.empty((T, m, Np))
        self.cdll.floor_normals(Np, T, m, ctypes.c_ulonglong(int(seed) & (2**64 - 1)),
                                _addr(out))
        return np.ascontiguousarray(out[..., :N])

    def prepare_mppi(self, prob: FloorProblem, x0, U, Z):
        """As :meth:`prepare_sais` for the MPPI rollout (results S, crashed, v (T, 2, N))."""
        self._check(prob)
        U = np.ascontiguousarray(U, dtype=float)
        T = U.shape[0]
        N = Z.shape[-1]
        Np = -(-N // self.lanes) * self.lanes
        Zp = _pad(Z, Np)
        x0 = np.ascontiguousarray(x0, dtype=float)
        sc = np.ascontiguousarray(prob.scene)
        v = np.empty((T, 2, Np))
        res = np.empty((len(MPPI_RESULTS), Np))
        keep = (U, Zp, x0, sc, v, res, prob.params)
        args = (Np, T, prob.n_circles, _addr(prob.params), _addr(sc), _addr(x0), _addr(U),
                _addr(Zp), _addr(v), _addr(res))
        fn = self.cdll.floor_mppi

        def call(_keep=keep) -> None:
            fn(*args)

        def outputs() -> dict[str, np.ndarray]:
            return {"S": res[0, :N].copy(), "crashed": res[1, :N] > 0, "v": v[..., :N].copy()}

        return call, outputs

    def sais(self, prob: FloorProblem, x0, xs0, U, K, Z=None, *, N: int | None = None,
             seed: int | None = None) -> dict[str, np.ndarray]:
        call, outputs = self.prepare_sais(prob, x0, xs0, U, K, Z, N=N, seed=seed)
        call()
        return outputs()

    def mppi(self, prob: FloorProblem, x0, U, Z) -> dict[str, np.ndarray]:
        call, outputs = self.prepare_mppi(prob, x0, U, Z)
        call()
        return outputs()


def floor_source(lanes: int) -> str:
    """The library's generator (its block of ``lanes`` samples) followed by the floor."""
    rng = rng_source()
    line = next((ln for ln in rng.splitlines() if ln.startswith("#define WB_LANES ")), None)
    if line is None:
        raise RuntimeError("the library's generator source no longer defines WB_LANES")
    return rng.replace(line, f"#define WB_LANES {lanes}", 1) + "\n" + SOURCE.read_text()


_FLOORS: dict[tuple[int, int], Floor | None] = {}


def load_floor(lanes: int = LANES, group: int = 2) -> Floor | None:
    """Compile (or load from the code cache) the floor with ``lanes`` samples per block and
    ``group`` circles per division of the inverse-barrier sum (2: the generated kernels' pairwise
    form; 4: one division per four circles); None without a C compiler."""
    integer("lanes", lanes, 1)
    if group not in (2, 4):
        raise fail("group", group, "must be 2 or 4")
    key = (lanes, group)
    if key not in _FLOORS:
        prepare_openmp()
        lib = build_library(f"bench_floor_l{lanes}_g{group}", [], floor_source(lanes),
                            extra_flags=(*KERNEL_FLAGS, f"-DFLOOR_LANES={lanes}",
                                         f"-DFLOOR_GROUP={group}"))
        _FLOORS[key] = None if lib is None else Floor(lib.cdll)
    return _FLOORS[key]

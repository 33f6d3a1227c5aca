"""Seeing the sampler: a step's sample trajectories, from every sampling controller.

Off by default. Switch it on per controller with ``ctrl.record_samples(k, keep="spread")``
(:mod:`workbench.sampling.mppi`, :mod:`workbench.sampling.robust` and
:mod:`workbench.sampling.methods` have it; the gatekeeper hands it to its inner controller);
``ctrl.record_samples(0)`` switches it off again. While it is on, each step's info carries
``info.samples``, a :class:`SampleTrajectories`; while it is off ``info.samples`` is None and
the step does no extra work. Recording never draws from the step's generator and never changes
the batch, so a run with recording takes the same controls as one without.

Which ``k`` of the last batch's N samples are kept (``min(k, N)``; ``index`` says which):

* ``keep="spread"`` (default): lanes ``floor(i N / k)``, i = 0..k-1, evenly spaced. The lanes
  of a batch are independent draws, so this is an unbiased subset: crashed and low-weight
  samples appear as often as they occur.
* ``keep="top"``: the k highest update weights (ties to the lower lane): what the update
  actually averages over; ``samples.mass`` says how much of the weight they hold.

The trajectories are recomputed from the batch's applied sample controls (clipped; projected
or with feedback where the method does so) by rolling the problem's dynamics out from the
step's start state(s) in float64, ``x_{t+1} = dyn(x_t, v_t, scene)``, on a small compiled
library (the CasADi virtual machine without a C compiler): they equal the sampler's own
trajectories to rounding. The crash flags are the batch's own.
"""

from __future__ import annotations

import ctypes
import logging
import time
from dataclasses import dataclass
from typing import Literal

import casadi as ca
import numpy as np

from workbench.codegen import CompileError, Library, build_library
from workbench.codegen.fastcall import FastFunction
from workbench.problem.prediction import predicts, scene_at
from workbench.sampling.problem import SamplingProblem
from workbench.validation import MAX_BATCH, fail, integer, one_of

log = logging.getLogger("workbench.sampling.samples")

Keep = Literal["spread", "top"]
KEEP: tuple[str, ...] = ("spread", "top")
_LIBS: dict[str, Library | None] = {}
_DP = ctypes.c_void_p


def _frozen(a, dtype=float) -> np.ndarray:
    out = np.array(a, dtype=dtype)
    out.setflags(write=False)
    return out


@dataclass(frozen=True, kw_only=True, eq=False)
class SampleTrajectories:
    """The kept samples of one step's last batch (see the module docstring).

    ``real`` (K, T+1, nx): state trajectories of the samples from the measured state, the
    system the control acts on; ``controls`` (K, T, nu) their applied controls. ``nominal``
    and ``controls_nominal``: the same for methods that also sample a nominal system (Robust
    MPPI: from the chosen nominal state x*_0, without feedback; Tube-MPPI: the nominal batch
    from x_nom), None otherwise. ``weights`` (K,): the normalised importance weights of these
    samples in the update that makes the applied plan (Robust MPPI: the nominal weights of
    the plan u*; Tube-MPPI: the nominal batch's; otherwise the one batch's); they sum to
    ``mass`` <= 1 (1 only when K = N). ``weights_real``: the real samples' own weights where a
    method has them (Robust MPPI's real weights; Tube-MPPI's actual batch), else None.
    ``crashed``/``crashed_nominal`` (K,): the batch's crash flags. ``index`` (K,): the batch
    lanes kept, ascending; ``keep``: how they were chosen; ``scene``: the step's scene vector;
    ``position``: the state indices of the position, 2 or 3 (None if the model has none);
    ``time_s``: wall time of the recording (not part of the step's own ``time_s``)."""

    real: np.ndarray
    controls: np.ndarray
    crashed: np.ndarray
    weights: np.ndarray
    index: np.ndarray
    n_samples: int
    keep: str = "spread"
    scene: np.ndarray | None = None
    position: tuple[int, ...] | None = (0, 1)
    nominal: np.ndarray | None = None
    controls_nominal: np.ndarray | None = None
    crashed_nominal: np.ndarray | None = None
    weights_real: np.ndarray | None = None
    time_s: float = 0.0

    def __post_init__(self) -> None:
        X = _frozen(self.real)
        if X.ndim != 3 or X.shape[1] < 2:
            raise fail("SampleTrajectories.real", X.shape, "expected (K, T+1, nx) with T >= 1")
        K, T1, _ = X.shape
        V = _frozen(self.controls)
        if V.ndim != 3 or V.shape[:2] != (K, T1 - 1):
            raise fail("SampleTrajectories.controls", V.shape, f"expected ({K}, {T1 - 1}, nu)")
        sets = {"real": X, "controls": V,
                "crashed": self._vector("crashed", self.crashed, K, bool),
                "weights": self._vector("weights", self.weights, K, float),
                "index": self._vector("index", self.index, K, int),
                "scene": _frozen(np.zeros(0) if self.scene is None else self.scene).ravel()}
        if self.nominal is not None:
            sets["nominal"] = _frozen(self.nominal)
            if sets["nominal"].shape != X.shape:
                raise fail("SampleTrajectories.nominal", sets["nominal"].shape,
                           f"expected the shape of real, {X.shape}")
        for name, n in (("controls_nominal", None), ("crashed_nominal", bool),
                        ("weights_real", float)):
            v = getattr(self, name)
            if v is None:
                continue
            if n is None:
                sets[name] = _frozen(v)
                if sets[name].shape != V.shape:
                    raise fail(f"SampleTrajectories.{name}", sets[name].shape,
                               f"expected the shape of controls, {V.shape}")
            else:
                sets[name] = self._vector(name, v, K, n)
        integer("SampleTrajectories.n_samples", self.n_samples, K)
        one_of("SampleTrajectories.keep", self.keep, KEEP)
        for name, v in sets.items():
            object.__setattr__(self, name, v)

    @staticmethod
    def _vector(name: str, value, K: int, dtype) -> np.ndarray:
        v = _frozen(value, dtype)
        if v.shape != (K,):
            raise fail(f"SampleTrajectories.{name}", v.shape, f"expected ({K},)")
        return v

    @property
    def k(self) -> int:
        """Samples kept."""
        return int(self.real.shape[0])

    @property
    def mass(self) -> float:
        """The share of the update's weight the kept samples hold (1 when all are kept)."""
        return float(self.weights.sum())

    @property
    def n_crashed(self) -> int:
        return int(self.crashed.sum())


def kept_lanes(n_samples: int, k: int, keep: str, weights=None) -> np.ndarray:
    """The ``min(k, n_samples)`` lanes ``keep`` chooses, ascending (see the module docstring;
    ``weights`` (N,) are needed for "top")."""
    N = integer("n_samples", n_samples, 1)
    k = min(integer("k", k, 1), N)
    if one_of("keep", keep, KEEP) == "spread":
        return (np.arange(k, dtype=np.int64) * N) // k
    w = np.asarray(weights, dtype=float)
    if w.shape != (N,):
        raise fail("weights", w.shape, f"expected ({N},)")
    return np.sort(np.argsort(-w, kind="stable")[:k])


def _rollout_function(sp: SamplingProblem) -> ca.Function:
    f = sp.functions()["dyn"]
    sym = f.sx_in()
    return ca.Function("wb_samples_dyn", sym, [ca.densify(o) for o in f.call(sym)])


_ROLLOUT_C = """
int wb_samples_rollout(int K, int T, const casadi_real* x0, int x0_stride,
                       const casadi_real* V, const casadi_real* scene, casadi_real* X) {
  const casadi_real* arg[WB_RO_ARG];
  casadi_real* res[WB_RO_RES];
  casadi_int iw[WB_RO_IW];
  casadi_real w[WB_RO_W];
  for (int k = 0; k < K; ++k) {
    casadi_real* Xk = X + (long long)k * (T + 1) * WB_RO_NX;
    for (int i = 0; i < WB_RO_NX; ++i) Xk[i] = x0[(long long)k * x0_stride + i];
    for (int t = 0; t < T; ++t) {
      arg[0] = Xk + (long long)t * WB_RO_NX;
      arg[1] = V + ((long long)k * T + t) * WB_RO_NU;
      arg[2] = scene;
      res[0] = Xk + (long long)(t + 1) * WB_RO_NX;
      if (wb_samples_dyn(arg, res, iw, w, 0)) return 1;
    }
  }
  return 0;
}
"""


def rollout_library(sp: SamplingProblem) -> Library | None:
    """The problem's compiled rollout (cached on disk and per process); None without a C
    compiler (or when the model does not compile: then a warning is logged)."""
    key = sp.fingerprint()
    if key not in _LIBS:
        f = _rollout_function(sp)
        macros = "\n".join([
            f"#define WB_RO_NX {sp.nx}", f"#define WB_RO_NU {sp.nu}",
            f"#define WB_RO_ARG {max(f.sz_arg(), 3)}", f"#define WB_RO_RES {max(f.sz_res(), 1)}",
            f"#define WB_RO_IW {max(f.sz_iw(), 1)}", f"#define WB_RO_W {max(f.sz_w(), 1)}"])
        try:
            lib = build_library(f"samples_{sp.model.name.replace('+', '_')}", [f],
                                macros + "\n" + _ROLLOUT_C)
        except CompileError as exc:
            log.warning("sample rollouts of %s use the CasADi virtual machine: %s",
                        sp.model.name, exc)
            lib = None
        if lib is not None:
            fn = lib.cdll.wb_samples_rollout
            fn.restype = ctypes.c_int
            fn.argtypes = [ctypes.c_int, ctypes.c_int, _DP, ctypes.c_int, _DP, _DP, _DP]
        _LIBS[key] = lib
    return _LIBS[key]


class Rollout:
    """State trajectories (K, T+1, nx) of control sequences V (K, T, nu) from start states
    x0 ((nx,) shared, or (K, nx)) in a scene: ``x_{t+1} = dyn(x_t, v_t, scene)``, the
    problem's own dynamics, compiled (``backend="auto"``) or on the CasADi virtual machine
    (``backend="casadi"``, or "auto" without a C compiler). A scene with moving circles is
    predicted per step (step t in the scene of (t + 1) dt, as the sampler's rollouts), on the
    CasADi virtual machine (the compiled rollout holds one scene)."""

    def __init__(self, sp: SamplingProblem, backend: Literal["auto", "casadi"] = "auto"):
        one_of("backend", backend, ("auto", "casadi"))
        self.sp = sp
        self._moves = predicts(sp.model)
        self.lib = rollout_library(sp) if backend == "auto" and not self._moves else None
        self._f = _rollout_function(sp)
        self._vm: dict[int, FastFunction] = {}

    def __call__(self, x0, V, scene) -> np.ndarray:
        nx, nu = self.sp.nx, self.sp.nu
        V = np.ascontiguousarray(V, dtype=float)
        if V.ndim != 3 or V.shape[2] != nu or V.shape[1] < 1:
            raise fail("V", V.shape, f"expected (K, T >= 1, {nu})")
        K, T = V.shape[:2]
        x0 = np.ascontiguousarray(x0, dtype=float)
        if x0.shape not in ((nx,), (K, nx)):
            raise fail("x0", x0.shape, f"expected ({nx},) or ({K}, {nx})")
        s = np.ascontiguousarray(self.sp.model.scene_vector(scene), dtype=float)
        X = np.empty((K, T + 1, nx))
        if self.lib is not None:
            s_buf = s if s.size else np.zeros(1)
            rc = self.lib.cdll.wb_samples_rollout(K, T, x0.ctypes.data, 0 if x0.ndim == 1 else nx,
                                                  V.ctypes.data, s_buf.ctypes.data,
                                                  X.ctypes.data)
            if rc != 0:
                raise RuntimeError(f"the compiled dynamics of {self.sp.model.name} failed")
            return X
        f = self._vm.get(K)
        if f is None:
            f = self._vm[K] = FastFunction(self._f, K, shared=(2,))
        X[:, 0] = x0
        m = self.sp.model
        for t in range(T):
            st = scene_at(m, s, (t + 1) * m.dt) if self._moves else s
            X[:, t + 1] = f(X[:, t], V[:, t], st)[0].reshape(K, nx)
        return X


def lanes_first(v: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Lanes ``index`` of lane-major samples v (T, nu, N) as (K, T, nu)."""
    return np.ascontiguousarray(np.transpose(np.asarray(v, dtype=float)[:, :, index], (2, 0, 1)))


class SampleRecorder:
    """Keeps ``k`` samples of a batch (``keep``) and rolls their trajectories out; the
    controllers call :meth:`record` at the end of a step (see the module docstring)."""

    def __init__(self, sp: SamplingProblem, k: int = 64, keep: Keep = "spread"):
        self.k = integer("record_samples.k", k, 1, MAX_BATCH)
        self.keep = one_of("record_samples.keep", keep, KEEP)
        self.sp = sp
        self.rollout = Rollout(sp)

    def record(self, *, x0, v, crashed, weights, scene, x0_nominal=None, v_nominal=None,
               crashed_nominal=None, weights_real=None) -> SampleTrajectories:
        """The kept samples of a batch: lane-major controls ``v`` (T, nu, N) applied from
        ``x0``, the batch's crash flags and update weights (N,); with ``x0_nominal`` and
        ``v_nominal`` also the nominal system's samples (the same lanes)."""
        t0 = time.perf_counter()
        w = np.asarray(weights, dtype=float)
        N = w.size
        idx = kept_lanes(N, self.k, self.keep, w)
        V = lanes_first(v, idx)
        nominal = {}
        if v_nominal is not None:
            Vn = lanes_first(v_nominal, idx)
            nominal = {"nominal": self.rollout(x0_nominal, Vn, scene), "controls_nominal": Vn,
                       "crashed_nominal": np.asarray(crashed_nominal)[idx]}
        if weights_real is not None:
            nominal["weights_real"] = np.asarray(weights_real, dtype=float)[idx]
        X = self.rollout(x0, V, scene)
        return SampleTrajectories(
            real=X, controls=V, crashed=np.asarray(crashed)[idx], weights=w[idx], index=idx,
            n_samples=N, keep=self.keep, scene=self.sp.model.scene_vector(scene),
            position=self.sp.model.position, **nominal, time_s=time.perf_counter() - t0)


class RecordsSamples:
    """The opt-in shared by the sampling controllers: :meth:`record_samples`."""

    sp: SamplingProblem
    sample_recorder: SampleRecorder | None = None

    def record_samples(self, k: int = 64, keep: Keep = "spread") -> None:
        """From the next step on, hand out ``k`` sample trajectories of each step's last batch
        as ``info.samples`` (a :class:`SampleTrajectories`; ``keep``: "spread" or "top", see
        :mod:`workbench.sampling.samples`). ``k = 0`` switches recording off (the default:
        ``info.samples`` is None and a step does no extra work). Builds (or loads from the
        cache) the compiled rollout of the problem's dynamics once."""
        if integer("record_samples.k", k, 0, MAX_BATCH) == 0:
            one_of("record_samples.keep", keep, KEEP)
            self.sample_recorder = None
            return
        self.sample_recorder = SampleRecorder(self.sp, k, keep)


__all__ = ["KEEP", "RecordsSamples", "Rollout", "SampleRecorder", "SampleTrajectories",
           "kept_lanes", "lanes_first", "rollout_library"]

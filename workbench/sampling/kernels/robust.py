"""Candidate starts of Robust MPPI's nominal-state selection in one compiled call: the old
nominal state propagated one step, then the lift of every mixed candidate (assumptions §9.3),
for :class:`~workbench.sampling.robust_step.CandidateStarts`. The compiled K_safe of the
feedback law is :mod:`workbench.sampling.feedback.compiled`.
"""

from __future__ import annotations

import ctypes

import casadi as ca
import numpy as np

from workbench.codegen import Library, build_library

_dp = ctypes.c_void_p


STARTS_SOURCE = r"""
#include <stddef.h>

static int wb_starts_call(int (*f)(const casadi_real**, casadi_real**, casadi_int*,
                                   casadi_real*, int),
                          const double* i0, const double* i1, const double* i2, double* o0) {
  const casadi_real* arg[WB_ST_ARG];
  casadi_real* res[WB_ST_RES];
  casadi_int iw[WB_ST_IW];
  casadi_real w[WB_ST_W];
  arg[0] = i0; arg[1] = i1; arg[2] = i2;
  res[0] = o0;
  return f(arg, res, iw, w, 0);
}

/* a1 = F(a0, u0) in the scene */
int wb_starts_propagate(const double* a0, const double* u0, const double* scene, double* a1) {
  return wb_starts_call(wb_starts_dyn1, a0, u0, scene, a1);
}

/* out (nc, NX): the lift of each row of mixed (nc, NPHYS) in the scene */
int wb_starts_lift(int nc, const double* mixed, const double* scene, double* out) {
  for (int i = 0; i < nc; ++i)
    if (wb_starts_call(wb_starts_lift1, mixed + (size_t)i * NPHYS, scene, 0,
                       out + (size_t)i * NX))
      return 1;
  return 0;
}
"""

_STARTS: dict[str, Library | None] = {}


def _dense(name: str, f: ca.Function) -> ca.Function:
    sym = f.sx_in()
    return ca.Function(name, sym, [ca.densify(o) for o in f.call(sym)], f.name_in(),
                       f.name_out())


def starts_library(dyn, lift, nx: int, n_physical: int, key: str) -> Library | None:
    """The candidate-starts library of a sampling problem: its dynamics ``dyn`` (x, u, scene)
    and lift (x_physical, scene), compiled (cached on disk and per process under ``key``, the
    problem's identity); None without a compiler."""
    if key not in _STARTS:
        fd, fl = _dense("wb_starts_dyn1", dyn), _dense("wb_starts_lift1", lift)
        fns = [fd, fl]
        sizes = {k: max([1, *(getattr(f, f"sz_{k.lower()}")() for f in fns)])
                 for k in ("ARG", "RES", "IW", "W")}
        macros = "".join(f"#define WB_ST_{k} {v}\n" for k, v in sizes.items())
        macros += f"#define NX {nx}\n#define NPHYS {n_physical}\n"
        lib = build_library("rmppi_starts", fns, macros + STARTS_SOURCE)
        if lib is not None:
            c = lib.cdll
            c.wb_starts_propagate.restype = ctypes.c_int
            c.wb_starts_propagate.argtypes = [_dp] * 4
            c.wb_starts_lift.restype = ctypes.c_int
            c.wb_starts_lift.argtypes = [ctypes.c_int] + [_dp] * 3
        _STARTS[key] = lib
    return _STARTS[key]


class StartsKernel:
    """The candidate starts of Robust MPPI's selection on prepared buffers: a1 = F(a0, u0),
    then (after the caller's mixing) the lift of every mixture. Not thread-safe."""

    def __init__(self, library: Library, nx: int, nu: int, n_physical: int, n_candidates: int,
                 n_scene: int):
        self._c = library.cdll
        self.nc, self.nx, self.n = n_candidates, nx, n_physical
        self.b = {"a0": np.zeros(nx), "u0": np.zeros(nu), "scene": np.zeros(max(n_scene, 1)),
                  "a1": np.zeros(nx), "mixed": np.zeros((n_candidates, n_physical)),
                  "out": np.zeros((n_candidates, nx))}
        self._a = {k: v.__array_interface__["data"][0] for k, v in self.b.items()}
        self._ns = n_scene

    def propagate(self, a0: np.ndarray, u0: np.ndarray, scene: np.ndarray) -> np.ndarray:
        """F(a0, u0) in ``scene`` (a view of an internal buffer)."""
        b, a = self.b, self._a
        b["a0"][:] = a0
        b["u0"][:] = u0
        b["scene"][: self._ns] = scene
        if self._c.wb_starts_propagate(a["a0"], a["u0"], a["scene"], a["a1"]):
            raise RuntimeError("the candidate propagation failed")
        return b["a1"]

    def lift(self, mixed_physical: np.ndarray) -> np.ndarray:
        """(nc, nx): each row of ``mixed_physical`` (nc, n_physical) lifted in the scene of
        the last :meth:`propagate` (a new array)."""
        b, a = self.b, self._a
        b["mixed"][:] = mixed_physical
        if self._c.wb_starts_lift(self.nc, a["mixed"], a["scene"], a["out"]):
            raise RuntimeError("the candidate lift failed")
        return b["out"].copy()

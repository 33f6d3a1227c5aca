"""The compiled twin: the problem's Functions and core.c in one cached shared library."""

from __future__ import annotations

import ctypes
from importlib import resources

import casadi as ca
import numpy as np

from workbench.codegen import Library, build_library
from workbench.ilqg.reference import step_function
from workbench.problem import FUNCTION_NAMES, Problem

_LIBS: dict[str, Library | None] = {}
_dp = ctypes.c_void_p  # raw addresses: numpy's .ctypes.data_as costs microseconds per call


def row_major_functions(problem: Problem) -> list[ca.Function]:
    """``wb_<name>`` twins of the problem Functions whose matrix outputs are row-major in memory."""
    out = []
    for f in [problem.functions[n] for n in FUNCTION_NAMES] + [step_function(problem)]:
        name = f.name()
        sym = f.sx_in()
        res = [r.T if r.size1() > 1 and r.size2() > 1 else r for r in f.call(sym)]
        out.append(ca.Function(f"wb_{name}", sym, res, f.name_in(), f.name_out(), {"cse": True}))
    return out


def _macros(problem: Problem, fns: list[ca.Function]) -> str:
    sz = {
        "ARG": max([6, *(f.sz_arg() for f in fns)]),
        "RES": max([6, *(f.sz_res() for f in fns)]),
        "IW": max([1, *(f.sz_iw() for f in fns)]),
        "W": max([1, *(f.sz_w() for f in fns)]),
    }
    lines = [f"#define NX {problem.nx}", f"#define NU {problem.nu}",
             f"#define NP {max(problem.n_p, 1)}", f"#define NH {problem.nh}"]
    lines += [f"#define WB_SZ_{k} {v}" for k, v in sz.items()]
    return "\n".join(lines) + "\n"


def problem_library(problem: Problem) -> Library | None:
    """The problem's compiled library (cached on disk and per process); None without a compiler."""
    if problem.fingerprint not in _LIBS:
        fns = row_major_functions(problem)
        core = resources.files("workbench.ilqg").joinpath("core.c").read_text()
        lib = build_library(f"ilqg_{problem.model.name.replace('+', '_')}", fns,
                            _macros(problem, fns) + core)
        if lib is not None:
            _declare(lib.cdll)
        _LIBS[problem.fingerprint] = lib
    return _LIBS[problem.fingerprint]


def _declare(c: ctypes.CDLL) -> None:
    i, d = ctypes.c_int, ctypes.c_double
    c.wb_forward.restype = d
    c.wb_forward.argtypes = [i, _dp, _dp, _dp, _dp, _dp, _dp, d, _dp, _dp, i, _dp, _dp]
    c.wb_derivatives.restype = None
    c.wb_derivatives.argtypes = [i, _dp, _dp, _dp] + [_dp] * 7
    c.wb_line_search.restype = i
    c.wb_line_search.argtypes = [i] + [_dp] * 6 + [d, _dp, _dp, i, d, _dp, _dp, _dp, _dp, _dp]
    c.wb_backward.restype = i
    c.wb_backward.argtypes = [i] + [_dp] * 10 + [d, i, i, _dp, _dp, _dp]
    c.wb_box_qp.restype = i
    c.wb_box_qp.argtypes = [i, _dp, _dp, _dp, _dp, _dp, _dp, _dp, _dp, _dp]


def _ptr(a: np.ndarray) -> int:
    """Address of a C-contiguous float64 (or int32) array's data."""
    return a.__array_interface__["data"][0]


def _c(a) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=float)


class CompiledPasses:
    """Same interface as :class:`~workbench.ilqg.reference.NumpyPasses`, in compiled C.

    Work arrays are allocated once per (problem, horizon) and reused across iterations.
    """

    name = "compiled"

    def __init__(self, problem: Problem, T: int, library: Library):
        nx, nu = problem.nx, problem.nu
        self.problem, self.T, self._c = problem, T, library.cdll
        self._d = {
            "A": np.zeros((T, nx, nx)), "B": np.zeros((T, nx, nu)),
            "lx": np.zeros((T + 1, nx)), "lu": np.zeros((T, nu)),
            "lxx": np.zeros((T + 1, nx, nx)), "luu": np.zeros((T, nu, nu)),
            "lux": np.zeros((T, nu, nx)),
        }
        self._pd = [_ptr(self._d[n]) for n in ("A", "B", "lx", "lu", "lxx", "luu", "lux")]
        self._P_dummy = np.zeros((T + 1, 1))

    def _params(self, P):
        return self._P_dummy if P.shape[1] == 0 else _c(P)

    def derivatives(self, X, U, P):
        X, U, P = _c(X), _c(U), self._params(P)
        self._c.wb_derivatives(self.T, _ptr(X), _ptr(U), _ptr(P), *self._pd)
        return self._d

    def backward(self, d, U, umin, umax, mu, reg, boxed):
        T, nx, nu = self.T, self.problem.nx, self.problem.nu
        k, K, dV = np.zeros((T, nu)), np.zeros((T, nu, nx)), np.zeros(2)
        U, lo, hi = _c(U), _c(umin), _c(umax)
        ptrs = self._pd if d is self._d else [
            _ptr(_c(d[n])) for n in ("A", "B", "lx", "lu", "lxx", "luu", "lux")]
        status = self._c.wb_backward(T, *ptrs, _ptr(U), _ptr(lo), _ptr(hi), float(mu), int(reg),
                                     int(boxed), _ptr(k), _ptr(K), _ptr(dV))
        return status, k, K, dV

    def forward(self, x0, X, U, k, K, P, alpha, umin, umax, use_policy=True):
        x0, X, U, k, K, P = _c(x0), _c(X), _c(U), _c(k), _c(K), self._params(P)
        umin, umax = _c(umin), _c(umax)
        Xn, Un = np.empty_like(X), np.empty_like(U)
        J = self._c.wb_forward(self.T, _ptr(x0), _ptr(X), _ptr(U), _ptr(k), _ptr(K), _ptr(P),
                               float(alpha), _ptr(umin), _ptr(umax), int(use_policy),
                               _ptr(Xn), _ptr(Un))
        return Xn, Un, float(J)

    def line_search(self, x0, X, U, k, K, P, J, dV, alphas, z_min, umin, umax):
        x0, X, U, k, K, P = _c(x0), _c(X), _c(U), _c(k), _c(K), self._params(P)
        umin, umax, dV, a = _c(umin), _c(umax), _c(dV), _c(alphas)
        Xn, Un, out = np.empty_like(X), np.empty_like(U), np.zeros(3)
        i = self._c.wb_line_search(self.T, _ptr(x0), _ptr(X), _ptr(U), _ptr(k), _ptr(K),
                                   _ptr(P), float(J), _ptr(dV), _ptr(a), a.size, float(z_min),
                                   _ptr(umin), _ptr(umax), _ptr(Xn), _ptr(Un), _ptr(out))
        if i < 0:
            return False, X, U, J, 0.0, 0.0
        return True, Xn, Un, float(out[0]), float(out[1]), float(out[2])


def box_qp_compiled(library: Library, H, g, lo, hi, x0):
    """The C box QP (for tests): returns (x, result, free mask)."""
    n = g.size
    x, L = np.zeros(n), np.zeros(n * n)
    free, nf = np.zeros(n, np.int32), np.zeros(1, np.int32)
    H, g, lo, hi, x0 = (_c(a) for a in (H, g, lo, hi, x0))
    res = library.cdll.wb_box_qp(n, _ptr(H), _ptr(g), _ptr(lo), _ptr(hi), _ptr(x0), _ptr(x),
                                 _ptr(free), _ptr(L), _ptr(nf))
    return x, res, free.astype(bool)

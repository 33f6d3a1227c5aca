"""The compiled iLQG passes: the problem's Functions and core.c in one cached shared library
(their twin: :mod:`workbench.ilqg.twin`)."""

from __future__ import annotations

import ctypes
from importlib import resources

import casadi as ca
import numpy as np

from workbench.codegen import Library, build_library
from workbench.ilqg.passes import (
    BackwardResult,
    BoxQPResult,
    ForwardResult,
    LineSearchResult,
    SolveResult,
)
from workbench.ilqg.twin import step_function
from workbench.problem.problem import FUNCTION_NAMES, Problem

_LIBS: dict[str, Library | None] = {}
_dp = ctypes.c_void_p  # raw addresses: numpy's .ctypes.data_as costs microseconds per call


class SolveOptions(ctypes.Structure):
    """The options of the C outer loop: core.c's ``wb_solve_options``, field by field (same
    names, types and order; :func:`solve_options_layout` reports the C side's layout)."""

    _fields_ = [
        ("max_iter", ctypes.c_int),
        ("reg", ctypes.c_int),  # 0 control-space, 1 state-space regularisation
        ("boxed", ctypes.c_int),  # 1: control limits through the box QP
        ("second_order", ctypes.c_int),  # 1: full DDP
        ("gn_fallback", ctypes.c_int),  # 1: a failed second-order step redone as Gauss-Newton
        ("fallback_mu", ctypes.c_double),  # ... failed: not PD for any mu <= fallback_mu
        ("mu_init", ctypes.c_double),
        ("mu_factor", ctypes.c_double),
        ("mu_min", ctypes.c_double),
        ("mu_max", ctypes.c_double),
        ("z_min", ctypes.c_double),
        ("tol_abs", ctypes.c_double),
        ("tol_rel", ctypes.c_double),
        ("tol_grad", ctypes.c_double),
    ]


def solve_options_layout(library: Library) -> tuple[int, tuple[tuple[str, int, int], ...]]:
    """The C layout of ``wb_solve_options``: (sizeof, ((field, offset, size), ...))."""
    out, names = (ctypes.c_longlong * 64)(), ctypes.c_char_p()  # room for 31 fields
    n = library.cdll.wb_solve_options_layout(out, ctypes.byref(names))
    fields = (names.value or b"").decode().split()
    if len(fields) != n:
        raise RuntimeError(f"wb_solve_options_layout reported {n} fields named {fields}")
    return out[0], tuple((f, out[1 + 2 * i], out[2 + 2 * i]) for i, f in enumerate(fields))


def row_major_functions(problem: Problem) -> list[ca.Function]:
    """``wb_<name>`` copies of the problem Functions whose matrix outputs are row-major in memory.

    Every copy takes the scene as its fourth input (the inputs before it padded with empty
    ones), so core.c's ``wb_call`` hands the current scene to each of them in one place."""
    out = []
    for f in [problem.functions[n] for n in FUNCTION_NAMES] + [step_function(problem)]:
        name = f.name()
        sym = f.sx_in()
        names = list(f.name_in())
        res = [r.T if r.size1() > 1 and r.size2() > 1 else r for r in f.call(sym)]
        if "scene" in names:
            i = names.index("scene")
            scene = sym.pop(i)
            names.pop(i)
        else:
            scene = ca.SX.sym("scene", problem.n_scene)
        while len(sym) < 3:
            sym.append(ca.SX(0, 1))
            names.append(f"unused{len(sym)}")
        out.append(ca.Function(f"wb_{name}", [*sym, scene], res, [*names, "scene"],
                               f.name_out(), {"cse": True}))
    return out


def core_macros(problem: Problem, fns: list[ca.Function]) -> str:
    """The C definitions core.c is compiled against: ``NX``, ``NU``, ``NP`` (at least 1),
    ``NH``, the CasADi work-array sizes ``WB_SZ_ARG``/``RES``/``IW``/``W`` (the largest over
    ``fns``, at least 6, 6, 1, 1) and the structural nonzeros of A = dF/dx and B = dF/du."""
    sz = {
        "ARG": max([6, *(f.sz_arg() for f in fns)]),
        "RES": max([6, *(f.sz_res() for f in fns)]),
        "IW": max([1, *(f.sz_iw() for f in fns)]),
        "W": max([1, *(f.sz_w() for f in fns)]),
    }
    lines = [f"#define NX {problem.nx}", f"#define NU {problem.nu}",
             f"#define NP {max(problem.n_p, 1)}", f"#define NH {problem.nh}"]
    lines += [f"#define WB_SZ_{k} {v}" for k, v in sz.items()]
    return "\n".join(lines) + "\n" + _jacobian_patterns(problem)


def _jacobian_patterns(problem: Problem) -> str:
    """Structural nonzeros of A = dF/dx and B = dF/du (compressed columns) for the backward
    pass: its products skip the structural zeros (same sums, same order, so the same results)."""
    m = problem.model
    out = []
    for name, wrt in (("A", m.x), ("B", m.u)):
        sp = ca.jacobian(m.x_next, wrt).sparsity()
        for arr, vals in (("COLIND", sp.colind()), ("ROW", sp.row() or [0])):
            out.append(f"static const int WB_{name}_{arr}[] = {{{', '.join(map(str, vals))}}};")
    return "\n".join(out) + "\n"


def core_source(problem: Problem, fns: list[ca.Function]) -> str:
    """The C text compiled after the generated ``fns`` (:func:`row_major_functions`):
    :func:`core_macros`, then core.c (``wb_call`` with the current scene ``wb_scene``, the
    passes ``wb_forward``, ``wb_derivatives``, ``wb_box_qp``, ``wb_backward``,
    ``wb_line_search`` and the outer loop ``wb_solve``). Another library may append C that
    calls them (:mod:`workbench.sampling.feedback.compiled`)."""
    core = resources.files("workbench.ilqg").joinpath("core.c").read_text()
    return core_macros(problem, fns) + core


def problem_library(problem: Problem) -> Library | None:
    """The problem's compiled library (cached on disk and per process); None without a compiler."""
    if problem.fingerprint not in _LIBS:
        fns = row_major_functions(problem)
        lib = build_library(f"ilqg_{problem.model.name.replace('+', '_')}", fns,
                            core_source(problem, fns))
        if lib is not None:
            _declare(lib.cdll)
        _LIBS[problem.fingerprint] = lib
    return _LIBS[problem.fingerprint]


def _declare(c: ctypes.CDLL) -> None:
    i, d = ctypes.c_int, ctypes.c_double
    c.wb_forward.restype = d
    c.wb_forward.argtypes = [i, _dp, _dp, _dp, _dp, _dp, _dp, d, _dp, _dp, i, _dp, _dp]
    c.wb_derivatives.restype = None
    c.wb_derivatives.argtypes = [i, _dp, _dp, _dp, *[_dp] * 7]
    c.wb_line_search.restype = i
    c.wb_line_search.argtypes = [i] + [_dp] * 6 + [d, _dp, _dp, i, d, _dp, _dp, _dp, _dp, _dp]
    c.wb_backward.restype = i
    c.wb_backward.argtypes = [i, *[_dp] * 10, d, i, i, _dp, _dp, _dp, _dp, i]
    c.wb_solve.restype = None
    c.wb_solve.argtypes = [i, *[_dp] * 7, ctypes.POINTER(SolveOptions), _dp, i, *[_dp] * 16]
    c.wb_solve_options_layout.restype = i
    c.wb_solve_options_layout.argtypes = [ctypes.POINTER(ctypes.c_longlong),
                                          ctypes.POINTER(ctypes.c_char_p)]
    c.wb_box_qp.restype = i
    c.wb_box_qp.argtypes = [i, _dp, _dp, _dp, _dp, _dp, _dp, _dp, _dp, _dp]
    c.wb_set_scene.restype = None
    c.wb_set_scene.argtypes = [_dp]


def _ptr(a: np.ndarray) -> int:
    """Address of a C-contiguous float64 (or int32) array's data."""
    return a.__array_interface__["data"][0]


def _c(a) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=float)


class CompiledPasses:
    """Same interface as :class:`~workbench.ilqg.twin.PassesTwin`, in compiled C.

    Every array the C functions read or write lives in a buffer allocated once per
    (problem, horizon), whose address is looked up once: a call copies its inputs into the
    buffers (a no-op when they already are the buffers) and copies results out.
    """

    name = "compiled"

    def __init__(self, problem: Problem, T: int, library: Library):
        nx, nu = problem.nx, problem.nu
        self.problem, self.T, self._c = problem, T, library.cdll
        shapes = {
            "A": (T, nx, nx), "B": (T, nx, nu), "lx": (T + 1, nx), "lu": (T, nu),
            "lxx": (T + 1, nx, nx), "luu": (T, nu, nu), "lux": (T, nu, nx),
            "X": (T + 1, nx), "U": (T, nu), "P": (T + 1, max(problem.n_p, 1)), "x0": (nx,),
            "k": (T, nu), "K": (T, nu, nx), "dV": (2,), "umin": (nu,), "umax": (nu,),
            "Xn": (T + 1, nx), "Un": (T, nu), "out": (3,), "alphas": (32,),
            "k2": (T, nu), "K2": (T, nu, nx), "J": (1,), "sout": (4,),
            "Xd": (T + 1, nx), "scene": (max(problem.n_scene, 1),),
        }
        self._b = {n: np.zeros(s) for n, s in shapes.items()}
        self._a = {n: _ptr(v) for n, v in self._b.items()}
        self._d = {n: self._b[n] for n in ("A", "B", "lx", "lu", "lxx", "luu", "lux")}
        self._d["X"] = self._b["Xd"]  # the trajectory of the derivatives (second order)
        self._pd = [self._a[n] for n in ("A", "B", "lx", "lu", "lxx", "luu", "lux")]
        self.set_scene(problem.model.scene_value)

    def set_scene(self, scene: np.ndarray) -> None:
        """The scene (flat, ``problem.n_scene``) the following passes use."""
        self._b["scene"][: self.problem.n_scene] = scene

    def _scene(self) -> None:
        # the library's scene pointer is per thread and shared by every CompiledPasses of the
        # same problem: point it at this object's scene before each call
        self._c.wb_set_scene(self._a["scene"])

    def _put(self, name: str, value) -> int:
        buf = self._b[name]
        if value is not buf and not (name == "P" and np.shape(value)[-1] == 0):
            np.copyto(buf, value)
        return self._a[name]

    def derivatives(self, X, U, P):
        self._scene()
        self._c.wb_derivatives(self.T, self._put("X", X), self._put("U", U), self._put("P", P),
                               *self._pd)
        np.copyto(self._b["Xd"], self._b["X"])
        return self._d

    def backward(self, d, U, umin, umax, mu, reg, boxed, second_order=False):
        if d is not self._d:
            for n in self._d:
                np.copyto(self._d[n], d[n])
        self._scene()
        status = self._c.wb_backward(
            self.T, *self._pd, self._put("U", U), self._put("umin", umin),
            self._put("umax", umax), float(mu), int(reg), int(boxed), self._a["k"],
            self._a["K"], self._a["dV"], self._a["Xd"], int(second_order))
        return BackwardResult(status=status, k=self._b["k"].copy(), K=self._b["K"].copy(),
                              dV=self._b["dV"].copy())

    def _policy(self, x0, X, U, k, K, P) -> list[int]:
        return [self._put("x0", x0), self._put("X", X), self._put("U", U), self._put("k", k),
                self._put("K", K), self._put("P", P)]

    def forward(self, x0, X, U, k, K, P, alpha, umin, umax, use_policy=True):
        ptrs = self._policy(x0, X, U, k, K, P)
        self._scene()
        J = self._c.wb_forward(self.T, *ptrs, float(alpha), self._put("umin", umin),
                               self._put("umax", umax), int(use_policy), self._a["Xn"],
                               self._a["Un"])
        return ForwardResult(X=self._b["Xn"].copy(), U=self._b["Un"].copy(), cost=float(J))

    def solve(self, x0, X, U, J, P, umin, umax, options: SolveOptions, alphas):
        """The whole outer loop in C (``wb_solve``), from the accepted rollout (X, U, J)."""
        b, a = self._b, self._a
        self._put("X", X), self._put("U", U), self._put("P", P), self._put("x0", x0)
        b["J"][0] = J
        n = len(alphas)
        b["alphas"][:n] = alphas
        hist = np.empty((options.max_iter, 8))
        self._scene()
        self._c.wb_solve(self.T, a["x0"], a["X"], a["U"], a["J"], a["P"],
                         self._put("umin", umin), self._put("umax", umax),
                         ctypes.byref(options), a["alphas"], n, a["k"], a["K"], _ptr(hist),
                         a["sout"], *self._pd, a["k2"], a["K2"], a["Xn"], a["Un"], a["out"])
        stop, conv, n_hist, mu = b["sout"]
        return SolveResult(X=b["X"].copy(), U=b["U"].copy(), k=b["k"].copy(), K=b["K"].copy(),
                           cost=float(b["J"][0]), stop=int(stop), converged=bool(conv),
                           history=hist[: int(n_hist)].copy(), mu=float(mu))

    def line_search(self, x0, X, U, k, K, P, J, dV, alphas, z_min, umin, umax):
        ptrs = self._policy(x0, X, U, k, K, P)
        n = len(alphas)
        self._b["alphas"][:n] = alphas
        self._scene()
        i = self._c.wb_line_search(self.T, *ptrs, float(J), self._put("dV", dV),
                                   self._a["alphas"], n, float(z_min), self._put("umin", umin),
                                   self._put("umax", umax), self._a["Xn"], self._a["Un"],
                                   self._a["out"])
        if i < 0:
            return LineSearchResult(accepted=False, X=X, U=U, cost=J, alpha=0.0, expected=0.0)
        out = self._b["out"]  # (J_new, alpha, expected), as wb_line_search writes it
        return LineSearchResult(accepted=True, X=self._b["Xn"].copy(), U=self._b["Un"].copy(),
                                cost=float(out[0]), alpha=float(out[1]), expected=float(out[2]))


def box_qp_compiled(library: Library, H, g, lo, hi, x0):
    """The C box QP (for tests); its Cholesky factor is not returned (``L`` is None)."""
    n = g.size
    x, L = np.zeros(n), np.zeros(n * n)
    free, nf = np.zeros(n, np.int32), np.zeros(1, np.int32)
    H, g, lo, hi, x0 = (_c(a) for a in (H, g, lo, hi, x0))
    res = library.cdll.wb_box_qp(n, _ptr(H), _ptr(g), _ptr(lo), _ptr(hi), _ptr(x0), _ptr(x),
                                 _ptr(free), _ptr(L), _ptr(nf))
    return BoxQPResult(x=x, result=res, free=free.astype(bool))

"""Exponential control barrier function (ECBF) safety filter, assumptions §7.

The discrete model is read as the continuous-time control-affine system
``f(x) + g(x) u = (F(x, u) - x) / dt`` (exact for Euler; validated affine in u). For every margin
h_i the filter uses exact Lie derivatives from CasADi:

* relative degree 1:  L_f h + L_g h u >= -gamma h                      (assumptions §7.3)
* relative degree 2:  L_f^2 h + (L_g L_f h + k1 L_g h) u + k1 L_f h + k0 h >= 0
  with s^2 + k1 s + k0 = (s + p1)(s + p2)                              (assumptions §7.1)

The relative degree of each margin is read from the discrete model (:func:`relative_degrees`):
a zero-order-hold double integrator is degree 2 although u enters its first difference at
O(dt^2).

Each row reads ``a_i^T u >= b_i``. The QP ``min ||u - u_ref||^2`` subject to these rows and the
control box is solved by OSQP, set up once with a fixed sparsity pattern; each step updates only
q, the values of the ECBF rows and their bounds. Soft mode (default) adds slacks delta_i >= 0 (see
:class:`ECBFOptions` for their cost); hard mode falls back to clip(u_ref) when OSQP fails. Either
way the filter returns a :class:`FilterResult` and never prints or raises on an infeasible step.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import casadi as ca
import numpy as np
import osqp
import scipy.sparse as sp

from workbench.codegen.fastcall import bind
from workbench.problem.models import Model
from workbench.validation import fail, flag, integer, one_of, real

Mode = Literal["soft", "hard"]
RelativeDegree = Literal["auto", 1, 2]
_USABLE = ("solved", "solved inaccurate")
MAX_OSQP_ITER = 10**6  # OSQP iterations per filter step (default 4000)
_ANSWERS = ("primal infeasible", "primal infeasible inaccurate")  # a valid verdict, not an error


@dataclass(frozen=True)
class ECBFOptions:
    """ECBF filter settings; defaults assumptions §7 ([A]: poles, gamma; solver settings from
    assumptions §7.2).

    poles: (p1, p2) > 0 for relative degree 2, so k1 = p1 + p2 and k0 = p1 p2 ([A] 5, 5).
    gamma: class-K gain for relative degree 1 ([A] 5).
    relative_degree: "auto" (per margin, from the discrete model: :func:`relative_degrees`),
    or 1 / 2 for every margin (checked against the detected degree).
    mode: "soft" (slacks delta >= 0) or "hard" (fall back to clip(u_ref) when OSQP fails).
    slack_linear, slack_quadratic: soft-mode slack cost sum(slack_linear delta + slack_quadratic
    delta^2), on rows normalised to ||a_i|| = 1 (delta in control units). [A], not
    assumptions §7.2's
    rho = 1e6 * delta^2: with that weight OSQP (first-order ADMM) hit its iteration limit on
    about half of realistic infeasible instances, and the quadratic term alone leaves
    delta = y / (2 rho) > 0 on every active step, flagging feasible steps as infeasible. The
    linear term is an exact penalty: delta = 0 whenever the hard QP is feasible (multipliers
    stay far below 1e3), and otherwise u is the least-violation control, as with rho -> inf.
    slack_tol: a step whose slack (the violation of a normalised row at the returned u) exceeds
    it is infeasible. eps_abs also bounds the violation the shortcut accepts (ECBFFilter).
    max_iter: OSQP's iteration limit per step, in [1, :data:`MAX_OSQP_ITER`].
    """

    poles: tuple[float, float] = (5.0, 5.0)
    gamma: float = 5.0
    relative_degree: RelativeDegree = "auto"
    mode: Mode = "soft"
    slack_linear: float = 1e3
    slack_quadratic: float = 1.0
    slack_tol: float = 1e-6
    eps_abs: float = 1e-6
    eps_rel: float = 1e-6
    polish: bool = True
    warm_start: bool = True
    max_iter: int = 4000

    def __post_init__(self) -> None:
        allowed = "need two finite poles p1, p2 > 0"
        if isinstance(self.poles, str) or not hasattr(self.poles, "__len__"):
            raise fail("ECBFOptions.poles", self.poles, allowed)
        if any(isinstance(v, bool | np.bool_) for v in self.poles):
            raise fail("ECBFOptions.poles", self.poles, allowed + " (numbers, not true/false)")
        p = np.asarray(self.poles, dtype=float)
        if p.shape != (2,) or not np.all(np.isfinite(p)) or np.any(p <= 0):
            raise fail("ECBFOptions.poles", self.poles, allowed)
        object.__setattr__(self, "poles", (float(p[0]), float(p[1])))
        real("ECBFOptions.gamma", self.gamma, 0.0, strict=True)
        if isinstance(self.relative_degree, str):
            one_of("ECBFOptions.relative_degree", self.relative_degree, ("auto",))
        else:  # or a fixed degree, 1 or 2
            integer("ECBFOptions.relative_degree", self.relative_degree, 1, 2)
        one_of("ECBFOptions.mode", self.mode, ("soft", "hard"))
        real("ECBFOptions.slack_linear", self.slack_linear, 0.0, strict=True)
        real("ECBFOptions.slack_quadratic", self.slack_quadratic, 0.0)
        for name in ("slack_tol", "eps_abs", "eps_rel"):
            real(f"ECBFOptions.{name}", getattr(self, name), 0.0, strict=True)
        flag("ECBFOptions.polish", self.polish)
        flag("ECBFOptions.warm_start", self.warm_start)
        integer("ECBFOptions.max_iter", self.max_iter, 1, MAX_OSQP_ITER)

    @property
    def k0(self) -> float:
        return self.poles[0] * self.poles[1]

    @property
    def k1(self) -> float:
        return self.poles[0] + self.poles[1]


@dataclass(frozen=True)
class FilterResult:
    """One filtered step: the applied control and how it was obtained.

    status: "unconstrained" (u_ref feasible), "box" (clip(u_ref) feasible), an OSQP status
    ("solved", ...), or "fallback: <OSQP status>" (u = clip(u_ref)). slack (nh,): violation of
    each ECBF row at u, max(0, b_i - a_i u) / ||a_i|| (control units; the soft QP's delta).
    infeasible: some slack > slack_tol, or a fallback. active_rows: ECBF rows binding (or
    violated) at u; empty when the shortcut applies.
    """

    u: np.ndarray
    status: str
    slack: np.ndarray
    active_rows: tuple[int, ...]
    infeasible: bool
    fallback_used: bool


@dataclass(frozen=True, eq=False)
class ECBFRows:
    """The ECBF rows a(x) (nh, nu), b(x) (nh,) of a model, and the Lie derivatives behind them.

    ``rows``: (x, scene) -> (a, b). ``lie``: (x, scene) -> (h, Lf h, Lf^2 h, Lg h (nh,nu),
    Lg Lf h (nh,nu)). ``relative_degrees``: one entry (1 or 2) per margin. ``scene_value``: the
    model's default scene, used when a call gives none.
    """

    rows: ca.Function
    lie: ca.Function
    relative_degrees: tuple[int, ...]
    scene_value: np.ndarray

    def __call__(self, x, scene=None) -> tuple[np.ndarray, np.ndarray]:
        s = self.scene_value if scene is None else np.asarray(scene, dtype=float)
        a, b = self.rows(np.asarray(x, dtype=float), s)
        return np.asarray(a), np.asarray(b).ravel()

    def batch(self, X, scene=None) -> tuple[np.ndarray, np.ndarray]:
        """Rows at many states X (N, nx): a (N, nh, nu), b (N, nh)."""
        X = np.asarray(X, dtype=float)
        s = self.scene_value if scene is None else np.asarray(scene, dtype=float)
        n, nh = X.shape[0], self.rows.size1_out(1)
        nu = self.rows.size2_out(0)
        a, b = self.rows.map("rows", "serial", n, [1], [])(X.T, s)
        a = np.asarray(a).reshape(nh, n, nu).transpose(1, 0, 2)
        return a, np.asarray(b).T.reshape(n, nh)


def control_affine(model: Model) -> tuple[ca.SX, ca.SX]:
    """Drift f(x) (nx,) and input matrix g(x) (nx, nu) of (F(x,u) - x)/dt = f(x) + g(x) u."""
    xdot = (model.x_next - model.x) / model.dt
    g = ca.jacobian(xdot, model.u)
    if ca.depends_on(g, model.u):
        raise fail("model.x_next", model.name,
                   "the ECBF filter needs dynamics affine in u: d/du (F - x)/dt depends on u")
    f = ca.substitute(xdot, model.u, ca.DM.zeros(model.nu))
    return ca.simplify(f), ca.simplify(g)


def _identically_zero(e: ca.SX) -> bool:
    e = ca.simplify(ca.SX(e))
    return e.nnz() == 0 or e.is_zero()


DEGREE_POINTS = 32  # random states of the relative-degree order test
_ORDER_SPLIT = 1.5  # log2 sensitivity ratio: ~1 for relative degree 1, ~2 for degree 2


def unreached_margins(model: Model) -> tuple[int, ...]:
    """The margins the control does not reach within two steps (h after one and after two
    steps of the held control both independent of u, symbolically): no ECBF row of degree 1
    or 2 can constrain them."""
    x, u = model.x, model.u
    h1 = ca.substitute(model.h, x, model.x_next)
    h2 = ca.substitute(model.h, x, ca.substitute(model.x_next, x, model.x_next))
    s1, s2 = ca.jacobian(h1, u), ca.jacobian(h2, u)
    return tuple(i for i in range(model.nh)
                 if _identically_zero(s1[i, :]) and _identically_zero(s2[i, :]))


def relative_degrees(model: Model) -> tuple[int, ...]:
    """Relative degree (1 or 2) of every margin, read from the discrete model itself.

    Margin i has degree 2 when its first difference h_i(F(x, u)) - h_i(x) does not depend on u
    (Euler double integrator), and degree 1 when it does at first order in dt. A zero-order-hold
    double integrator's first difference does depend on u, but only through the
    1/2 dt^2 u position term: the effect of u on h after one step is O(dt^2), the signature of
    degree 2 (a degree-1 margin responds at O(dt)). The order is measured on the model: with
    the control held, F(F(x, u), u) is the model over 2 dt, so the sensitivity
    d h(F(F(x,u),u))/du over d h(F(x,u))/du is about 2^r for a margin of degree r; the median
    over seeded random states decides (log2 ratio above 1.5: degree 2).
    """
    x, u = model.x, model.u
    h1 = ca.substitute(model.h, x, model.x_next)
    x2 = ca.substitute(model.x_next, x, model.x_next)
    h2 = ca.substitute(model.h, x, x2)
    s1, s2 = ca.jacobian(h1, u), ca.jacobian(h2, u)
    sens = ca.Function("sens", [x, u], [ca.substitute(s1, model.scene, model.scene_value),
                                        ca.substitute(s2, model.scene, model.scene_value)])
    rng = np.random.default_rng(20261123)
    X = rng.normal(0.0, 2.0, (DEGREE_POINTS, model.nx))
    u0 = np.clip(np.zeros(model.nu), model.u_min, model.u_max)
    pairs = [tuple(np.asarray(v) for v in sens(xk, u0)) for xk in X]
    degrees = []
    for i in range(model.nh):
        if _identically_zero(s1[i, :]):
            degrees.append(2)
            continue
        ratios = []
        for a, b in pairs:
            na, nb = np.linalg.norm(a[i]), np.linalg.norm(b[i])
            if np.isfinite(na) and np.isfinite(nb) and na > 0 and nb > 0:
                ratios.append(np.log2(nb / na))
        degrees.append(2 if ratios and np.median(ratios) > _ORDER_SPLIT else 1)
    return tuple(degrees)


def ecbf_rows(model: Model, options: ECBFOptions = ECBFOptions()) -> ECBFRows:
    """Exact ECBF rows for every margin of ``model`` (relative degree 1 or 2, detected by
    :func:`relative_degrees`).

    Degree 1: L_g h u >= -gamma h - L_f h (the CBF condition h_dot >= -gamma h).
    Degree 2: (L_g L_f h + k1 L_g h) u >= -L_f^2 h - k1 L_f h - k0 h, the ECBF condition
    h_ddot + k1 h_dot + k0 h >= 0 with h_dot = L_f h + L_g h u; L_g h is zero for an Euler
    double integrator and the O(dt) discretisation term for a zero-order-hold one.
    """
    if model.nh == 0:
        raise fail("model.h", model.name, "the ECBF filter needs at least one safety margin")
    x = model.x
    f, g = control_affine(model)
    h = model.h
    lfh = ca.mtimes(ca.jacobian(h, x), f)
    lgh = ca.mtimes(ca.jacobian(h, x), g)
    lf2h = ca.mtimes(ca.jacobian(lfh, x), f)
    lglfh = ca.mtimes(ca.jacobian(lfh, x), g)
    detected = relative_degrees(model)
    a_rows, b_rows = [], []
    for i, deg in enumerate(detected):
        if deg == 2 and _identically_zero(lglfh[i, :]) and _identically_zero(lgh[i, :]):
            raise fail("model.h", i, "relative degree above 2 is not supported")
        if options.relative_degree != "auto" and options.relative_degree != deg:
            raise fail("ECBFOptions.relative_degree", options.relative_degree,
                       f"margin {i} has relative degree {deg} in the discrete model")
        if deg == 1:
            a_rows.append(lgh[i, :])
            b_rows.append(-options.gamma * h[i] - lfh[i])
        else:
            a_rows.append(lglfh[i, :] + options.k1 * lgh[i, :])
            b_rows.append(-lf2h[i] - options.k1 * lfh[i] - options.k0 * h[i])
    d = ca.densify
    sc = model.scene
    rows = ca.Function("ecbf_rows", [x, sc], [d(ca.vertcat(*a_rows)), d(ca.vertcat(*b_rows))],
                       ["x", "scene"], ["a", "b"], {"cse": True})
    lie = ca.Function("ecbf_lie", [x, sc], [d(h), d(lfh), d(lf2h), d(lgh), d(lglfh)],
                      ["x", "scene"], ["h", "Lfh", "Lf2h", "Lgh", "LgLfh"], {"cse": True})
    return ECBFRows(rows=rows, lie=lie, relative_degrees=detected,
                    scene_value=model.scene_value.copy())


class ECBFFilter:
    """The ECBF-QP safety filter with one OSQP workspace, set up once.

    Variables z = [u (nu); delta (nh)] in soft mode, z = u in hard mode. Constraint rows:
    ECBF rows a_i u (+ delta_i) >= b_i; delta_i >= 0 (soft); u_min <= u <= u_max.
    The only mutable state is the OSQP workspace (its warm start).

    Shortcut: when clip(u_ref) satisfies every (normalised) row to within eps_abs it is the
    QP's minimiser (it minimises the strictly convex objective over the box), so OSQP is not
    called. Besides saving time, this keeps OSQP away from QPs without an active constraint,
    where it prints "Polishing not needed" to stdout and returns an unpolished point.
    """

    def __init__(self, model: Model, options: ECBFOptions = ECBFOptions()):
        self.options, self.model = options, model
        self.ecbf = ecbf_rows(model, options)
        self.nu, self.nh = model.nu, model.nh
        self.u_min, self.u_max = model.u_min.copy(), model.u_max.copy()
        # low-overhead evaluation of the rows (about 1 us instead of tens through __call__)
        self._x = np.zeros(model.nx)
        self._a_t = np.zeros((self.nu, self.nh))  # CasADi writes a column-major: a^T row-major
        self._b = np.zeros(self.nh)
        self._scene = model.scene_value.copy()
        self._buf, self._eval = self.ecbf.rows.buffer()
        bind(self._buf, (self._x, self._scene), (self._a_t, self._b))
        self._setup()

    def _setup(self) -> None:
        nu, nh, soft = self.nu, self.nh, self.options.mode == "soft"
        ns = nh if soft else 0
        n, m = nu + ns, nh + ns + nu
        data: list[float] = []
        indices: list[int] = []
        indptr = [0]
        self._a_pos = np.zeros((nh, nu), dtype=np.int64)
        for j in range(nu):  # u columns: dense ECBF block, then the box row
            for i in range(nh):
                self._a_pos[i, j] = len(data)
                data.append(1.0)
                indices.append(i)
            data.append(1.0)
            indices.append(nh + ns + j)
            indptr.append(len(data))
        for i in range(ns):  # slack columns: ECBF row i and the row delta_i >= 0
            data += [1.0, 1.0]
            indices += [i, nh + i]
            indptr.append(len(data))
        A = sp.csc_matrix((np.array(data), np.array(indices), np.array(indptr)), shape=(m, n))
        o = self.options
        P = sp.diags(np.r_[2.0 * np.ones(nu), 2.0 * o.slack_quadratic * np.ones(ns)])
        self._q = np.r_[np.zeros(nu), o.slack_linear * np.ones(ns)]
        self._l = np.r_[np.zeros(nh + ns), self.u_min]
        upper = np.r_[np.full(nh + ns, np.inf), self.u_max]
        self._Ax = np.array(data)
        self._solver = osqp.OSQP()
        self._solver.setup(sp.triu(P, format="csc"), self._q, A, self._l, upper,
                           verbose=False, eps_abs=o.eps_abs, eps_rel=o.eps_rel,
                           polishing=o.polish, warm_starting=o.warm_start, max_iter=o.max_iter)

    def set_scene(self, scene) -> None:
        """The obstacles of the following calls (see
        :meth:`~workbench.problem.Model.scene_vector`)."""
        self._scene[:] = self.model.scene_vector(scene)

    def __call__(self, x, u_ref) -> FilterResult:
        """Filter u_ref at state x (in the scene last set, default the model's own)."""
        return self.solve_rows(*self.rows(x), u_ref)

    def _state(self, x) -> np.ndarray:
        """x as (nx,) finite floats, or ValueError naming x (before anything reaches OSQP)."""
        nx = self._x.size
        try:
            xa = np.asarray(x, dtype=float)
        except (TypeError, ValueError) as exc:
            raise fail("x", x, f"the state must be {nx} finite numbers") from exc
        if xa.shape != (nx,):
            raise fail("x", x, f"the state must have shape ({nx},), got {xa.shape}")
        if not np.isfinite(xa).all():
            raise fail("x", x, f"the state must be {nx} finite numbers (NaN/inf given)")
        return xa

    def rows(self, x) -> tuple[np.ndarray, np.ndarray]:
        """ECBF rows a (nh, nu), b (nh,) at x (same values as ``self.ecbf(x)``)."""
        self._x[:] = self._state(x)
        self._eval()
        return self._a_t.T.copy(), self._b.copy()

    def solve_rows(self, a: np.ndarray, b: np.ndarray, u_ref) -> FilterResult:
        """min ||u - u_ref||^2 s.t. a u >= b (soft or hard) and the box; a (nh,nu), b (nh,)."""
        u_ref = np.asarray(u_ref, dtype=float).ravel()
        if u_ref.shape != (self.nu,) or not np.isfinite(u_ref).all():
            raise fail("u_ref", u_ref, f"expected {self.nu} finite entries")
        a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float).ravel()
        if a.shape != (self.nh, self.nu) or not np.isfinite(a).all():
            raise fail("a", a, f"ECBF rows must be ({self.nh}, {self.nu}) finite numbers")
        if b.shape != (self.nh,) or not np.isfinite(b).all():
            raise fail("b", b, f"ECBF bounds must be {self.nh} finite numbers")
        u_box = np.minimum(np.maximum(u_ref, self.u_min), self.u_max)
        norms = np.maximum(np.sqrt((a * a).sum(axis=1)), 1e-12)
        violation = (b - a @ u_box) / norms
        if (violation <= self.options.eps_abs).all():  # the shortcut (class docstring)
            status = "unconstrained" if (u_box == u_ref).all() else "box"
            return FilterResult(u=u_box, status=status, slack=np.maximum(violation, 0.0),
                                active_rows=(), infeasible=False, fallback_used=False)
        an, bn = a / norms[:, None], b / norms  # rows with ||a_i|| = 1
        u, status, fallback = self._qp(an, bn, u_ref)
        residual = bn - an @ u
        slack = np.maximum(residual, 0.0)
        tol = self.options.slack_tol
        active = tuple(np.flatnonzero(residual >= -tol).tolist())
        return FilterResult(u=u, status=status, slack=slack, active_rows=active,
                            infeasible=bool(fallback or (slack > tol).any()),
                            fallback_used=fallback)

    def _qp(self, an: np.ndarray, bn: np.ndarray, u_ref: np.ndarray) -> tuple:
        """OSQP on normalised rows: (u in the box, status, fallback used).

        A status other than solved or (hard mode) primal infeasible is a solver error that may
        leave the workspace unusable (e.g. a non-quasidefinite KKT matrix after bad data, a
        diverged warm start): the workspace is set up afresh and the QP solved once more, so
        no step can poison the steps after it. An interrupt raises KeyboardInterrupt.
        """
        nu = self.nu
        self._q[:nu] = -2.0 * u_ref
        self._l[: self.nh] = bn
        self._Ax[self._a_pos] = an
        q, lo, Ax = self._q.copy(), self._l.copy(), self._Ax.copy()
        u, status = self._solve_once()
        if status not in _USABLE and status not in _ANSWERS:
            self._setup()
            self._q[:], self._l[:], self._Ax[:] = q, lo, Ax
            u, status = self._solve_once()
            if status not in _USABLE and status not in _ANSWERS:
                self._setup()  # leave a clean workspace for the next step
        fallback = status not in _USABLE or u.shape != (nu,) or not np.isfinite(u).all()
        if fallback:
            u, status = u_ref, f"fallback: {status}"
        return np.minimum(np.maximum(u, self.u_min), self.u_max), status, fallback

    def _solve_once(self) -> tuple[np.ndarray, str]:
        self._solver.update(q=self._q, l=self._l, Ax=self._Ax)
        res = self._solver.solve(raise_error=False)
        status = res.info.status
        if res.info.status_val == osqp.SolverStatus.OSQP_SIGINT or status == "interrupted":
            # OSQP catches SIGINT inside its solve and returns "interrupted"; falling back would
            # turn a Ctrl-C into a normal-looking step. Leave a fresh workspace and re-raise.
            self._setup()
            raise KeyboardInterrupt("ECBF filter: the QP solve was interrupted (SIGINT)")
        u = np.asarray(res.x, dtype=float)[: self.nu]
        if u.shape == (self.nu,) and not np.isfinite(u).all() and status in _USABLE:
            status = "solved with non-finite x"
        return u, status

    def filter_batch(self, X, U_ref) -> BatchFilterResult:
        """Filter N (state, reference) pairs; identical to calling the filter on each in order
        (same shortcut, same OSQP calls in the same order), with less per-step overhead."""
        X, U_ref = np.asarray(X, dtype=float), np.asarray(U_ref, dtype=float)
        nx = self._x.size
        if X.ndim != 2 or X.shape[1] != nx:
            raise fail("X", X, f"states must have shape (N, {nx}), got {X.shape}")
        if not np.isfinite(X).all():
            bad = int(np.flatnonzero(~np.isfinite(X).all(axis=1))[0])
            raise fail("X", X, f"states must be finite (row {bad} is not)")
        if U_ref.shape != (X.shape[0], self.nu) or not np.all(np.isfinite(U_ref)):
            raise fail("U_ref", U_ref, f"expected ({X.shape[0]}, {self.nu}) finite entries")
        a, b = self.ecbf.batch(X, self._scene)
        U = np.clip(U_ref, self.u_min, self.u_max)
        norms = np.maximum(np.sqrt((a * a).sum(axis=2)), 1e-12)
        violation = (b - np.einsum("nij,nj->ni", a, U)) / norms
        solved = ~np.all(violation <= self.options.eps_abs, axis=1)
        fallback = np.zeros(X.shape[0], dtype=bool)
        an, bn = a / norms[:, :, None], b / norms
        for i in np.flatnonzero(solved):
            U[i], _, fallback[i] = self._qp(an[i], bn[i], U_ref[i])
        slack = np.where(solved[:, None], np.maximum(0.0, bn - np.einsum("nij,nj->ni", an, U)),
                         np.maximum(violation, 0.0))
        infeasible = fallback | np.any(slack > self.options.slack_tol, axis=1)
        return BatchFilterResult(u=U, slack=slack, infeasible=infeasible, fallback_used=fallback,
                                 qp_solved=solved)


@dataclass(frozen=True)
class BatchFilterResult:
    """Filtered controls for N pairs: u (N,nu), slack (N,nh), flags (N,), qp_solved (N,)."""

    u: np.ndarray
    slack: np.ndarray
    infeasible: np.ndarray
    fallback_used: np.ndarray
    qp_solved: np.ndarray

"""The ECBF feedback law of Robust MPPI (what it shares with the AL law:
:mod:`workbench.sampling.feedback`).

* :class:`ECBFFeedback` — the gains of the ECBF-QP filter (:mod:`workbench.filters.ecbf`)
  wrapped around the tracking law u_ref = u*_k + K_k (x - x*_k), linearised at x*_k with the
  filter's active set held fixed: d pi_k / dx at x*_k by implicit differentiation of the QP's
  KKT system (Fiacco 1976; Amos & Kolter 2017, arXiv:1703.00443).

Moving circles (a scene with moving slots): the tracking law's rollout predicts them
(:class:`~workbench.sampling.feedback.ilqg.ILQGFeedback`), the filter's rows along the nominal
use the present scene (the ECBF of a moving circle would need its velocity in the derivatives
of h, which the filter does not model).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import casadi as ca
import daqp
import numpy as np

from workbench.codegen.fastcall import FastFunction
from workbench.filters.ecbf import ECBFFilter, ECBFOptions
from workbench.problem.models import Model
from workbench.sampling.feedback.base import (
    FeedbackWeights,
    Gains,
    check_plain_law,
    fallback_gains,
    pad_gains,
)
from workbench.sampling.feedback.effect import differs
from workbench.sampling.feedback.ilqg import ILQGFeedback
from workbench.validation import as_array, fail


def _kkt_matrix(H: np.ndarray, E: np.ndarray) -> np.ndarray:
    """[H -E^T; E 0]."""
    n, q = H.shape[0], E.shape[0]
    M = np.zeros((n + q, n + q))
    M[:n, :n], M[:n, n:], M[n:, :n] = H, -E.T, E
    return M


_CHUNK = 16  # states per batched row-Jacobian call


def _solve_kkt(M: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """M z = rhs; least squares when the held rows are dependent (M singular). Any z with
    M z = rhs has the same control part (H is positive definite), so a direct solve whose
    residual is small is as good as the least-squares one."""
    try:
        z = np.linalg.solve(M, rhs)
        tol = 1e-10 * max(1.0, float(np.abs(rhs).max()), float(np.abs(M).max()))
        if np.all(np.isfinite(z)) and np.abs(M @ z - rhs).max() <= tol * max(
                1.0, float(np.abs(z).max())):
            return z
    except np.linalg.LinAlgError:
        pass
    return np.linalg.lstsq(M, rhs, rcond=None)[0]


def _solve_kkt_batch(M: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """:func:`_solve_kkt` of each M (N, n, n), rhs (N, n, m), with the same direct solve,
    residual test and least-squares fallback."""
    try:
        z = np.linalg.solve(M, rhs)
    except np.linalg.LinAlgError:  # one M is singular: each on its own
        return np.array([_solve_kkt(m, r) for m, r in zip(M, rhs, strict=True)])
    with np.errstate(invalid="ignore", over="ignore"):
        tol = 1e-10 * np.fmax(np.fmax(1.0, np.abs(rhs).max(axis=(1, 2))),
                              np.abs(M).max(axis=(1, 2)))
        resid = np.abs(M @ z - rhs).max(axis=(1, 2))
        ok = np.isfinite(z).all(axis=(1, 2)) & (
            resid <= tol * np.fmax(1.0, np.abs(z).max(axis=(1, 2))))
    for i in np.flatnonzero(~ok):
        z[i] = np.linalg.lstsq(M[i], rhs[i], rcond=None)[0]
    return z


@dataclass(frozen=True)
class FilterSensitivity:
    """d pi / dx of the ECBF-QP at one state with its active set held fixed.

    gain (nu, nx); u: the QP's solution, recomputed on the active set; hard: ECBF rows held as
    equalities; soft: rows violated at u (soft mode, infeasible QP: positive slacks);
    box_upper / box_lower: control indices held at a bound."""

    gain: np.ndarray
    u: np.ndarray
    hard: tuple[int, ...]
    soft: tuple[int, ...]
    box_upper: tuple[int, ...]
    box_lower: tuple[int, ...]


def _pair(sens: FilterSensitivity | None) -> tuple[np.ndarray, bool] | None:
    """(gain, infeasible: some row violated) of a sensitivity."""
    return None if sens is None else (sens.gain, bool(sens.soft))


class ECBFFeedback:
    """Gains of the ECBF-QP filter wrapped around the plain iLQG tracking law.

    At step k the filtered control is pi_k(x) = argmin_u |u - (u*_k + K_k (x - x*_k))|² s.t.
    the ECBF rows a_i(x)^T u >= b_i(x) (:func:`~workbench.filters.ecbf.ecbf_rows`, normalised
    to |a_i| = 1 as in :class:`~workbench.filters.ecbf.ECBFFilter`; soft mode adds the same
    slack cost) and the control box; K_k are the tracking gains of
    :class:`~workbench.sampling.feedback.ilqg.ILQGFeedback` on the same model. The returned gain is
    d pi_k/dx at x*_k with the QP's active set there (u_ref = u*_k) held fixed. With active
    rows A (ECBF rows and box bounds with a positive multiplier) and no violated rows it is

        d pi/dx = (I - P)(K + sum_i lambda_i da_i/dx) + A^+ (db/dx - (da/dx) pi(x*)),

    P = A^+ A, lambda the multipliers of pi - u_ref = A^T lambda: the tracking gain projected
    onto the active rows' null space, the rows' own motion, and the turn of that null space as
    a_i(x) rotates (zero for constant rows, not for circles). It is computed from the QP's KKT
    system with the active set fixed (least squares where dependent active rows make it
    singular: the control part of the solution is still unique); rows violated in an
    infeasible soft QP enter through their slack cost. Row Jacobians: CasADi's, of the filter's
    own row Function.

    The QP at x*_k is solved exactly by daqp (dual active set) on the rows that can bind
    somewhere in the box (the others cannot be active), the QP of ECBFFilter (which OSQP
    solves to its tolerance); should daqp fail, ECBFFilter itself is used. As in the filter,
    steps where clip(u*_k) satisfies every row to within ``eps_abs`` are unconstrained and keep
    K_k; so do box bounds that are merely touched (zero multiplier): the sampler clips every
    control, which reproduces the box to first order. In hard mode an infeasible step falls
    back to clip(u_ref), as the filter does, and keeps K_k.

    Only the gains enter the sampler: the feedforward offset pi_k(x*_k) - u*_k (nonzero where a
    row is active) cannot be represented by SAIS' u* + K (x - x*) and is not applied.

    Fallbacks as in :class:`~workbench.sampling.feedback.ilqg.ILQGFeedback` (reasons from
    ``FALLBACK_REASONS``): when the tracking gains fall back, or the row Jacobians or the
    filtered gains are not finite, the previous gains are shifted by the stride.

    Activity: ``ecbf_active`` — the share of horizon steps whose gain the filter changed: some
    ECBF row is active there and the filter's gain differs from the tracking gain K_k
    (:func:`~workbench.sampling.feedback.effect.differs`; a hard-mode infeasible step keeps
    K_k and does not count); ``ecbf_infeasible`` — the share where the QP is infeasible
    (positive slacks, or the hard-mode fallback), an event. Robust MPPI counts both only on
    steps where the gains reach the plant (the nominal state differs from the measured one).
    """

    def __init__(self, model: Model, horizon: int, nx_full: int,
                 weights: FeedbackWeights = FeedbackWeights(),
                 ecbf: ECBFOptions = ECBFOptions(),  # noqa: B008 (frozen)
                 name: str = "ecbf"):
        check_plain_law(model, horizon, nx_full, weights, "ECBFFeedback")
        if not isinstance(ecbf, ECBFOptions):
            raise fail("ecbf", ecbf, "must be an ECBFOptions")
        self.model, self.name, self.opt = model, name, ecbf
        self.T, self.nx_full = horizon, nx_full
        self.nx, self.nu, self.nh = model.nx, model.nu, model.nh  # (Model computes them)
        self.tracking = ILQGFeedback(model, horizon, model.nx, weights, name="ilqg")
        self.filter = ECBFFilter(model, ecbf)
        x = ca.SX.sym("x", self.nx)
        s = ca.SX.sym("scene", model.n_scene)
        a, b = self.filter.ecbf.rows(x, s)
        norm = ca.fmax(ca.sqrt(ca.sum2(a * a)), 1e-12)  # as ECBFFilter normalises them
        an, bn = a / norm, b / norm
        rows = ca.Function("ecbf_rows_normalised", [x, s], [an, bn], {"cse": True})
        self._rows = FastFunction(rows, horizon, shared=(1,))
        jac = ca.Function("ecbf_row_jacobians", [x, s],
                          [an, bn, ca.jacobian(ca.vec(an), x), ca.jacobian(bn, x)], {"cse": True})
        self._jac = FastFunction(jac)
        self._chunk = min(horizon, _CHUNK)
        self._jac_batch = FastFunction(jac, self._chunk, shared=(1,))
        self.set_scene(None)

    def set_scene(self, scene) -> None:
        """The obstacles of the tracking gains, the filter and its rows (see
        :meth:`~workbench.problem.Model.scene_vector`; None: the model's own)."""
        self._scene = self.model.scene_vector(scene)
        self.tracking.set_scene(self._scene)
        self.filter.set_scene(self._scene)

    def nominal(self, x_nom: np.ndarray, U: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The clipped open-loop nominal trajectory (X (T+1, nx), U (T, nu))."""
        return self.tracking.nominal(x_nom, U)

    def rows(self, x: np.ndarray) -> tuple[np.ndarray, ...]:
        """Normalised rows at x in the current scene: a (nh, nu), b (nh,), da/dx (nh, nu, nx),
        db/dx (nh, nx)."""
        nh, nu, nx = self.nh, self.nu, self.nx
        a, b, da, db = self._jac(x, self._scene)
        return (a.reshape(nu, nh).T, b, da.reshape(nx, nu, nh).transpose(2, 1, 0),
                db.reshape(nx, nh).T)

    def solve(self, a: np.ndarray, b: np.ndarray, u_ref: np.ndarray):
        """The filter's QP on normalised rows a (nh, nu), b (nh,) and its active set: (u, hard
        rows, soft (violated) rows, controls at the upper / lower bound), or None where the
        filter falls back to clip(u_ref) (hard mode, infeasible)."""
        m, o = self.model, self.opt
        lo, hi, nu = m.u_min, m.u_max, self.nu
        # min over the box of a_i u: a row with b_i below it holds for every boxed control
        low = np.where(a > 0, a * lo, np.where(a < 0, a * hi, 0.0)).sum(axis=1)
        keep = np.flatnonzero(~(b < low - 1e-9))
        ak, bk, n = a[keep], b[keep], keep.size
        inf = np.full(n, np.inf)
        if o.mode == "hard":
            H, f, A, ns = 2.0 * np.eye(nu), -2.0 * u_ref, ak, 0
            upper, lower = np.concatenate([hi, inf]), np.concatenate([lo, bk])
        else:  # z = [u; delta]: rows a_i u + delta_i >= b_i, delta >= 0
            H = np.diag(np.concatenate([np.full(nu, 2.0), np.full(n, 2.0 * o.slack_quadratic)]))
            f = np.concatenate([-2.0 * u_ref, np.full(n, o.slack_linear)])
            A, ns = np.hstack([ak, np.eye(n)]), n
            upper = np.concatenate([hi, inf, inf])
            lower = np.concatenate([lo, np.zeros(n), bk])
        z, _, flag, info = daqp.solve(H, f, A, upper, lower,
                                      np.zeros(upper.size, dtype=np.int32))
        z, lam = np.asarray(z, dtype=float), np.asarray(info["lam"], dtype=float)
        if flag in (1, 2) and np.all(np.isfinite(z)) and np.all(np.isfinite(lam)):
            u = np.minimum(np.maximum(z[:nu], lo), hi)
            # daqp's working set: lam > 0 at an upper bound, lam < 0 at a lower one
            on = lam[nu + ns :] < 0  # rows in the working set; soft mode: is delta_i = 0 too?
            zero_slack = lam[nu : nu + ns] < 0 if ns else np.ones(n, bool)
            return (u, list(keep[on & zero_slack]), keep[on & ~zero_slack],
                    list(np.flatnonzero(lam[:nu] > 0)), list(np.flatnonzero(lam[:nu] < 0)))
        if o.mode == "hard" and flag == -1:
            return None  # infeasible: the filter returns clip(u_ref)
        res = self.filter.solve_rows(a, b, u_ref)  # daqp failed: the filter itself (OSQP)
        if res.fallback_used:
            return None
        tol = 10.0 * max(o.eps_abs, o.eps_rel)
        resid = b - a @ res.u
        soft = np.flatnonzero(resid > tol) if o.mode == "soft" else np.zeros(0, int)
        return (res.u, list(np.flatnonzero(np.abs(resid) <= tol)), soft,
                list(np.flatnonzero(res.u >= hi - tol)), list(np.flatnonzero(res.u <= lo + tol)))

    def sensitivity(self, x: np.ndarray, u_ref: np.ndarray,
                    K: np.ndarray) -> FilterSensitivity | None:
        """d pi/dx at x for the reference u_ref + K (x' - x), with the QP's active set at x held
        fixed; None where the filter falls back to clip(u_ref) (hard mode, infeasible)."""
        a, b, da, db = self.rows(x)
        qp = self.solve(a, b, u_ref)
        if qp is None:
            return None
        return self._held(a, b, da, db, u_ref, K, *qp[1:])

    def _held(self, a, b, da, db, u_ref, K, hard, soft, upper, lower) -> FilterSensitivity:
        """d pi/dx from the rows and their Jacobians at x and the QP's active set there (hard,
        upper, lower: lists, shortened in place as multipliers drop rows and bounds)."""
        for _ in range(self.nh + 2 * self.nu + 1):
            M, u, nu_h, nu_u, nu_l = self._kkt(a, b, u_ref, hard, soft, upper, lower)
            # a merely touched box bound is left to the sampler's clip; a row pulling the wrong
            # way (negative multiplier) is not active
            small = 1e-9 * max(1.0, float(np.abs(u_ref).max()))
            drop = [(v, "u", j) for v, j in zip(nu_u, upper, strict=True) if v <= small]
            drop += [(v, "l", j) for v, j in zip(nu_l, lower, strict=True) if v <= small]
            drop += [(v, "h", i) for v, i in zip(nu_h, hard, strict=True) if v < -small]
            if not drop:
                break
            _, kind, j = min(drop)
            {"u": upper, "l": lower, "h": hard}[kind].remove(j)
        # d/dx of the KKT residuals at fixed (u, nu); J_z dz = -J_x. Residual 1:
        # H u - E^T nu - 2 (u* + K (x - x*)) - sum_soft (L + 2 rho b_i) a_i
        R = np.zeros((M.shape[0], self.nx))
        R[: self.nu] = -2.0 * K
        for v, i in zip(nu_h, hard, strict=True):
            R[: self.nu] -= v * da[i]
        L, rho = self.opt.slack_linear, self.opt.slack_quadratic
        for i in soft:
            s_i = b[i] - a[i] @ u  # the slack
            R[: self.nu] -= (L + 2.0 * rho * s_i) * da[i] + 2.0 * rho * np.outer(
                a[i], db[i] - u @ da[i])
        # residual 2: E u - e (box rows are constant)
        for r, i in enumerate(hard):
            R[self.nu + r] = u @ da[i] - db[i]
        G = _solve_kkt(M, -R)[: self.nu]
        return FilterSensitivity(gain=G, u=u, hard=tuple(int(i) for i in hard),
                                 soft=tuple(int(i) for i in soft),
                                 box_upper=tuple(int(j) for j in upper),
                                 box_lower=tuple(int(j) for j in lower))

    def _kkt(self, a, b, u_ref, hard, soft, upper, lower):
        """KKT matrix, solution and multipliers (>= 0 when active) with the active set held
        as E u = e (ECBF rows, then -u_j = -u_max_j, u_j = u_min_j):
        [H -E^T; E 0] [u; nu] = [2 u_ref + sum_soft (L + 2 rho b_i) a_i; e]."""
        m, o = self.model, self.opt
        eye = np.eye(self.nu)
        E = np.vstack([a[hard], -eye[upper], eye[lower]])
        e = np.concatenate([b[hard], -m.u_max[upper], m.u_min[lower]])
        H, g = 2.0 * eye, 2.0 * u_ref
        if len(soft):
            H = H + 2.0 * o.slack_quadratic * a[soft].T @ a[soft]
            g = g + a[soft].T @ (o.slack_linear + 2.0 * o.slack_quadratic * b[soft])
        M = _kkt_matrix(H, E)
        z = _solve_kkt(M, np.concatenate([g, e]))
        u, mult, nh_ = z[: self.nu], z[self.nu :], len(hard)
        return M, u, mult[:nh_], mult[nh_ : nh_ + len(upper)], mult[nh_ + len(upper) :]

    def gains(self, x_nom, U, previous: Gains | None, stride: int) -> Gains:
        """The gains (see the class): the QP of every active step solved by daqp as in
        :meth:`solve`, the row Jacobians and the KKT solves batched over the steps; equal to
        :meth:`gains_twin` (which runs :meth:`sensitivity` step by step)."""
        return self._gains(x_nom, U, previous, stride, fast=True)

    def gains_twin(self, x_nom, U, previous: Gains | None, stride: int) -> Gains:
        """The gains with :meth:`sensitivity` called at each active step (the slow twin of
        :meth:`gains`)."""
        return self._gains(x_nom, U, previous, stride, fast=False)

    def _gains(self, x_nom, U, previous, stride, fast: bool) -> Gains:
        U = as_array("U", U, (self.T, self.nu))
        shape = (self.T, self.nu, self.nx_full)
        g = self.tracking.gains(x_nom, U, None, stride)
        idle: Mapping[str, float] = {"ecbf_active": 0.0, "ecbf_infeasible": 0.0}
        if g.fallback is not None:
            return Gains(K=fallback_gains(previous, stride, shape), fallback=g.fallback,
                         nominal_unsafe=g.nominal_unsafe, mu=np.nan, activity=idle)
        X, Uc = self.nominal(x_nom, U)
        nh, nu = self.nh, self.nu
        a_all, b_all = self._rows(X[:-1], self._scene)
        a_all = a_all.reshape(self.T, nu, nh).transpose(0, 2, 1)
        b_all = b_all.reshape(self.T, nh)
        # as the filter's shortcut: clip(u_ref) = u* satisfies every row to within eps_abs
        violation = b_all - np.einsum("kij,kj->ki", a_all, Uc)
        K = g.K.copy()
        active = (violation > self.opt.eps_abs).any(axis=1)
        infeasible = np.zeros(self.T, bool)
        reason = None
        ks = np.flatnonzero(active)
        steps: Iterable[tuple[np.ndarray, bool] | None]
        if fast:  # (gain, infeasible) or None per active step
            rows = self._row_batch(X[ks])
            steps = self._sensitivities(rows, Uc[ks], g.K[ks])
        else:  # lazily: a non-finite gain stops the loop
            steps = (_pair(self.sensitivity(X[k], Uc[k], g.K[k])) for k in ks)
        for j, (k, sens) in enumerate(zip(ks, steps, strict=True)):
            if sens is None:  # hard mode, infeasible: clip(u_ref), the tracking gain
                infeasible[k] = True
                continue
            gain, infeasible[k] = sens
            if not np.all(np.isfinite(gain)):
                at = [r[j] for r in rows] if fast else self.rows(X[k])
                finite = all(np.all(np.isfinite(r)) for r in at)
                reason = "nonfinite_gains" if finite else "nonfinite_derivatives"
                break
            K[k] = gain
        # effects (workbench.sampling.feedback.effect): the steps whose gain the filter changed
        # (none when the gains fall back: the previous ones are used)
        changed = differs(K, g.K, axis=(1, 2)) if reason is None else np.zeros(self.T, bool)
        activity = {"ecbf_active": float(changed.mean()),
                    "ecbf_infeasible": float(infeasible.mean())}
        if reason is not None:
            return Gains(K=fallback_gains(previous, stride, shape), fallback=reason,
                         nominal_unsafe=g.nominal_unsafe, mu=np.nan, activity=activity)
        return Gains(K=pad_gains(K, self.nx_full), fallback=None, nominal_unsafe=g.nominal_unsafe,
                     mu=g.mu, activity=activity)

    def _row_batch(self, X: np.ndarray) -> tuple[np.ndarray, ...]:
        """:meth:`rows` at each state of X (m, nx), stacked: (m, nh, nu), (m, nh),
        (m, nh, nu, nx), (m, nh, nx)."""
        nh, nu, nx, c, m = self.nh, self.nu, self.nx, self._chunk, X.shape[0]
        a, b = np.empty((m, nh, nu)), np.empty((m, nh))
        da, db = np.empty((m, nh, nu, nx)), np.empty((m, nh, nx))
        for s in range(0, m, c):
            chunk = X[s : s + c]
            n = chunk.shape[0]
            if n < c:  # pad with the last state (its results are not used)
                chunk = np.vstack([chunk, np.repeat(chunk[-1:], c - n, axis=0)])
            oa, ob, oda, odb = self._jac_batch(chunk, self._scene)
            a[s : s + n] = oa.reshape(c, nu, nh)[:n].transpose(0, 2, 1)
            b[s : s + n] = ob.reshape(c, nh)[:n]
            da[s : s + n] = oda.reshape(c, nx, nu, nh)[:n].transpose(0, 3, 2, 1)
            db[s : s + n] = odb.reshape(c, nx, nh)[:n].transpose(0, 2, 1)
        return a, b, da, db

    def _active_sets(self, a, b, U_ref) -> tuple[np.ndarray, ...]:
        """:meth:`solve`'s active sets at m steps (rows a (m, nh, nu), b (m, nh), references
        U_ref (m, nu)) as masks: hard, soft rows (m, nh), controls at the upper / lower bound
        (m, nu), and where solve() returns None (m,). daqp on solve()'s data, the steps with
        the same number of kept rows set up together; anything but a clean daqp answer goes
        through solve() itself."""
        m, o, nu = self.model, self.opt, self.nu
        lo, hi = m.u_min, m.u_max
        low = np.where(a > 0, a * lo, np.where(a < 0, a * hi, 0.0)).sum(axis=2)
        keep = ~(b < low - 1e-9)
        n_keep = keep.sum(axis=1)
        hard, soft = np.zeros(keep.shape, bool), np.zeros(keep.shape, bool)
        upper, lower = np.zeros(U_ref.shape, bool), np.zeros(U_ref.shape, bool)
        none, retry = np.zeros(len(a), bool), []
        soft_mode = o.mode != "hard"
        for n in np.unique(n_keep):
            js = np.flatnonzero(n_keep == n)
            N, col = js.size, js[:, None]
            kept = np.nonzero(keep[js])[1].reshape(N, n)
            inf = np.full(n, np.inf)
            f = np.empty((N, nu + n * soft_mode))
            f[:, :nu] = -2.0 * U_ref[js]
            if soft_mode:
                ns = n
                H = np.diag(np.concatenate([np.full(nu, 2.0),
                                            np.full(n, 2.0 * o.slack_quadratic)]))
                up = np.concatenate([hi, inf, inf])
                A = np.zeros((N, n, nu + n))
                A[:, :, nu:] = np.eye(n)
                f[:, nu:] = o.slack_linear
                low_b = np.zeros((N, nu + 2 * n))
            else:
                ns, H, up = 0, 2.0 * np.eye(nu), np.concatenate([hi, inf])
                A = np.zeros((N, n, nu))
                low_b = np.empty((N, nu + n))
            A[:, :, :nu] = a[col, kept]
            low_b[:, :nu], low_b[:, nu + ns :] = lo, b[col, kept]
            z, lam = np.empty(f.shape), np.empty(low_b.shape)
            flag = np.empty(N, int)
            for r in range(N):
                zr, _, flag[r], info = daqp.solve(H, f[r], A[r], up, low_b[r],
                                                  np.zeros(up.size, dtype=np.int32))
                z[r], lam[r] = zr, info["lam"]
            ok = (flag == 1) | (flag == 2)
            ok &= np.isfinite(z).all(axis=1) & np.isfinite(lam).all(axis=1)
            # daqp's working set: lam > 0 at an upper bound, lam < 0 at a lower one
            on = lam[:, nu + ns :] < 0
            zero_slack = lam[:, nu : nu + ns] < 0 if ns else np.ones((N, n), bool)
            rows = np.broadcast_to(col, kept.shape)
            hard[rows[ok], kept[ok]] = (on & zero_slack)[ok]
            soft[rows[ok], kept[ok]] = (on & ~zero_slack)[ok]
            upper[js[ok]], lower[js[ok]] = lam[ok, :nu] > 0, lam[ok, :nu] < 0
            retry.extend(js[~ok])
        for j in sorted(retry):  # daqp failed: solve() itself (OSQP, or None), in step order
            qp = self.solve(a[j], b[j], U_ref[j])
            if qp is None:
                none[j] = True
                continue
            for mask, idx in zip((hard, soft, upper, lower), qp[1:], strict=True):
                mask[j, np.asarray(idx, dtype=int)] = True
        return hard, soft, upper, lower, none

    def _sensitivities(self, rows, U_ref, K) -> list[tuple[np.ndarray, bool] | None]:
        """(gain, infeasible) or None per step, as :meth:`sensitivity` with references U_ref
        (m, nu), tracking gains K (m, nu, nx) and rows from :meth:`_row_batch`: the same QPs,
        then the KKT solves of steps with the same shape of active set batched; a step whose
        multipliers drop a bound or row goes through the per-step solves."""
        sets = self._active_sets(rows[0], rows[1], U_ref)
        none = sets[-1]
        # box bounds as one block (upper, then lower, as sensitivity() holds them)
        box = np.concatenate([sets[2], sets[3]], axis=1)
        counts = np.stack([sets[0].sum(axis=1), sets[1].sum(axis=1), box.sum(axis=1)], axis=1)
        out: list[tuple[np.ndarray, bool] | None] = [None] * len(U_ref)
        groups: dict[tuple[int, ...], list[np.intp]] = {}
        for j in np.flatnonzero(~none):
            groups.setdefault(tuple(counts[j]), []).append(j)
        a, b, da, db = rows
        for key, js in groups.items():
            J = np.array(js)
            hard_i, soft_i, box_i = (np.nonzero(s[J])[1].reshape(len(J), c)
                                     for s, c in zip((sets[0], sets[1], box), key, strict=True))
            gains = self._kkt_batch(rows, J, hard_i, soft_i, box_i, U_ref[J], K[J])
            for r, j in enumerate(J):
                if gains[r] is None:  # a bound or row dropped: the per-step law
                    bounds = box_i[r]
                    out[j] = _pair(self._held(
                        a[j], b[j], da[j], db[j], U_ref[j], K[j], list(hard_i[r]), soft_i[r],
                        list(bounds[bounds < self.nu]), list(bounds[bounds >= self.nu] - self.nu)))
                else:
                    out[j] = (gains[r], key[1] > 0)
        return out

    def _kkt_batch(self, rows, J, hard, soft, box, U_ref, K) -> list:
        """The gains of :meth:`sensitivity` for steps J with active sets of one shape (index
        arrays (N, count); box: j for u_j at its upper bound, nu + j at its lower one, upper
        first); None where the multipliers would drop a bound or row."""
        a, b, da, db = rows
        nu, nx, o, N = self.nu, self.nx, self.opt, len(J)
        L, rho = o.slack_linear, o.slack_quadratic
        col = J[:, None]
        eye = np.eye(nu)
        at_upper, j_box = box < nu, box % nu
        E = np.concatenate([a[col, hard], np.where(at_upper[..., None], -eye[j_box],
                                                   eye[j_box])], axis=1)
        e = np.concatenate([b[col, hard], np.where(at_upper, -self.model.u_max[j_box],
                                                   self.model.u_min[j_box])], axis=1)
        H = np.broadcast_to(2.0 * eye, (N, nu, nu))
        g = 2.0 * U_ref
        a_s, b_s = a[col, soft], b[col, soft]
        if soft.shape[1]:
            H = H + (2.0 * rho * a_s).transpose(0, 2, 1) @ a_s
            g = g + (a_s.transpose(0, 2, 1) @ (L + 2.0 * rho * b_s)[..., None])[..., 0]
        q = E.shape[1]
        M = np.zeros((N, nu + q, nu + q))
        M[:, :nu, :nu], M[:, :nu, nu:], M[:, nu:, :nu] = H, -E.transpose(0, 2, 1), E
        z = _solve_kkt_batch(M, np.concatenate([g, e], axis=1)[..., None])[..., 0]
        u, mult, nh_ = z[:, :nu], z[:, nu:], hard.shape[1]
        nu_h, nu_box = mult[:, :nh_], mult[:, nh_:]
        small = (1e-9 * np.fmax(1.0, np.abs(U_ref).max(axis=1)))[:, None]
        drop = (nu_box <= small).any(axis=1) | (nu_h < -small).any(axis=1)
        R = np.zeros((N, nu + q, nx))
        R[:, :nu] = -2.0 * K
        da_h, db_h = da[col, hard], db[col, hard]
        for r in range(nh_):
            R[:, :nu] -= nu_h[:, r, None, None] * da_h[:, r]
        da_s, db_s = da[col, soft], db[col, soft]
        for r in range(soft.shape[1]):
            s_r = b_s[:, r] - np.einsum("ki,ki->k", a_s[:, r], u)  # the slack
            du = db_s[:, r] - np.einsum("ki,kix->kx", u, da_s[:, r])
            R[:, :nu] -= (L + 2.0 * rho * s_r)[:, None, None] * da_s[:, r] + 2.0 * rho * (
                a_s[:, r, :, None] * du[:, None, :])
        for r in range(nh_):
            R[:, nu + r] = np.einsum("ki,kix->kx", u, da_h[:, r]) - db_h[:, r]
        G = _solve_kkt_batch(M, -R)[:, :nu]
        return [None if d else G[i] for i, d in enumerate(drop)]

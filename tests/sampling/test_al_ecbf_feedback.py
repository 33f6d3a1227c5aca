"""The augmented-Lagrangian and ECBF feedback laws of the SAIS sampler: equal to the plain
tracking gains where their mechanism is idle, equal to independent oracles where it acts
(a NumPy Riccati pass on finite-difference linearisations of the AL cost; central finite
differences of the actual ECBF-QP filter), fallbacks, scenes, and both inside RobustMPPI."""

from __future__ import annotations

import re

import casadi as ca
import numpy as np
import pytest
import qpsolvers
from conftest import central_jacobian

from workbench.filters.ecbf import ECBFFilter, ECBFOptions
from workbench.ilqg.passes import BackwardResult
from workbench.problem.models import Circle, double_integrator
from workbench.sampling.feedback import FALLBACK_REASONS, FeedbackWeights, ILQGFeedback, shifted
from workbench.sampling.feedback.al import ALFeedback, ALFeedbackOptions, ALGains
from workbench.sampling.feedback.ecbf import ECBFFeedback
from workbench.sampling.mppi import MPPIConfig
from workbench.sampling.planning import physical_model
from workbench.sampling.robust import RMPPIConfig, RobustMPPI
from workbench.scenarios.navigation import navigation_setup
from workbench.sim import Disturbance, closed_loop

T = 30
OBSTACLE = Circle((2.0, 2.0), 0.8)
THROUGH = np.array([0.5, 2.0, 3.0, 0.0])  # coasts straight through the obstacle
GRAZING = np.array([0.5, 1.1, 3.0, 0.0])  # passes 0.1 below it, never inside
FAR = np.array([0.0, -2.0, 1.0, 0.0])  # nowhere near it
AT_SPEED = np.array([0.5, 1.3, 3.0, 0.0])  # heads for its flank at 3 m/s: the ECBF acts


def close(a, b, tol):
    """Per-element relative closeness |a - b| <= tol * max(|a|, |b|, 1)."""
    return bool(np.all(np.abs(a - b) <= tol * np.maximum(np.maximum(np.abs(a), np.abs(b)), 1)))


@pytest.fixture(scope="module")
def model():
    return double_integrator(obstacles=(OBSTACLE,), u_limit=5.0)


@pytest.fixture(scope="module")
def al(model):
    return ALFeedback(model, T, 5)


@pytest.fixture(scope="module")
def ilqg(model):
    return ILQGFeedback(model, T, 5)


@pytest.fixture(scope="module")
def ecbf(model):
    return ECBFFeedback(model, T, 5)


# ---------------------------------------------------------------------------- AL: the oracle


def rollout(model, x0, U):
    """Clipped open-loop rollout with the model's own dynamics (not the iLQG passes)."""
    f = ca.Function("f", [model.x, model.u], [model.x_next])
    X = [np.asarray(x0, float)]
    Uc = np.clip(U, model.u_min, model.u_max)
    for u in Uc:
        X.append(np.asarray(f(X[-1], u)).ravel())
    return np.array(X), Uc


def riccati_al_gains(model, X, U, lam, mu, w=FeedbackWeights()):
    """Independent oracle: a plain NumPy Riccati pass (control regularisation w.mu, as the
    law's first level) on central finite-difference linearisations of the AL cost
    ½|x-x*|²_Q + ½|u-u*|²_R + sum_i mu/2 max(0, c_i + lam_i/mu)² with c = -h, Hessian in the
    Gauss-Newton form mu grad(c_i) grad(c_i)^T on the active terms (mu c_i + lam_i > 0), the
    form of the AL-iLQG inner problem (its indefinite (mu c + lam) Hess(c) term is dropped)."""
    f = ca.Function("f", [model.x, model.u], [model.x_next])

    def fx(x, u):
        return np.asarray(f(x, u)).ravel()

    def c(x):
        return -model.margins(x)

    Q, R = np.diag(w.Q), np.diag(w.R)

    def lxx(k):
        g = central_jacobian(c, X[k])
        act = mu * c(X[k]) + lam[k] > 0
        return Q + mu * g[act].T @ g[act]

    V = lxx(len(U))
    K = np.zeros((len(U), model.nu, model.nx))
    for k in range(len(U) - 1, -1, -1):
        A = central_jacobian(lambda x: fx(x, U[k]), X[k])
        B = central_jacobian(lambda u: fx(X[k], u), U[k])
        Qxx, Qux, Quu = lxx(k) + A.T @ V @ A, B.T @ V @ A, R + B.T @ V @ B
        K[k] = -np.linalg.solve(Quu + w.mu * np.eye(model.nu), Qux)
        V = Qxx + K[k].T @ Quu @ K[k] + K[k].T @ Qux + Qux.T @ K[k]
        V = 0.5 * (V + V.T)
    return K


# ---------------------------------------------------------------------------- AL: tests


def test_al_gains_equal_the_plain_tracking_gains_when_no_penalty_is_active(model, al, ilqg):
    U = np.zeros((T, 2))
    for x0 in (FAR, GRAZING):  # never violates: mu c + lambda < 0 everywhere with lambda = 0
        g, ref = al.gains(x0, U, None, 0), ilqg.gains(x0, U, None, 0)
        assert isinstance(g, ALGains) and g.fallback is None
        assert g.activity == {"al_active": 0.0} and not g.nominal_unsafe
        assert g.K.shape == (T, 2, 5) and not np.any(g.K[:, :, 4])
        assert close(g.K, ref.K, 1e-10) and np.abs(g.K).max() > 1.0
        assert not np.any(g.multipliers)  # max(0, 0 + mu c) = 0 on a safe nominal


def test_al_gains_match_an_independent_riccati_pass_when_the_nominal_crosses(model, al, ilqg):
    U = np.zeros((T, 2))
    g = al.gains(THROUGH, U, None, 0)
    X, Uc = rollout(model, THROUGH, U)
    C = -np.array([model.margins(x) for x in X])
    assert g.fallback is None and g.nominal_unsafe and C.max() > 0.3
    mu = ALFeedbackOptions().mu
    assert g.activity["al_active"] == pytest.approx(np.mean(C[1:, 0] > 0))
    assert g.activity["al_active"] > 0.3
    np.testing.assert_array_equal(g.multipliers_used, 0.0)
    K_ref = riccati_al_gains(model, X, Uc, g.multipliers_used, mu)
    assert close(g.K[:, :, :4], K_ref, 1e-7)
    # the penalty moves the gains: far from the plain tracking gains
    plain = ilqg.gains(THROUGH, U, None, 0).K
    assert np.abs(g.K - plain).max() > 0.1 * np.abs(plain).max()
    # one PHR update on the nominal: lambda <- max(0, lambda + mu c), row 0 (x_0 fixed) stays 0
    expect = np.maximum(0.0, mu * C)
    expect[0] = 0.0
    np.testing.assert_allclose(g.multipliers, expect, rtol=1e-12, atol=1e-9)


def test_al_multipliers_are_warm_started_and_keep_the_penalty_on(model, al, ilqg):
    """After a crossing nominal the shifted multipliers keep the penalty active on a nominal
    that only grazes the obstacle (mu c + lambda > 0 with c < 0): the gains then differ from the
    plain tracking gains, and still equal the oracle with those multipliers."""
    U = np.zeros((T, 2))
    g1 = al.gains(THROUGH, U, None, 0)
    g2 = al.gains(GRAZING, U, g1, 1)
    lam = np.zeros_like(g1.multipliers)
    lam[1:-1] = g1.multipliers[2:]  # shifted by the stride; the new tail row at lambda_init
    np.testing.assert_array_equal(g2.multipliers_used, lam)
    X, Uc = rollout(model, GRAZING, U)
    assert min(model.margins(x).min() for x in X) > 0
    assert g2.activity["al_active"] > 0.2 and not g2.nominal_unsafe
    assert close(g2.K[:, :, :4], riccati_al_gains(model, X, Uc, lam, al.opt.mu), 1e-7)
    plain = ilqg.gains(GRAZING, U, None, 0).K
    assert np.abs(g2.K - plain).max() > 0.1 * np.abs(plain).max()
    # a stride of 3 shifts by 3 and refills three tail rows
    g3 = al.gains(GRAZING, U, g1, 3)
    np.testing.assert_array_equal(g3.multipliers_used[1:-3], g1.multipliers[4:])
    np.testing.assert_array_equal(g3.multipliers_used[-3:], 0.0)


def test_al_multipliers_are_capped(model):
    law = ALFeedback(model, T, 4, options=ALFeedbackOptions(lambda_max=50.0))
    g = law.gains(THROUGH, np.zeros((T, 2)), None, 0)
    assert g.multipliers.max() == 50.0


@pytest.mark.parametrize("law_name", ["al", "ecbf"])
def test_fallbacks_shift_the_previous_gains_and_say_why(request, law_name, monkeypatch):
    law = request.getfixturevalue(law_name)
    passes = law.passes if law_name == "al" else law.tracking.passes
    U = np.zeros((T, 2))
    prev = law.gains(AT_SPEED, U, None, 0)
    monkeypatch.setattr(passes, "backward",
                        lambda *a: BackwardResult(status=1, k=None, K=None, dV=None))
    g = law.gains(AT_SPEED, U, prev, 1)
    assert g.fallback == "backward_failed" and g.fallback in FALLBACK_REASONS
    np.testing.assert_array_equal(g.K, shifted(prev.K, 1))
    monkeypatch.undo()
    d = passes.derivatives

    def poisoned(*a):
        out = dict(d(*a))
        out["A"] = out["A"] * np.nan
        return out

    monkeypatch.setattr(passes, "derivatives", poisoned)
    assert law.gains(AT_SPEED, U, prev, 0).fallback == "nonfinite_derivatives"
    g0 = law.gains(AT_SPEED, U, None, 0)  # nothing to shift: K = 0, and the reason is given
    assert g0.fallback == "nonfinite_derivatives" and not np.any(g0.K)
    if law_name == "al":  # the multiplier update does not depend on the gains
        np.testing.assert_array_equal(g0.multipliers, prev.multipliers)


@pytest.mark.parametrize(("kw", "field"), [
    ({"mu": 0.0}, "ALFeedbackOptions.mu"), ({"mu": np.nan}, "ALFeedbackOptions.mu"),
    ({"lambda_init": -1.0}, "ALFeedbackOptions.lambda_init"),
    ({"lambda_init": 10.0, "lambda_max": 1.0}, "ALFeedbackOptions.lambda_max"),
    ({"mu": True}, "ALFeedbackOptions.mu")])
def test_bad_al_options_name_the_field(kw, field):
    with pytest.raises(ValueError, match=re.escape(field)):
        ALFeedbackOptions(**kw)


def test_laws_refuse_models_they_do_not_act_on(model):
    nav = navigation_setup()
    for law in (ALFeedback, ECBFFeedback):
        with pytest.raises(ValueError, match="physical"):
            law(nav.problem.model, T, 5)  # barrier-embedded
        with pytest.raises(ValueError, match="margin"):
            law(double_integrator(), T, 4)  # nothing to keep safe
        with pytest.raises(ValueError, match=r"FeedbackWeights\.Q"):
            law(model, T, 4, FeedbackWeights(Q=(1.0, 1.0)))
        with pytest.raises(ValueError, match="nx_full"):
            law(model, T, 3)
    with pytest.raises(ValueError, match="ecbf"):
        ECBFFeedback(model, T, 4, ecbf=ALFeedbackOptions())


# ---------------------------------------------------------------------------- ECBF


def fd_filter_gains(filt: ECBFFilter, x_star, u_star, K, eps=1e-6):
    """Central differences of the actual filter applied to u_ref = u* + K (x - x*)."""
    def pi(x):
        return filt(x, u_star + K @ (x - x_star)).u

    return central_jacobian(pi, x_star, eps)


def projection_gains(model, x_star, u_ref, K, drop=()):
    """The active-set formula, written from scratch: the active set from daqp's duals, the row
    derivatives by finite differences of the (unnormalised) ECBF rows,
    d pi/dx = (I - P)(K + sum_i lambda_i da_i/dx) + A^+ (db/dx - da/dx u) with u - u_ref =
    A^T lambda. ``drop``: "projection" (K itself), "curvature" (no lambda da/dx term: A held
    constant in the projector)."""
    rows = ECBFFilter(model).ecbf
    a, b = rows(x_star)
    n = np.linalg.norm(a, axis=1)
    sol = qpsolvers.solve_problem(qpsolvers.Problem(
        P=2 * np.eye(2), q=-2 * u_ref, G=-a / n[:, None], h=-b / n, lb=model.u_min,
        ub=model.u_max), solver="daqp")
    assert sol.found
    u = sol.x
    rows_i = np.flatnonzero(sol.z > 1e-9)
    box = np.flatnonzero(np.abs(sol.z_box) > 1e-9)
    A = np.vstack([a[rows_i], np.eye(2)[box]])
    dA = [central_jacobian(lambda x: rows(x)[0][i], x_star) for i in rows_i]
    dA += [np.zeros((2, 4))] * len(box)
    db = [central_jacobian(lambda x: rows(x)[1][i:i + 1], x_star)[0] for i in rows_i]
    db += [np.zeros(4)] * len(box)
    if "projection" in drop or not len(A):
        return K
    Ap = np.linalg.pinv(A)
    P = Ap @ A
    lam = np.linalg.lstsq(A.T, u - u_ref, rcond=None)[0]
    curv = sum(li * d for li, d in zip(lam, dA, strict=True))
    G = (np.eye(2) - P) @ K + Ap @ np.array([dbi - u @ d for dbi, d in zip(db, dA, strict=True)])
    if "curvature" not in drop:
        G = G + (np.eye(2) - P) @ curv
    return G


def test_ecbf_gains_equal_the_tracking_gains_where_no_row_is_active(ecbf, ilqg):
    U = np.zeros((T, 2))
    g, ref = ecbf.gains(FAR, U, None, 0), ilqg.gains(FAR, U, None, 0)
    assert g.activity["ecbf_active"] == 0.0 and g.fallback is None
    np.testing.assert_array_equal(g.K, ref.K)


def test_ecbf_gains_are_the_derivative_of_the_actual_filter(model, ecbf, ilqg):
    """At every step of a nominal that passes the obstacle's flank at speed: steps where no row
    is active, steps where one row is, steps at a box vertex and infeasible (soft) steps; the
    analytic gains agree with central differences of the OSQP filter at tight tolerances."""
    U = np.zeros((T, 2))
    g, K = ecbf.gains(AT_SPEED, U, None, 0), ilqg.gains(AT_SPEED, U, None, 0).K[:, :, :4]
    X, Uc = rollout(model, AT_SPEED, U)
    tight = ECBFFilter(model, ECBFOptions(eps_abs=1e-12, eps_rel=1e-12, max_iter=100000))
    kinds, worst = {}, 0.0
    for k in range(T):
        res = tight(X[k], Uc[k])
        K_fd = fd_filter_gains(tight, X[k], Uc[k], K[k])
        err = np.linalg.norm(g.K[k, :, :4] - K_fd) / max(np.linalg.norm(K_fd), 1.0)
        worst = max(worst, err)
        assert err < 1e-5, (k, res.status, err)
        box = bool(np.any(np.isin(res.u, (model.u_min[0], model.u_max[0]))))
        kind = ("none" if not res.active_rows else "infeasible" if res.infeasible
                else "row+box" if box else "row")
        kinds.setdefault(kind, []).append(k)
    assert set(kinds) == {"none", "row", "row+box", "infeasible"}, kinds
    assert not np.any(g.K[:, :, 4])
    ref = ecbf.gains_twin(AT_SPEED, U, None, 0)  # the per-step twin: the same gains
    assert ref.activity == g.activity and close(ref.K, g.K, 1e-12)
    n_active = T - len(kinds["none"])
    assert g.activity["ecbf_active"] == pytest.approx(n_active / T)
    assert g.activity["ecbf_infeasible"] == pytest.approx(len(kinds["infeasible"]) / T)
    # the same formula written from scratch (daqp active set, finite-difference rows) agrees
    # on the feasible active steps; each mutation misses the filter's derivative by orders
    for k in kinds["row"] + kinds["row+box"]:
        K_fd = fd_filter_gains(tight, X[k], Uc[k], K[k])
        scale = max(np.linalg.norm(K_fd), 1.0)
        ok = projection_gains(model, X[k], Uc[k], K[k])
        assert np.linalg.norm(ok - K_fd) / scale < 1e-5
        assert np.linalg.norm(ok - g.K[k, :, :4]) / scale < 1e-6
        assert np.linalg.norm(projection_gains(model, X[k], Uc[k], K[k], {"projection"})
                              - K_fd) / scale > 1e-2
    for k in kinds["row"]:  # held A: the brief formula without the rotating null space
        K_fd = fd_filter_gains(tight, X[k], Uc[k], K[k])
        bad = projection_gains(model, X[k], Uc[k], K[k], {"curvature"})
        assert np.linalg.norm(bad - K_fd) / max(np.linalg.norm(K_fd), 1.0) > 1e-3


def test_ecbf_sensitivity_reports_the_active_set(model, ecbf, ilqg):
    """The QP's solution (daqp on the rows that can bind) is the filter's, and the active set
    is reported: a single row, and violated (soft) rows of an infeasible QP."""
    U = np.zeros((T, 2))
    K = ilqg.gains(AT_SPEED, U, None, 0).K[:, :, :4]
    X, Uc = rollout(model, AT_SPEED, U)
    tight = ECBFFilter(model, ECBFOptions(eps_abs=1e-12, eps_rel=1e-12, max_iter=100000))
    seen = set()
    for k in range(T):
        s, res = ecbf.sensitivity(X[k], Uc[k], K[k]), tight(X[k], Uc[k])
        np.testing.assert_allclose(s.u, res.u, atol=1e-9)
        seen.add((s.hard, s.soft, s.box_upper, s.box_lower))
    assert ((0,), (), (), ()) in seen  # a single row
    assert any(h == () and sf == (0,) for h, sf, _, _ in seen)  # violated (soft) row


def test_ecbf_uses_the_osqp_filter_where_daqp_fails(model, ecbf, monkeypatch):
    import workbench.sampling.feedback.ecbf as sf

    U = np.zeros((T, 2))
    g = ecbf.gains(AT_SPEED, U, None, 0)
    monkeypatch.setattr(sf.daqp, "solve", lambda H, f, *a: (np.zeros_like(f), 0.0, -4,
                                                            {"lam": np.zeros(len(a[1]))}))
    g_osqp = ecbf.gains(AT_SPEED, U, None, 0)
    assert g_osqp.activity == g.activity
    assert close(g_osqp.K, g.K, 1e-8)


def test_ecbf_hard_mode_keeps_the_tracking_gain_where_the_filter_falls_back(model, ilqg):
    law = ECBFFeedback(model, T, 4, ecbf=ECBFOptions(mode="hard"))
    U = np.zeros((T, 2))
    g, K = law.gains(AT_SPEED, U, None, 0), ilqg.gains(AT_SPEED, U, None, 0).K[:, :, :4]
    X, Uc = rollout(model, AT_SPEED, U)
    res = law.filter.filter_batch(X[:-1], Uc)  # OSQP: primal infeasible -> clip(u_ref)
    assert res.fallback_used.any()
    assert g.activity["ecbf_infeasible"] == pytest.approx(res.fallback_used.mean())
    np.testing.assert_array_equal(g.K[res.fallback_used, :, :4], K[res.fallback_used])


def test_set_scene_moves_the_mechanisms(model, al, ecbf, ilqg):
    """Same nominal, FAR from the default obstacle: an obstacle placed on its path by
    set_scene switches both mechanisms on; the model's own scene switches them off again."""
    U = np.zeros((T, 2))
    X, _ = rollout(model, FAR, U)
    on_path = [(X[T // 2, 0] + 0.3, X[T // 2, 1], 0.3)]
    for law, key in ((al, "al_active"), (ecbf, "ecbf_active")):
        assert law.gains(FAR, U, None, 0).activity[key] == 0.0
        law.set_scene(on_path)
        g = law.gains(FAR, U, None, 0)
        law.set_scene(None)
        assert g.activity[key] > 0 and g.fallback is None
        assert not np.allclose(g.K, ilqg.gains(FAR, U, None, 0).K)
        assert law.gains(FAR, U, None, 0).activity[key] == 0.0


# ---------------------------------------------------------------------------- in RobustMPPI


@pytest.fixture(scope="module")
def nav():
    return navigation_setup()


@pytest.mark.parametrize("kind", ["al", "ecbf"])
def test_laws_run_inside_robust_mppi(nav, kind):
    pm = physical_model(nav.problem.model)
    law = (ALFeedback(pm, 30, nav.problem.nx) if kind == "al"
           else ECBFFeedback(pm, 30, nav.problem.nx))
    key = {"al": "al_active", "ecbf": "ecbf_active"}[kind]
    cfg = MPPIConfig(n_samples=64, horizon=30, sigma=nav.mppi.sigma, lam=nav.mppi.lam)
    ctrl = RobustMPPI(nav.problem, nav.goal, cfg, RMPPIConfig(alpha=1e6), feedback=law)
    ep = closed_loop(ctrl, nav.plant, nav.x0, 6, np.random.default_rng(1),
                     np.random.default_rng(2), Disturbance(100.0))
    assert len(ep.infos) == 6
    for info in ep.infos:
        act = info.stats.activity
        assert key in act and 0.0 <= act[key] <= 1.0 and info.ksafe_fallback is None
    # a moved map reaches the law through the controller
    obstacles = [(c.center[0] + 0.1, c.center[1], c.radius) for c in nav.scene.obstacles()]
    ctrl.set_scene(obstacles)
    np.testing.assert_array_equal(law._scene, ctrl.scene)
    state = ctrl.initial_state()
    for _ in range(3):
        state, u, info = ctrl.step(state, nav.x0, np.random.default_rng(3))
        assert np.all(np.isfinite(u)) and key in info.stats.activity
    assert state.gains.K.shape == (30, 2, 5) and not np.any(state.gains.K[:, :, 4])
    if kind == "al":
        assert state.gains.multipliers.shape == (31, pm.nh)

"""ECBF safety filter (assumptions §7): Lie derivatives, closed forms, a second QP solver,
infeasibility; interrupts, non-finite and wrongly shaped inputs."""

from __future__ import annotations

import os
import re
import signal
import threading
import time

import casadi as ca
import numpy as np
import pytest
import qpsolvers

from workbench.filters.ecbf import ECBFFilter, ECBFOptions, control_affine, ecbf_rows
from workbench.problem.models import Model, double_integrator, single_integrator
from workbench.problem.obstacles import Circle, circle_margins

OBSTACLES = (Circle((0.0, 0.1), 1.5), Circle((2.5, -1.0), 0.7))
ECBF_OBSTACLES = (Circle((0.0, 0.1), 1.5), Circle((0.5, 2.0), 0.7))
X_ACTIVE = np.array([-1.7, 0.1, 3.0, 0.0])  # near the first obstacle, moving towards it
U_TOWARDS = np.array([10.0, 0.0])


def _random_states(rng, n, around=(0.0, 0.1), r_min=1.6, r_max=3.5, speed=6.0):
    ang = rng.uniform(0, 2 * np.pi, n)
    d = rng.uniform(r_min, r_max, n)
    p = np.array(around) + d[:, None] * np.column_stack([np.cos(ang), np.sin(ang)])
    return np.hstack([p, speed * rng.standard_normal((n, 2))])


def _unicycle(obstacle: Circle) -> Model:
    x, u = ca.SX.sym("x", 3), ca.SX.sym("u", 2)
    dt = 0.05
    x_next = x + dt * ca.vertcat(u[0] * ca.cos(x[2]), u[0] * ca.sin(x[2]), u[1])
    return Model.from_expressions("unicycle", x, u, x_next, dt=dt, u_min=[-2, -3],
                                  u_max=[2, 3], h=circle_margins(x[:2], (obstacle,)),
                                  obstacles=(obstacle,))


def test_rows_match_the_spec_closed_form_for_the_double_integrator(rng):
    opts = ECBFOptions(poles=(3.0, 7.0))
    rows = ecbf_rows(double_integrator(obstacles=OBSTACLES), opts)
    assert rows.relative_degrees == (2, 2)
    k0, k1 = 21.0, 10.0
    for x in _random_states(rng, 20):
        a, b = rows(x)
        p, v = x[:2], x[2:]
        for i, c in enumerate(OBSTACLES):
            d = p - np.array(c.center)
            h = d @ d - c.radius**2
            np.testing.assert_allclose(a[i], 2 * d, rtol=1e-12, atol=1e-12)  # L_g L_f h
            np.testing.assert_allclose(b[i], -2 * v @ v - 2 * k1 * d @ v - k0 * h,
                                       rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("make", [
    lambda: double_integrator(obstacles=OBSTACLES, integrator="euler"),
    lambda: single_integrator(obstacles=OBSTACLES),
    lambda: _unicycle(Circle((1.0, 0.5), 0.6)),
])
def test_lie_derivatives_match_finite_differences(make, rng):
    """L_f h, L_g h, L_f^2 h, L_g L_f h against central differences along f and the columns
    of g (f, g from the discrete map (F - x)/dt)."""
    model = make()
    f_sx, g_sx = control_affine(model)
    f = ca.Function("f", [model.x], [f_sx])
    g = ca.Function("g", [model.x], [g_sx])
    s = model.scene_value
    h = ca.Function("h", [model.x], [ca.substitute(model.h, model.scene, s)])
    rows = ecbf_rows(model)
    eps = 1e-6

    def along(fun, x, d):
        return (np.asarray(fun(x + eps * d)).ravel() - np.asarray(fun(x - eps * d)).ravel()) / (
            2 * eps)

    lfh_fun = ca.Function("lfh", [model.x], [rows.lie(model.x, s)[1]])
    for _ in range(5):
        x = rng.standard_normal(model.nx) * 2 + 3.0
        _, lfh, lf2h, lgh, lglfh = (np.asarray(v) for v in rows.lie(x, s))
        fx, gx = np.asarray(f(x)).ravel(), np.asarray(g(x))
        np.testing.assert_allclose(lfh.ravel(), along(h, x, fx), atol=1e-6)
        np.testing.assert_allclose(lf2h.ravel(), along(lfh_fun, x, fx), atol=1e-5)
        for j in range(model.nu):
            np.testing.assert_allclose(lgh[:, j], along(h, x, gx[:, j]), atol=1e-6)
            np.testing.assert_allclose(lglfh[:, j], along(lfh_fun, x, gx[:, j]), atol=1e-5)
    expected = {"double_integrator": 2, "single_integrator": 1, "unicycle": 1}[model.name]
    assert set(rows.relative_degrees) == {expected}


def test_single_integrator_row_is_the_spec_cbf():
    rows = ecbf_rows(single_integrator(obstacles=OBSTACLES[:1]), ECBFOptions(gamma=4.0))
    x = np.array([-2.0, 0.5])
    a, b = rows(x)
    d = x - np.array(OBSTACLES[0].center)
    np.testing.assert_allclose(a[0], 2 * d)
    np.testing.assert_allclose(b[0], -4.0 * (d @ d - 1.5**2))


def test_invalid_models_and_options_name_the_field():
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 2)
    nonaffine = Model.from_expressions("sq", x, u, x + 0.1 * u**2, dt=0.1, u_min=[-1, -1],
                                       u_max=[1, 1], h=circle_margins(x, OBSTACLES[:1]))
    with pytest.raises(ValueError, match=r"model.x_next"):
        ECBFFilter(nonaffine)
    with pytest.raises(ValueError, match=r"relative_degree"):
        ecbf_rows(single_integrator(obstacles=OBSTACLES), ECBFOptions(relative_degree=2))
    with pytest.raises(ValueError, match=r"relative_degree"):
        ecbf_rows(double_integrator(obstacles=OBSTACLES), ECBFOptions(relative_degree=1))
    with pytest.raises(ValueError, match=r"model.h"):
        ecbf_rows(double_integrator())
    with pytest.raises(ValueError, match=r"ECBFOptions.poles"):
        ECBFOptions(poles=(5.0, -1.0))
    with pytest.raises(ValueError, match=r"ECBFOptions.mode"):
        ECBFOptions(mode="medium")


@pytest.mark.parametrize("mode", ["soft", "hard"])
def test_single_constraint_equals_its_closed_form_projection(mode, rng):
    """Without an active box, min |u - u_ref|^2 s.t. a u >= b is u_ref + max(0, b - a u_ref)
    a / |a|^2: OSQP must reproduce it when the row is violated; otherwise u = u_ref exactly."""
    model = double_integrator(obstacles=OBSTACLES[:1], u_limit=1e4)
    filt = ECBFFilter(model, ECBFOptions(mode=mode))
    n_active = 0
    for x in _random_states(rng, 40):
        u_ref = 20 * rng.standard_normal(2)
        a, b = filt.ecbf(x)
        a, b = a[0], b[0]
        expected = u_ref + max(0.0, b - a @ u_ref) / (a @ a) * a
        res = filt(x, u_ref)
        assert not res.infeasible and not res.fallback_used
        np.testing.assert_allclose(res.u, expected, atol=1e-6)
        if b - a @ u_ref > 0:
            n_active += 1
            assert res.status == "solved" and res.active_rows == (0,)
        else:
            assert res.status == "unconstrained" and res.active_rows == ()
            np.testing.assert_array_equal(res.u, u_ref)
    assert 5 <= n_active <= 35


@pytest.mark.parametrize("mode", ["soft", "hard"])
def test_osqp_agrees_with_daqp_on_random_instances(mode, rng):
    """The same QP (rows normalised, slacks in soft mode) through qpsolvers/daqp, on instances
    where OSQP runs and where the exact shortcuts (u_ref, clip(u_ref)) apply."""
    model = double_integrator(obstacles=OBSTACLES, u_limit=15.0)
    opts = ECBFOptions(mode=mode)
    filt = ECBFFilter(model, opts)
    lb, ub = model.u_min, model.u_max
    statuses = []
    for x in _random_states(rng, 200, r_min=1.55, r_max=2.5, speed=4.0):
        u_ref = 12 * rng.standard_normal(2)
        a, b = filt.ecbf(x)
        an = a / np.linalg.norm(a, axis=1)[:, None]
        bn = b / np.linalg.norm(a, axis=1)
        if mode == "hard":
            ref = qpsolvers.solve_qp(2 * np.eye(2), -2 * u_ref, G=-an, h=-bn, lb=lb, ub=ub,
                                     solver="daqp")
            if ref is None:  # infeasible: see the infeasibility test
                continue
        else:
            nh = len(b)
            P = np.diag(np.r_[2.0, 2.0, 2 * opts.slack_quadratic * np.ones(nh)])
            q = np.r_[-2 * u_ref, opts.slack_linear * np.ones(nh)]
            G = -np.hstack([an, np.eye(nh)])
            ref = qpsolvers.solve_qp(P, q, G=G, h=-bn, lb=np.r_[lb, np.zeros(nh)],
                                     ub=np.r_[ub, np.full(nh, np.inf)], solver="daqp")
        res = filt(x, u_ref)
        statuses.append(res.status)
        assert not res.fallback_used
        np.testing.assert_allclose(res.u, ref[:2], atol=1e-6)
        if not res.infeasible:
            assert np.all(res.slack <= 1e-6)
    assert statuses.count("solved") >= 40
    assert {"unconstrained", "box", "solved"} <= set(statuses)


def test_infeasible_step_gives_slack_and_a_flag_never_an_exception(capfd):
    """Fast towards the obstacle and close to it: no control in the box satisfies the row."""
    model = double_integrator(obstacles=OBSTACLES[:1], u_limit=15.0)
    x = np.array([-1.6, 0.1, 10.0, 0.0])
    u_ref = np.array([10.0, 0.0])
    a, b = ECBFFilter(model).ecbf(x)
    assert a[0] @ np.array([-15.0, 0.0]) < b[0]  # infeasible within the box
    soft = ECBFFilter(model)(x, u_ref)
    assert soft.infeasible and not soft.fallback_used and soft.status == "solved"
    assert soft.slack[0] > 1.0
    np.testing.assert_allclose(soft.u, [-15.0, 0.0], atol=1e-6)  # the least-violation control
    np.testing.assert_allclose(soft.slack[0], (b[0] - a[0] @ soft.u) / np.linalg.norm(a[0]))
    hard = ECBFFilter(model, ECBFOptions(mode="hard"))(x, u_ref)
    assert hard.infeasible and hard.fallback_used and hard.status.startswith("fallback")
    np.testing.assert_array_equal(hard.u, u_ref)  # clip(u_ref); inside the box here
    assert hard.slack[0] > 1.0
    assert capfd.readouterr().out == ""


def test_filter_batch_equals_stepwise_calls(rng):
    model = double_integrator(obstacles=OBSTACLES, u_limit=15.0)
    X = _random_states(rng, 50, r_min=1.55, r_max=3.0, speed=5.0)
    U_ref = 12 * rng.standard_normal((50, 2))
    batch = ECBFFilter(model).filter_batch(X, U_ref)
    single = ECBFFilter(model)
    results = [single(x, u) for x, u in zip(X, U_ref, strict=True)]
    np.testing.assert_array_equal(batch.u, np.array([r.u for r in results]))
    np.testing.assert_array_equal(batch.infeasible, [r.infeasible for r in results])
    np.testing.assert_array_equal(batch.qp_solved,
                                  [r.status not in ("unconstrained", "box") for r in results])
    assert batch.qp_solved.any() and not batch.qp_solved.all()


def _rotating_plane(obstacle: Circle, w: float = 0.7, dt: float = 0.05) -> Model:
    """p+ = p + dt (Omega p + u), Omega a rotation rate w: a drift, and u acting on p directly,
    so the margin is truly relative degree 1 and L_f h = 2 (p - c)^T Omega p is nonzero."""
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 2)
    drift = ca.vertcat(-w * x[1], w * x[0])
    return Model.from_expressions("rotating_plane", x, u, x + dt * (drift + u), dt=dt,
                                  u_min=[-5, -5], u_max=[5, 5],
                                  h=circle_margins(x, (obstacle,)), obstacles=(obstacle,))


def test_degree_one_row_includes_lf_h_closed_form(rng):
    """A degree-1 row is L_g h u >= -gamma h - L_f h. On the rotating plane
    L_f h = 2 d^T Omega p, L_g h = 2 d (d = p - c): checked against that closed form."""
    c, w = Circle((1.0, -0.5), 0.8), 0.7
    model = _rotating_plane(c, w)
    rows = ecbf_rows(model, ECBFOptions(gamma=3.0))
    assert rows.relative_degrees == (1,)
    omega = np.array([[0.0, -w], [w, 0.0]])
    for _ in range(10):
        p = rng.uniform(-4, 4, 2)
        d = p - np.array(c.center)
        h = d @ d - c.radius**2
        a, b = rows(p)
        np.testing.assert_allclose(a[0], 2 * d, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(b[0], -3.0 * h - 2 * d @ (omega @ p), rtol=1e-12, atol=1e-12)
        lfh = float(np.asarray(rows.lie(p, model.scene_value)[1]).ravel()[0])
        assert abs(lfh) > 0 or abs(d @ (omega @ p)) == 0


def test_zoh_double_integrator_is_relative_degree_two_closed_form(rng):
    """u enters the ZOH double integrator's first difference only through the
    1/2 dt^2 u term, so the margin is degree 2. Read as xdot = (F - x)/dt: f = [v, 0],
    g = [dt/2 I, I], so L_f h = 2 d.v, L_g h = dt d, L_f^2 h = 2|v|^2, L_g L_f h = dt v + 2 d,
    and the row is (L_g L_f h + k1 L_g h) u >= -L_f^2 h - k1 L_f h - k0 h."""
    dt = 0.02
    model = double_integrator(obstacles=OBSTACLES, integrator="zoh", dt=dt)
    opts = ECBFOptions(poles=(3.0, 7.0))
    rows = ecbf_rows(model, opts)
    assert rows.relative_degrees == (2, 2)
    k0, k1 = 21.0, 10.0
    for x in _random_states(rng, 10):
        p, v = x[:2], x[2:]
        a, b = rows(x)
        for i, c in enumerate(OBSTACLES):
            d = p - np.array(c.center)
            h = d @ d - c.radius**2
            np.testing.assert_allclose(a[i], dt * v + 2 * d + k1 * dt * d, rtol=1e-12,
                                       atol=1e-12)
            np.testing.assert_allclose(b[i], -2 * v @ v - 2 * k1 * d @ v - k0 * h,
                                       rtol=1e-12, atol=1e-9)
    with pytest.raises(ValueError, match=r"ECBFOptions.relative_degree = 1.*relative degree 2"):
        ecbf_rows(model, ECBFOptions(relative_degree=1))
    assert ecbf_rows(model, ECBFOptions(relative_degree=2)).relative_degrees == (2, 2)


@pytest.mark.parametrize("dt", [0.01, 0.05, 0.2])
def test_relative_degree_is_detected_from_the_discrete_model(dt):
    from workbench.filters.ecbf import relative_degrees

    c = Circle((1.0, 0.5), 0.6)
    assert relative_degrees(double_integrator(obstacles=(c,), dt=dt)) == (2,)
    assert relative_degrees(double_integrator(obstacles=(c,), dt=dt, integrator="zoh")) == (2,)
    assert relative_degrees(single_integrator(obstacles=(c,), dt=dt)) == (1,)
    assert relative_degrees(_rotating_plane(c, dt=dt)) == (1,)


# ---------------------------------------------------------------------------------------------
# a filter for the fault tests below


def _filter(**options) -> ECBFFilter:
    return ECBFFilter(double_integrator(obstacles=ECBF_OBSTACLES, u_limit=15.0),
                      ECBFOptions(**options))


# ---------------------------------------------------------------------------------------------
# an interrupt inside the QP solve must propagate, not become a fallback step


def _endless(filt: ECBFFilter) -> ECBFFilter:
    """Make every OSQP solve run until interrupted (no termination checks, huge max_iter)."""
    filt._solver.update_settings(max_iter=10**9, check_termination=0)
    return filt


def _sigint_after(seconds: float) -> threading.Timer:
    timer = threading.Timer(seconds, lambda: os.kill(os.getpid(), signal.SIGINT))
    timer.start()
    return timer


@pytest.mark.parametrize("call", ["single", "batch"])
def test_class1_sigint_inside_osqp_raises_keyboard_interrupt_promptly(call):
    filt = _endless(_filter())
    t0 = time.perf_counter()
    timer = _sigint_after(0.3)
    try:
        with pytest.raises(KeyboardInterrupt):
            if call == "single":
                filt(X_ACTIVE, U_TOWARDS)
            else:
                filt.filter_batch(np.array([X_ACTIVE, X_ACTIVE]), np.array([U_TOWARDS] * 2))
    finally:
        timer.cancel()
    assert time.perf_counter() - t0 < 5.0


def test_class1_filter_is_usable_after_an_interrupt():
    filt = _endless(_filter())
    timer = _sigint_after(0.3)
    try:
        with pytest.raises(KeyboardInterrupt):
            filt(X_ACTIVE, U_TOWARDS)
    finally:
        timer.cancel()
    res = filt(X_ACTIVE, U_TOWARDS)  # the workspace was set up afresh (normal settings)
    assert res.status == "solved" and not res.fallback_used
    np.testing.assert_allclose(res.u, _filter()(X_ACTIVE, U_TOWARDS).u, atol=1e-9)


def test_class1_interrupted_status_is_never_a_fallback(monkeypatch):
    """The status OSQP returns after catching SIGINT maps to KeyboardInterrupt (no signal)."""
    import osqp

    filt = _filter()
    real = filt._solver

    class Interrupted:
        def update(self, **kw):
            real.update(**kw)

        def solve(self, raise_error=False):
            res = real.solve(raise_error=False)
            res.info.status, res.info.status_val = "interrupted", osqp.SolverStatus.OSQP_SIGINT
            return res

    filt._solver = Interrupted()
    with pytest.raises(KeyboardInterrupt):
        filt(X_ACTIVE, U_TOWARDS)


# ---------------------------------------------------------------------------------------------
# a NaN state must not poison the OSQP workspace


@pytest.mark.parametrize("bad", [
    [np.nan, 0.1, 3.0, 0.0], [-1.7, np.inf, 3.0, 0.0], [-1.7, 0.1, 3.0, -np.inf]])
def test_class2_non_finite_state_is_rejected_before_the_solver(bad):
    filt = _filter()
    with pytest.raises(ValueError, match=r"^x = .* finite"):
        filt(np.array(bad), U_TOWARDS)
    res = filt(X_ACTIVE, U_TOWARDS)  # the next normal step is solved, not a fallback
    assert res.status == "solved" and not res.fallback_used


def test_class2_non_finite_batch_state_names_the_row():
    X = np.array([X_ACTIVE, [np.nan, 0.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match=r"(?s)^X = .*row 1"):
        _filter().filter_batch(X, np.array([U_TOWARDS] * 2))


@pytest.mark.parametrize("field", ["a", "b"])
def test_class2_non_finite_rows_are_rejected(field):
    filt = _filter()
    a, b = filt.rows(X_ACTIVE)
    (a if field == "a" else b)[0] = np.nan
    with pytest.raises(ValueError, match=rf"(?s)^{field} = .*finite"):
        filt.solve_rows(a, b, U_TOWARDS)
    assert filt(X_ACTIVE, U_TOWARDS).status == "solved"


def test_class2_broken_workspace_is_reset_and_the_step_solved(capfd):
    """A workspace left broken (non-quasidefinite KKT after NaN data reached OSQP) is set up
    afresh on the error status: the step is solved, and so are the later ones."""
    filt = _filter()
    expected = _filter()(X_ACTIVE, U_TOWARDS).u
    # what one step at a NaN state did before the input check: NaN rows through OSQP
    nh, pos = filt.nh, filt._a_pos
    filt._l[:nh], filt._Ax[pos] = np.nan, np.nan
    filt._solver.update(q=filt._q, l=filt._l, Ax=filt._Ax)
    filt._solver.solve(raise_error=False)
    for _ in range(3):
        res = filt(X_ACTIVE, U_TOWARDS)
        assert res.status == "solved" and not res.fallback_used
        np.testing.assert_allclose(res.u, expected, atol=1e-9)
    capfd.readouterr()


# a state of the wrong length names the state, not numpy broadcasting


@pytest.mark.parametrize("x", [[1.0, 2.0], [1.0, 2.0, 3.0, 4.0, 5.0], [[-1.7, 0.1, 3.0, 0.0]]])
def test_class7_ecbf_state_of_wrong_shape_names_x(x):
    with pytest.raises(ValueError, match=r"^x = .*shape \(4,\)"):
        _filter()(x, U_TOWARDS)


def test_class7_ecbf_batch_of_wrong_width_names_X():
    with pytest.raises(ValueError, match=r"(?s)^X = .*shape \(N, 4\)"):
        _filter().filter_batch(np.zeros((3, 2)), np.zeros((3, 2)))


@pytest.mark.parametrize(("kw", "message"), [
    ({"max_iter": True},
     "ECBFOptions.max_iter = True is invalid: must be an integer in [1, 1000000]"),
    ({"relative_degree": True},
     "ECBFOptions.relative_degree = True is invalid: must be an integer in [1, 2]"),
    ({"gamma": True}, "ECBFOptions.gamma = True is invalid: must be a finite number > 0"),
    ({"polish": 1}, "ECBFOptions.polish = 1 is invalid: must be true or false"),
    ({"warm_start": 0.0}, "ECBFOptions.warm_start = 0. is invalid: must be true or false"),
])
def test_options_reject_bool_numbers_and_numeric_flags(kw, message):
    with pytest.raises(ValueError, match="^" + re.escape(message)):
        ECBFOptions(**kw)

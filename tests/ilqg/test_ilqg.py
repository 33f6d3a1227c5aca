"""iLQG: Riccati oracle, control limits, box QP vs a QP solver, compiled passes vs NumPy twin,
the C outer loop's options record."""

from __future__ import annotations

import ctypes
import re

import numpy as np
import pytest
import qpsolvers

from workbench.ilqg import ILQGOptions, ilqg, make_passes
from workbench.ilqg.compiled import (
    SolveOptions,
    box_qp_compiled,
    problem_library,
    solve_options_layout,
)
from workbench.ilqg.twin import PassesTwin, box_qp
from workbench.problem.costs import quadratic_tracking
from workbench.problem.models import double_integrator
from workbench.problem.problem import Problem


def _lq_problem(u_limit=np.inf):
    model = double_integrator(u_limit=u_limit)
    cost = quadratic_tracking(model, Q=[3, 2, 0.5, 0.1], R=[0.05, 0.02], S=[50, 40, 5, 5])
    return Problem.build(model, cost)


def _riccati(A, B, Q, R, S, x0, r):
    """Finite-horizon LQR with state reference r (T+1,n): an oracle independent of iLQG."""
    T = r.shape[0] - 1
    Pm, s = S.copy(), -S @ r[T]
    gains = []
    for t in range(T - 1, -1, -1):
        Quu, Qux = R + B.T @ Pm @ B, B.T @ Pm @ A
        Qxx, qx, qu = Q + A.T @ Pm @ A, -Q @ r[t] + A.T @ s, B.T @ s
        K, kff = -np.linalg.solve(Quu, Qux), -np.linalg.solve(Quu, qu)
        Pm, s = Qxx + Qux.T @ K, qx + Qux.T @ kff
        gains.append((K, kff))
    gains.reverse()
    x, U = x0.copy(), []
    for K, kff in gains:
        U.append(K @ x + kff)
        x = A @ x + B @ U[-1]
    return np.array(U)


@pytest.mark.parametrize("backend", ["compiled", "numpy"])
def test_lq_one_iteration_equals_riccati(backend, rng):
    problem = _lq_problem()
    T, dt = 60, problem.model.dt
    A = np.block([[np.eye(2), dt * np.eye(2)], [np.zeros((2, 2)), np.eye(2)]])
    B = np.vstack([np.zeros((2, 2)), dt * np.eye(2)])
    x0 = np.array([1.0, -2.0, 0.5, 0.3])
    r = np.cumsum(rng.normal(0, 0.1, (T + 1, 4)), axis=0)
    P = problem.cost.params(T, x_ref=r)
    U_star = _riccati(A, B, np.diag([3, 2, 0.5, 0.1]), np.diag([0.05, 0.02]),
                      np.diag([50, 40, 5, 5.0]), x0, r)
    res = ilqg(problem, x0, rng.normal(0, 3, (T, 2)), P,
               ILQGOptions(max_iter=1, mu_init=0.0, mu_min=0.0, backend=backend))
    assert res.history[0].accepted and res.history[0].alpha == 1.0
    np.testing.assert_allclose(res.U, U_star, rtol=1e-8, atol=1e-8)


@pytest.mark.parametrize("backend", ["compiled", "numpy"])
def test_control_limits_hold_exactly(backend, bas_tracking, scene):
    problem, P = bas_tracking
    lim = problem.model.u_max
    res = ilqg(problem, scene.start, np.zeros((scene.horizon, 2)), P,
               ILQGOptions(backend=backend, max_iter=15))
    assert np.all(res.U <= lim) and np.all(res.U >= -lim)
    assert np.any(np.isclose(np.abs(res.U), lim, rtol=0, atol=0))  # some limits are active


def test_box_qp_agrees_with_qp_solver(bas_tracking, rng):
    lib = problem_library(bas_tracking[0])
    solver = "daqp" if "daqp" in qpsolvers.available_solvers else "osqp"
    n_active = 0
    for _ in range(200):
        n = int(rng.integers(1, 6))
        M = rng.normal(size=(n, n))
        H = M @ M.T + 0.1 * np.eye(n)
        g = rng.normal(0, 3, n)
        lo = -rng.uniform(0, 2, n)
        hi = rng.uniform(0, 2, n)
        x_ref = qpsolvers.solve_qp(H, g, lb=lo, ub=hi, solver=solver, eps_abs=1e-12) \
            if solver == "osqp" else qpsolvers.solve_qp(H, g, lb=lo, ub=hi, solver=solver)
        x0 = rng.normal(size=n)
        qp_np = box_qp(H, g, lo, hi, x0)
        qp_c = box_qp_compiled(lib, H, g, lo, hi, x0)
        assert qp_np.result >= 1 and qp_c.result == qp_np.result
        np.testing.assert_allclose(qp_np.x, x_ref, atol=1e-7)
        np.testing.assert_allclose(qp_c.x, qp_np.x, rtol=1e-12, atol=1e-14)
        np.testing.assert_array_equal(qp_c.free, qp_np.free)
        n_active += int(np.any(~qp_np.free))
    assert n_active > 50  # the test exercises clamped coordinates


def test_box_qp_reports_non_convex():
    H = np.array([[1.0, 0.0], [0.0, -1.0]])
    qp = box_qp(H, np.array([0.1, 0.1]), -np.inf * np.ones(2), np.inf * np.ones(2), np.zeros(2))
    assert qp.result == -1


@pytest.mark.parametrize(("reg", "boxed"), [(0, True), (1, True), (0, False), (1, False)])
def test_compiled_passes_equal_numpy_twin(bas_tracking, scene, rng, reg, boxed):
    problem, P = bas_tracking
    T = scene.horizon
    fast, slow = make_passes(problem, T, "compiled"), PassesTwin(problem, T)
    x0 = problem.check_initial_state(scene.start)
    U = rng.normal(0, 4, (T, 2))
    umin, umax = problem.model.u_min, problem.model.u_max
    fw_s = slow.forward(x0, np.zeros((T + 1, 5)), U, np.zeros((T, 2)), np.zeros((T, 2, 5)),
                        P, 0.0, umin, umax, use_policy=False)
    fw_f = fast.forward(x0, np.zeros((T + 1, 5)), U, np.zeros((T, 2)), np.zeros((T, 2, 5)),
                        P, 0.0, umin, umax, use_policy=False)
    X, J = fw_s.X, fw_s.cost
    np.testing.assert_allclose(fw_f.X, X, rtol=1e-12, atol=1e-13)
    assert fw_f.cost == pytest.approx(J, rel=1e-12)
    U = np.clip(U, umin, umax)
    d_s, d_f = slow.derivatives(X, U, P), fast.derivatives(X, U, P)
    for name in d_s:
        np.testing.assert_allclose(d_f[name], d_s[name], rtol=1e-12, atol=1e-14, err_msg=name)
    bw_s = slow.backward(d_s, U, umin, umax, 0.3, reg, boxed)
    bw_f = fast.backward(d_f, U, umin, umax, 0.3, reg, boxed)
    assert bw_s.status == bw_f.status == 0
    np.testing.assert_allclose(bw_f.k, bw_s.k, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(bw_f.K, bw_s.K, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(bw_f.dV, bw_s.dV, rtol=1e-9)
    k_s, K_s, dV_s = bw_s.k, bw_s.K, bw_s.dV
    out_s = slow.line_search(x0, X, U, k_s, K_s, P, J, dV_s, (1.0, 0.5, 0.1), 0.0, umin, umax)
    out_f = fast.line_search(x0, X, U, k_s, K_s, P, J, dV_s, (1.0, 0.5, 0.1), 0.0, umin, umax)
    assert out_s.accepted == out_f.accepted and out_s.alpha == out_f.alpha
    np.testing.assert_allclose(out_f.X, out_s.X, rtol=1e-12, atol=1e-13)


def test_whole_solves_agree_across_backends(bas_tracking, scene):
    """Gauss-Newton, 30 iterations (second order: test_ddp.py compares whole solves, whose
    rounding differences reach ~4e-5 relative mid-solve in the indefinite phase, same steps)."""
    problem, P = bas_tracking
    U0 = np.zeros((scene.horizon, 2))
    gn = {"max_iter": 30, "second_order": False}
    a = ilqg(problem, scene.start, U0, P, ILQGOptions(backend="compiled", **gn))
    b = ilqg(problem, scene.start, U0, P, ILQGOptions(backend="numpy", **gn))
    assert a.backend == "compiled" and b.backend == "numpy"
    assert a.iterations == b.iterations
    assert a.cost == pytest.approx(b.cost, rel=1e-9)
    np.testing.assert_allclose(a.U, b.U, rtol=0, atol=1e-6)  # |U| <= 15: rounding only
    accepted = [h.cost for h in a.history if h.accepted]
    assert all(np.diff(accepted) < 0)  # every accepted step decreases the cost


def test_unsafe_initial_guess_is_replaced(bas_tracking, scene):
    problem, P = bas_tracking
    U0 = np.tile([15.0, 0.0], (scene.horizon, 1))  # straight into the obstacle
    res = ilqg(problem, scene.start, U0, P, ILQGOptions(max_iter=3))
    assert res.initial_guess_replaced


def test_bad_input_raises_named_errors(bas_tracking, scene):
    problem, P = bas_tracking
    U0 = np.zeros((scene.horizon, 2))
    with pytest.raises(ValueError, match="x0"):
        ilqg(problem, [np.inf, 0, 0, 0], U0, P)
    with pytest.raises(ValueError, match=r"x0 .*inside obstacle"):
        ilqg(problem, [0.0, 0.5, 0, 0], U0, P)
    with pytest.raises(ValueError, match="U0"):
        ilqg(problem, scene.start, np.zeros((scene.horizon, 3)), P)
    with pytest.raises(ValueError, match="P"):
        ilqg(problem, scene.start, U0, P[:, :3])
    with pytest.raises(ValueError, match="max_iter"):
        ILQGOptions(max_iter=0)
    with pytest.raises(ValueError, match="regularization"):
        ILQGOptions(regularization="both")
    with pytest.raises(ValueError, match="alphas"):
        ILQGOptions(alphas=(1.0, 2.0))


@pytest.mark.parametrize("q_beta", [1e-2, 1.0])
def test_compiled_outer_loop_equals_python_loop(scene, q_beta):
    """wb_solve (C) and the Python loop over the same compiled passes take the same steps."""
    from conftest import bas_tracking_problem

    problem, P = bas_tracking_problem(scene, q_beta=q_beta)
    U0 = np.zeros((scene.horizon, 2))
    a = ilqg(problem, scene.start, U0, P, ILQGOptions(outer_loop="compiled"))
    b = ilqg(problem, scene.start, U0, P, ILQGOptions(outer_loop="python"))
    assert (a.iterations, a.stop_reason, a.converged) == (b.iterations, b.stop_reason,
                                                          b.converged)
    assert [h.accepted for h in a.history] == [h.accepted for h in b.history]
    np.testing.assert_array_equal([h.alpha for h in a.history], [h.alpha for h in b.history])
    np.testing.assert_allclose(a.cost, b.cost, rtol=1e-14)
    np.testing.assert_allclose(a.U, b.U, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(a.K, b.K, rtol=1e-10, atol=1e-10)


def test_solve_options_record_has_the_c_layout(bas_tracking):
    """The ctypes mirror and core.c's wb_solve_options: same size, names, offsets, sizes."""
    size, fields = solve_options_layout(problem_library(bas_tracking[0]))
    assert size == ctypes.sizeof(SolveOptions)
    assert fields == tuple((name, getattr(SolveOptions, name).offset,
                            getattr(SolveOptions, name).size) for name, _ in SolveOptions._fields_)
    assert [f[0] for f in fields] == [
        "max_iter", "reg", "boxed", "second_order", "gn_fallback", "fallback_mu", "mu_init",
        "mu_factor", "mu_min", "mu_max", "z_min", "tol_abs", "tol_rel", "tol_grad"]


@pytest.mark.parametrize("options", [
    {"max_iter": 4},
    {"regularization": "state", "mu_init": 3.0, "mu_factor": 2.5},
    {"box_qp": False, "mu_min": 1e-3},
    {"z_min": 0.5, "tol_rel": 1e-3},
    {"tol_abs": 50.0},
    {"tol_grad": 0.5, "mu_init": 0.0},
    {"mu_max": 1.0, "mu_init": 0.9, "second_order": False},
    {"mu_max": 1.0, "mu_init": 0.9, "gauss_newton_fallback": False},
    {"fallback_mu": 10.0},
], ids=lambda o: ",".join(o))
def test_compiled_outer_loop_reads_each_option(bas_tracking, scene, options):
    """Each option reaches wb_solve in its own field: with non-default values the C loop takes
    the same steps and stops for the same reason as the Python loop."""
    problem, P = bas_tracking
    U0 = np.zeros((scene.horizon, 2))
    a = ilqg(problem, scene.start, U0, P, ILQGOptions(outer_loop="compiled", **options))
    b = ilqg(problem, scene.start, U0, P, ILQGOptions(outer_loop="python", **options))
    assert (a.iterations, a.stop_reason, a.converged) == (b.iterations, b.stop_reason,
                                                          b.converged)
    for field in ("accepted", "alpha", "mu"):
        assert [getattr(h, field) for h in a.history] == [getattr(h, field) for h in b.history]
    np.testing.assert_allclose(a.U, b.U, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize(("kw", "message"), [
    ({"max_iter": True},
     "ILQGOptions.max_iter = True is invalid: must be an integer in [1, 1000000]"),
    ({"mu_init": True}, "ILQGOptions.mu_init = True is invalid: must be a finite number >= 0"),
    ({"alphas": (1.0, True)}, "ILQGOptions.alphas = True is invalid: must be a finite number"),
    ({"z_min": False}, "ILQGOptions.z_min = False is invalid: must be a finite number"),
    ({"box_qp": 1}, "ILQGOptions.box_qp = 1 is invalid: must be true or false"),
    ({"second_order": 0}, "ILQGOptions.second_order = 0 is invalid: must be true or false"),
    ({"gauss_newton_fallback": 1},
     "ILQGOptions.gauss_newton_fallback = 1 is invalid: must be true or false"),
])
def test_options_reject_bool_numbers_and_numeric_flags(kw, message):
    with pytest.raises(ValueError, match="^" + re.escape(message)):
        ILQGOptions(**kw)

"""Full (second-order) DDP: the contracted dynamics Hessian against finite differences, the
compiled second-order backward pass against the NumPy twin, and the tracking solve against IPOPT."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import bas_tracking_problem, central_jacobian

from workbench.ilqg import ILQGOptions, ilqg, make_passes
from workbench.ilqg.oracle import solve_ipopt
from workbench.ilqg.twin import PassesTwin


def _safe_points(problem, rng, n):
    out = []
    while len(out) < n:
        x = np.r_[rng.uniform(-3, 3, 2), rng.normal(0, 2, 2)]
        if problem.model.margins(x).min() > 0.3:
            out.append((problem.model.lift(x), rng.uniform(-10, 10, 2), rng.normal(0, 5, 5)))
    return out


def test_dyn_hess_matches_finite_differences(bas_tracking, rng):
    """d/d(x,u) of lam'[A B] by central differences equals the generated Hessians."""
    problem, _ = bas_tracking
    f = problem.functions
    nx, s = problem.nx, problem.model.scene_value
    for x, u, lam in _safe_points(problem, rng, 10):
        fxx, fuu, fux = (np.asarray(m) for m in f["dyn_hess"](x, u, lam, s))

        def grad(z):
            A, B = (np.asarray(m) for m in f["dyn_jac"](z[:nx], z[nx:], s))
            return np.r_[lam @ A, lam @ B]

        H = central_jacobian(grad, np.r_[x, u], eps=1e-5)
        scale = np.abs(H).max()
        np.testing.assert_allclose(fxx, H[:nx, :nx], atol=1e-6 * scale)
        np.testing.assert_allclose(fuu, H[nx:, nx:], atol=1e-6 * scale)
        np.testing.assert_allclose(fux, H[nx:, :nx], atol=1e-6 * scale)
        np.testing.assert_allclose(fxx, fxx.T, rtol=1e-12, atol=1e-12 * scale)
        assert np.abs(fxx[:2, :2]).max() > 0  # the barrier state is curved in the position


@pytest.mark.parametrize(("reg", "boxed"), [(0, True), (1, True), (0, False), (1, False)])
def test_second_order_passes_equal_numpy_twin(bas_tracking, scene, rng, reg, boxed):
    problem, P = bas_tracking
    T = scene.horizon
    fast, slow = make_passes(problem, T, "compiled"), PassesTwin(problem, T)
    x0 = problem.check_initial_state(scene.start)
    umin, umax = problem.model.u_min, problem.model.u_max
    # a safe trajectory with curvature: a few first-order iterations from zero controls
    res = ilqg(problem, x0, np.zeros((T, 2)), P, ILQGOptions(max_iter=12))
    X, U = res.X, np.clip(res.U + rng.normal(0, 0.5, res.U.shape), umin, umax)
    X = slow.forward(x0, X, U, np.zeros((T, 2)), np.zeros((T, 2, 5)), P, 0.0, umin, umax,
                     use_policy=False).X
    d_s, d_f = slow.derivatives(X, U, P), fast.derivatives(X, U, P)
    np.testing.assert_array_equal(d_f["X"], d_s["X"])
    mu = 1e3  # large enough that Quu stays positive definite with the second-order terms
    bw_s = slow.backward(d_s, U, umin, umax, mu, reg, boxed, True)
    bw_f = fast.backward(d_f, U, umin, umax, mu, reg, boxed, True)
    assert bw_s.status == bw_f.status == 0
    k_s, K_s = bw_s.k, bw_s.K
    np.testing.assert_allclose(bw_f.k, k_s, rtol=1e-12, atol=1e-12 * np.abs(k_s).max())
    np.testing.assert_allclose(bw_f.K, K_s, rtol=1e-12, atol=1e-12 * np.abs(K_s).max())
    np.testing.assert_allclose(bw_f.dV, bw_s.dV, rtol=1e-12)
    # the second-order terms change the pass (the test would not see a missing term otherwise)
    K_1 = slow.backward(d_s, U, umin, umax, mu, reg, boxed, False).K
    assert np.abs(K_1 - K_s).max() > 1e-6 * np.abs(K_s).max()


def test_second_order_on_linear_dynamics_equals_gauss_newton():
    """The double integrator without barrier is linear: the Hessian terms vanish exactly."""
    from workbench.problem.costs import quadratic_tracking
    from workbench.problem.models import double_integrator
    from workbench.problem.problem import Problem

    model = double_integrator(u_limit=5.0)
    problem = Problem.build(model, quadratic_tracking(model, Q=[1, 1, 0.1, 0.1], R=[0.1, 0.1],
                                                      S=[10, 10, 1, 1]))
    T = 40
    P = problem.cost.params(T, x_ref=np.tile([1.0, 2.0, 0.0, 0.0], (T + 1, 1)))
    a = ilqg(problem, np.zeros(4), np.zeros((T, 2)), P, ILQGOptions(second_order=True))
    b = ilqg(problem, np.zeros(4), np.zeros((T, 2)), P, ILQGOptions(second_order=False))
    assert a.iterations == b.iterations
    np.testing.assert_array_equal(a.U, b.U)


@pytest.mark.parametrize("q_beta", [1e-2, 1.0])
def test_ddp_compiled_outer_loop_equals_python_loop(scene, q_beta):
    problem, P = bas_tracking_problem(scene, q_beta=q_beta)
    U0 = np.zeros((scene.horizon, 2))
    a = ilqg(problem, scene.start, U0, P, ILQGOptions(second_order=True))
    b = ilqg(problem, scene.start, U0, P, ILQGOptions(second_order=True, outer_loop="python"))
    assert (a.iterations, a.stop_reason) == (b.iterations, b.stop_reason)
    np.testing.assert_array_equal([h.alpha for h in a.history], [h.alpha for h in b.history])
    np.testing.assert_allclose(a.cost, b.cost, rtol=1e-14)
    np.testing.assert_allclose(a.U, b.U, rtol=1e-12, atol=1e-12)


def test_ddp_whole_solve_agrees_across_backends(bas_tracking, scene):
    """Same steps; rounding differences grow to ~1e-7 relative in the indefinite phase far
    from the optimum (measured, step sizes identical) and contract again at convergence."""
    problem, P = bas_tracking
    U0 = np.zeros((scene.horizon, 2))
    a = ilqg(problem, scene.start, U0, P, ILQGOptions(backend="compiled", second_order=True))
    b = ilqg(problem, scene.start, U0, P, ILQGOptions(backend="numpy", second_order=True))
    assert a.backend == "compiled" and b.backend == "numpy"
    assert a.iterations == b.iterations and a.converged and b.converged
    np.testing.assert_array_equal([h.alpha for h in a.history], [h.alpha for h in b.history])
    assert a.cost == pytest.approx(b.cost, rel=1e-12)


@pytest.mark.parametrize("q_beta", [1e-2, 1.0])
def test_ddp_tracking_converges_in_few_iterations_to_the_ipopt_optimum(scene, q_beta):
    """assumptions §3.3 scene, T=150: full DDP needs <= 50 iterations (Gauss-Newton iLQG: 80-115)
    and ends at IPOPT's optimum."""
    problem, P = bas_tracking_problem(scene, q_beta=q_beta)
    U0 = np.zeros((scene.horizon, 2))
    ddp = ilqg(problem, scene.start, U0, P, ILQGOptions(second_order=True))
    gn = ilqg(problem, scene.start, U0, P, ILQGOptions(second_order=False))
    assert ddp.converged and ddp.iterations <= 50
    assert ddp.iterations < gn.iterations
    assert min(problem.model.margins(x).min() for x in ddp.X) > 0
    oracle = solve_ipopt(problem, scene.start, U0, P)
    assert oracle.success
    assert abs(ddp.cost - oracle.cost) / oracle.cost < 1e-7  # measured: ~1e-9

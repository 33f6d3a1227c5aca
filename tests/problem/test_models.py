"""Models and the problem's exact derivatives against central finite differences."""

from __future__ import annotations

import re

import casadi as ca
import numpy as np
import pytest
from conftest import central_jacobian

from workbench.problem.barrier import BarrierOptions, embed_barrier
from workbench.problem.costs import quadratic_tracking
from workbench.problem.models import Model, double_integrator, single_integrator
from workbench.problem.obstacles import Circle, circles_from_arrays
from workbench.problem.problem import Problem

OBST = circles_from_arrays([[0.0, 0.1], [2.0, -1.0], [-1.5, 1.5]], [1.0, 0.5, 0.7])


def _safe_point(model: Model, rng, lo=-4.0, hi=4.0):
    while True:
        x = rng.uniform(lo, hi, model.n_physical)
        if model.nh == 0 or np.min(model.margins(x)) > 0.3:
            return model.lift(x)


MODELS = {
    "di_euler": lambda: double_integrator(obstacles=OBST),
    "di_zoh": lambda: double_integrator(obstacles=OBST, integrator="zoh"),
    "di_signed": lambda: double_integrator(obstacles=OBST, h_form="signed_distance"),
    "si": lambda: single_integrator(obstacles=OBST),
    "bas_inverse": lambda: embed_barrier(double_integrator(obstacles=OBST)),
    "bas_log_per_obstacle": lambda: embed_barrier(
        double_integrator(obstacles=OBST), BarrierOptions(kind="log", grouping="per_obstacle")),
    "bas_exp_groups_gamma": lambda: embed_barrier(
        double_integrator(obstacles=OBST, integrator="zoh"),
        BarrierOptions(kind="exp", grouping=((0, 2), (1,)), gamma=0.4)),
    "bas_si_gamma": lambda: embed_barrier(single_integrator(obstacles=OBST),
                                          BarrierOptions(gamma=-0.7)),
}


def _problem(model: Model) -> Problem:
    n = model.n_physical
    cost = quadratic_tracking(model, Q=np.arange(1, n + 1), R=[0.3, 0.7], S=2 * np.ones(n),
                              q_beta=0.2, s_beta=0.05)
    return Problem.build(model, cost)


@pytest.mark.parametrize("name", sorted(MODELS))
def test_dynamics_jacobians_match_finite_differences(name, rng):
    problem = _problem(MODELS[name]())
    f, jac = problem.functions["dyn"], problem.functions["dyn_jac"]
    s = problem.model.scene_value
    for _ in range(5):
        x, u = _safe_point(problem.model, rng), rng.uniform(-3, 3, problem.nu)
        A, B = (np.asarray(m) for m in jac(x, u, s))
        A_fd = central_jacobian(lambda z: np.asarray(f(z, u, s)), x)
        B_fd = central_jacobian(lambda z: np.asarray(f(x, z, s)), u)
        np.testing.assert_allclose(A, A_fd, rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(B, B_fd, rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("name", sorted(MODELS))
def test_cost_derivatives_match_finite_differences(name, rng):
    problem = _problem(MODELS[name]())
    fq, tq = problem.functions["stage_quad"], problem.functions["term_quad"]
    for _ in range(3):
        x, u = _safe_point(problem.model, rng), rng.uniform(-3, 3, problem.nu)
        p = rng.uniform(-1, 1, problem.n_p)
        _, lx, lu, lxx, luu, lux = (np.asarray(m) for m in fq(x, u, p))
        grad_x = lambda z: np.asarray(fq(z, u, p)[1])  # noqa: E731
        grad_u = lambda z: np.asarray(fq(x, z, p)[2])  # noqa: E731
        np.testing.assert_allclose(lx.ravel(), central_jacobian(
            lambda z: np.asarray(fq(z, u, p)[0]), x).ravel(), rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(lu.ravel(), central_jacobian(
            lambda z: np.asarray(fq(x, z, p)[0]), u).ravel(), rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(lxx, central_jacobian(grad_x, x), rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(luu, central_jacobian(grad_u, u), rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(lux, central_jacobian(
            lambda z: np.asarray(fq(z, u, p)[2]), x), rtol=1e-6, atol=1e-6)
        _, _, lTxx = (np.asarray(m) for m in tq(x, p))
        np.testing.assert_allclose(lTxx, central_jacobian(
            lambda z: np.asarray(tq(z, p)[1]), x), rtol=1e-6, atol=1e-6)


def test_embedded_jacobian_matches_spec_formula(rng):
    """assumptions §4.4: the beta row of F_bar_x and F_bar_u in closed form (inverse barrier,
    gamma)."""
    gamma = 0.3
    base = double_integrator(obstacles=OBST)
    model = embed_barrier(base, BarrierOptions(gamma=gamma))
    problem = _problem(model)
    x = _safe_point(model, rng, -1, 1)
    u = rng.uniform(-2, 2, 2)
    A, B = (np.asarray(m) for m in problem.functions["dyn_jac"](x, u, model.scene_value))
    dt = 0.02
    Fx = np.block([[np.eye(2), dt * np.eye(2)], [np.zeros((2, 2)), np.eye(2)]])
    Fu = np.vstack([np.zeros((2, 2)), dt * np.eye(2)])
    xp = Fx @ x[:4] + Fu @ u
    row_x, row_u = np.zeros(4), np.zeros(2)
    for c in OBST:
        gp = np.zeros(4)
        gp[:2] = 2 * (xp[:2] - c.center)
        hp = np.sum((xp[:2] - c.center) ** 2) - c.radius**2
        g0 = np.zeros(4)
        g0[:2] = 2 * (x[:2] - c.center)
        h0 = np.sum((x[:2] - c.center) ** 2) - c.radius**2
        row_x += -1 / hp**2 * gp @ Fx + gamma * (-1 / h0**2) * g0
        row_u += -1 / hp**2 * gp @ Fu
    np.testing.assert_allclose(A[4, :4], row_x, rtol=1e-12)
    assert A[4, 4] == pytest.approx(-gamma)
    np.testing.assert_allclose(B[4], row_u, atol=1e-15)
    assert np.all(row_u == 0)  # Euler: h(F(x,u)) does not depend on u (assumptions §2.2)


def test_barrier_state_follows_margins_and_crash_rule(rng):
    model = embed_barrier(double_integrator(obstacles=OBST))
    problem = _problem(model)
    x = model.lift([-3.0, -3.0, 0.0, 0.0])
    assert x[4] == pytest.approx(sum(1 / h for h in model.margins(x[:4])))
    # drive into obstacle 0 at the origin: the state jumps to beta_max and stays capped
    X = problem.rollout(x, np.tile([40.0, 40.0], (60, 1)))
    h = np.array([model.margins(z[:4]).min() for z in X])
    assert np.any(h <= 0)
    crashed = h <= 1e-6
    np.testing.assert_array_equal(X[crashed, 4], 1e6)
    assert np.all(X[:, 4] > 0)  # penetration is never rewarded with a negative barrier
    assert np.all(X[:, 4] <= 1e6)


def test_barrier_options_validation():
    with pytest.raises(ValueError, match="gamma"):
        BarrierOptions(gamma=1.5)
    with pytest.raises(ValueError, match="kind"):
        BarrierOptions(kind="quadratic")
    with pytest.raises(ValueError, match="grouping"):
        embed_barrier(double_integrator(obstacles=OBST), BarrierOptions(grouping=((0,), (1,))))
    with pytest.raises(ValueError, match=r"model\.h"):
        embed_barrier(double_integrator())


def test_model_validation_names_the_field():
    x, u = ca.SX.sym("x", 3), ca.SX.sym("u", 2)
    with pytest.raises(ValueError, match="x_next"):
        Model.from_expressions("bad", x, u, x[:2], dt=0.1, u_min=[-1, -1], u_max=[1, 1])
    with pytest.raises(ValueError, match="dt"):
        Model.from_expressions("bad", x, u, x, dt=0.0, u_min=[-1, -1], u_max=[1, 1])
    with pytest.raises(ValueError, match="dt"):
        double_integrator(dt=-0.02)
    with pytest.raises(ValueError, match=r"u_min\[1\] = 2 is above u_max\[1\] = 1"):
        Model.from_expressions("bad", x, u, x, dt=0.1, u_min=[-1, 2], u_max=[1, 1])
    with pytest.raises(ValueError, match="u_min"):
        Model.from_expressions("bad", x, u, x, dt=0.1, u_min=[-1, -1, 0], u_max=[1, 1])
    y = ca.SX.sym("y")
    with pytest.raises(ValueError, match="x_next"):
        Model.from_expressions("bad", x, u, x + y, dt=0.1, u_min=[-1, -1], u_max=[1, 1])
    with pytest.raises(ValueError, match="radius"):
        Circle((0, 0), -1.0)


def test_problem_input_validation(bas_tracking):
    problem, P = bas_tracking
    with pytest.raises(ValueError, match="x0"):
        problem.check_initial_state([0.0, np.nan, 0.0, 0.0])
    with pytest.raises(ValueError, match=r"x0 .*inside obstacle 0"):
        problem.check_initial_state([0.0, 0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="x0"):
        problem.check_initial_state([0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="U0"):
        problem.check_controls(np.zeros((10, 3)))
    with pytest.raises(ValueError, match=r"P = "):
        problem.check_params(P[:-1], P.shape[0] - 1)


def test_fingerprint_is_stable_and_sensitive(scene):
    from conftest import bas_tracking_problem

    a, _ = bas_tracking_problem(scene)
    b, _ = bas_tracking_problem(scene)
    c, _ = bas_tracking_problem(scene, q_beta=0.5)
    assert a.fingerprint == b.fingerprint != c.fingerprint


def test_hessian_override_replaces_exact_state_hessian():
    """Gauss-Newton replacements (assumptions §6.2) enter lxx; gradients stay exact."""
    import dataclasses

    model = double_integrator(obstacles=OBST, runtime_obstacles=False)  # a cost in h needs them
    cost = quadratic_tracking(model, Q=[1, 1, 1, 1], R=[1, 1], S=[1, 1, 1, 1])
    h0 = model.h[0]
    stage = cost.stage - 0.5 * h0**2  # exact Hessian is indefinite in p
    gn = ca.DM.eye(4) * 7.0
    plain = Problem.build(model, dataclasses.replace(cost, stage=stage))
    over = Problem.build(model, dataclasses.replace(cost, stage=stage, stage_hessian_x=gn))
    x, u, p = np.array([1.0, 2.0, 0.1, 0.2]), np.zeros(2), np.zeros(6)
    a, b = plain.functions["stage_quad"](x, u, p), over.functions["stage_quad"](x, u, p)
    np.testing.assert_array_equal(np.asarray(a[1]), np.asarray(b[1]))
    np.testing.assert_array_equal(np.asarray(b[3]), 7.0 * np.eye(4))
    assert not np.allclose(np.asarray(a[3]), np.asarray(b[3]))
    with pytest.raises(ValueError, match="stage_hessian_x"):
        Problem.build(model, dataclasses.replace(cost, stage_hessian_x=ca.DM.eye(3)))


@pytest.mark.parametrize(("make", "message"), [
    (lambda: BarrierOptions(kappa=True), "BarrierOptions.kappa = True is invalid: must be a "
                                         "finite number > 0"),
    (lambda: BarrierOptions(gamma=False), "BarrierOptions.gamma = False is invalid: must be a "
                                          "finite number >= -1 and <= 1"),
    (lambda: Circle((0.0, 0.0), True), "Circle.radius = True is invalid: must be a finite number"),
    (lambda: double_integrator(dt=True), "dt = True is invalid: must be a finite number > 0"),
])
def test_bool_is_not_a_real(make, message):
    with pytest.raises(ValueError, match="^" + re.escape(message)):
        make()

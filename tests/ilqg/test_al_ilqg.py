"""AL-iLQG (assumptions §6.2) on the tracking scene, against IPOPT with the hard constraint."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from workbench.ilqg.al import ALOptions, al_ilqg, al_problem
from workbench.ilqg.bas import TrackingWeights, tracking_params, tracking_problem
from workbench.ilqg.oracle import solve_ipopt
from workbench.problem.models import double_integrator
from workbench.problem.obstacles import Circle


@pytest.fixture(scope="module")
def tracking(scene):
    model = double_integrator(obstacles=(scene.obstacle,), u_limit=scene.u_limit)
    plain = tracking_problem(model, TrackingWeights())
    P = tracking_params(plain, scene.reference(), scene.target)
    alp = al_problem(model, plain.cost)
    U0 = np.zeros((scene.horizon, 2))
    return model, plain, P, alp, U0, al_ilqg(alp, np.array(scene.start), U0, P)


def test_al_ilqg_touches_the_constraint_and_matches_ipopt(tracking, scene):
    model, plain, P, _, U0, res = tracking
    assert res.converged and res.stop_reason == "converged"
    h = np.array([model.margins(x).min() for x in res.X[1:]])
    assert abs(h.min()) <= 1e-3  # grazes h = 0 ("exactly meets the safety constraint")
    assert res.max_violation <= 1e-4
    assert res.min_margin == pytest.approx(h.min(), abs=1e-12)
    # the unconstrained tracking optimum goes through the obstacle: the constraint is active
    assert res.history[0].max_violation > 1.0
    oracle = solve_ipopt(plain, scene.start, U0, P, hard_constraints=True)
    assert oracle.success
    assert abs(res.cost - oracle.cost) / oracle.cost < 1e-3
    assert res.cost == pytest.approx(plain.total_cost(res.X, res.U, P), rel=1e-12)
    np.testing.assert_allclose(res.X[:, :2], oracle.X[:, :2], atol=0.05)


def test_outer_loop_bookkeeping(tracking):
    _, _, _, alp, _, res = tracking
    lam, mu = res.multipliers, res.penalties
    assert lam.shape == mu.shape == (151, 1)
    assert np.all(lam >= 0) and np.all(lam[0] == 0) and np.all(mu[0] == 1.0)
    assert np.all((mu >= 1.0) & (mu <= 1e8))
    assert lam.max() > 0  # the constraint is active somewhere
    # multipliers are positive only where the trajectory is at (or inside) the boundary
    C = alp.constraint_values(res.X)
    assert np.all(C[lam[:, 0] > 1e-3, 0] > -0.05)
    viol = [it.max_violation for it in res.history]
    assert viol[-1] < 1e-3 * viol[0]
    assert len(res.history) <= 20
    assert res.K.shape == (150, 2, 4) and res.k.shape == (150, 2)


def test_one_problem_with_multiplier_parameters(tracking):
    """lam and mu are parameter blocks of one Problem; the state Hessian is Gauss-Newton."""
    _, _, _, alp, _, _ = tracking
    layout = dict(alp.problem.cost.param_layout)
    assert layout["lam"] == 1 and layout["mu"] == 1
    assert alp.problem.nh == 0  # margins live in the cost, not as crash checks
    quad = alp.problem.functions["stage_quad"]
    n_base = alp.n_base_params
    Q = np.diag([10.0, 10.0, 1.0, 1.0])
    inside, outside = np.array([0.0, 0.5, 1.0, 0.0]), np.array([0.0, -2.0, 1.0, 0.0])
    cases = ((inside, 0.0, 1e3, True), (inside, 5.0, 1.0, True),
             (outside, 0.0, 1e3, False),  # c = -2.16 < 0, lam = 0: inactive
             (outside, 5.0, 1.0, True))  # mu c + lam = 2.84 > 0: active (shifted branch)
    for x, lam, mu, active in cases:
        p = np.r_[np.zeros(n_base), lam, mu, alp.model.scene_value]
        lxx = np.asarray(quad(x, np.zeros(2), p)[3])
        grad_c = -2 * np.array([x[0], x[1] - 0.1, 0.0, 0.0])
        expected = Q + (mu * np.outer(grad_c, grad_c) if active else 0.0)
        np.testing.assert_allclose(lxx, expected, rtol=1e-12, atol=1e-9)
    # the exact Hessian would add (mu c + lam) Hess(c) = -2 (mu c + lam) I_p on the active branch
    exact = ca.hessian(alp.problem.cost.stage, alp.problem.model.x)[0]
    assert not ca.is_equal(ca.simplify(exact), ca.simplify(alp.problem.cost.stage_hessian_x))


def test_options_and_inputs_are_validated():
    with pytest.raises(ValueError, match=r"ALOptions.phi"):
        ALOptions(phi=1.0)
    with pytest.raises(ValueError, match=r"ALOptions.tau"):
        ALOptions(tau=1.5)
    with pytest.raises(ValueError, match=r"ALOptions.mu_update"):
        ALOptions(mu_update="sometimes")
    with pytest.raises(ValueError, match=r"model.h"):
        al_problem(double_integrator(), tracking_problem(double_integrator()).cost)
    model = double_integrator(obstacles=(Circle((0.0, 0.0), 1.0),))
    plain = tracking_problem(model)
    alp = al_problem(model, plain.cost)
    P = np.zeros((11, plain.n_p))
    with pytest.raises(ValueError, match=r"x0"):
        al_ilqg(alp, np.array([0.5, 0.0, 0.0, 0.0]), np.zeros((10, 2)), P)
    with pytest.raises(ValueError, match=r"P_base"):
        al_ilqg(alp, np.array([-3.0, 0.0, 0.0, 0.0]), np.zeros((10, 2)), P[:5])

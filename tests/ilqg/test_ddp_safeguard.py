"""The default iLQG step: full DDP with a Gauss-Newton fallback (ILQGOptions docstring).

Each branch of the fallback rule on a scripted pass object (Python outer loop); the C outer loop
against the Python one where the fallback acts; the planar quadrotor, where plain DDP stops in a
worse local minimum, and the tracking scene, where the fallback never acts.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import bas_tracking_problem
from test_bas_ilqg_vehicles import CASES, OPTIONS, T

from workbench.ilqg import ILQGOptions, ilqg
from workbench.ilqg.bas import TrackingWeights, tracking_problem
from workbench.ilqg.oracle import solve_ipopt
from workbench.ilqg.passes import BackwardResult, ForwardResult, LineSearchResult
from workbench.problem.barrier import BarrierOptions
from workbench.problem.costs import quadratic_tracking
from workbench.problem.models import double_integrator
from workbench.problem.problem import Problem

H = 4  # horizon of the scripted solves


class ScriptedPasses:
    """Passes whose outcomes are scripted per step kind: the backward pass is positive definite
    from ``pd_from[second_order]`` on, the line search accepts (alpha 1, cost - 1) or rejects
    per ``accept[second_order]``. ``calls`` logs (pass, second_order, mu)."""

    name = "scripted"

    def __init__(self, problem: Problem, pd_from: dict, accept: dict):
        self.nx, self.nu = problem.nx, problem.nu
        self.pd_from, self.accept, self.calls = pd_from, accept, []

    def set_scene(self, scene) -> None:
        pass

    def forward(self, x0, X, U, k, K, P, alpha, umin, umax, use_policy=True):
        return ForwardResult(X=np.zeros((H + 1, self.nx)), U=np.array(U), cost=100.0)

    def derivatives(self, X, U, P):
        self.calls.append(("derivatives", None, None))
        return {}

    def backward(self, d, U, umin, umax, mu, reg, boxed, second_order=False):
        self.calls.append(("backward", bool(second_order), mu))
        ok = mu >= self.pd_from[bool(second_order)]
        return BackwardResult(status=0 if ok else 1, k=np.full((H, self.nu), 0.5),
                              K=np.zeros((H, self.nu, self.nx)), dV=np.array([-2.0, 0.5]))

    def line_search(self, x0, X, U, k, K, P, J, dV, alphas, z_min, umin, umax):
        second = self.calls[-1][1]
        self.calls.append(("line_search", second, None))
        if self.accept[second]:
            return LineSearchResult(accepted=True, X=X, U=U, cost=J - 1.0, alpha=1.0,
                                    expected=1.0)
        return LineSearchResult(accepted=False, X=X, U=U, cost=J, alpha=0.0, expected=0.0)


@pytest.fixture(scope="module")
def linear_problem():
    model = double_integrator(u_limit=5.0)
    cost = quadratic_tracking(model, Q=[1, 1, 0.1, 0.1], R=[0.1, 0.1], S=[10, 10, 1, 1])
    problem = Problem.build(model, cost)
    return problem, problem.cost.params(H, x_ref=np.zeros((H + 1, 4)))


def scripted(linear_problem, pd_from, accept, **options):
    """One iteration from mu_init = 0.5: the calls made and the history row."""
    problem, P = linear_problem
    passes = ScriptedPasses(problem, pd_from, accept)
    res = ilqg(problem, np.ones(4), np.zeros((H, 2)), P,
               ILQGOptions(max_iter=1, outer_loop="python", **options), passes=passes)
    # the iteration's calls: up to the derivatives of the gains about the returned trajectory
    marks = [i for i, c in enumerate(passes.calls) if c[0] == "derivatives"] + [None]
    return passes.calls[1:marks[1]], res.history[0] if res.history else None, res


SO, GN = True, False
AFTER_ACCEPT = 0.5 / 1.6  # mu after an accepted step from mu 0.5, delta 1
AFTER_REJECT = 0.5 * 1.6  # mu after a rejected one


def test_accepted_second_order_step_is_kept(linear_problem):
    calls, h, _ = scripted(linear_problem, {SO: 0.0, GN: 0.0}, {SO: True, GN: True})
    assert calls == [("backward", SO, 0.5), ("line_search", SO, None)]
    assert (h.step, h.accepted, h.mu) == ("second_order", True, AFTER_ACCEPT)


def test_rejected_second_order_step_is_redone_as_gauss_newton(linear_problem):
    calls, h, _ = scripted(linear_problem, {SO: 0.0, GN: 0.0}, {SO: False, GN: True})
    assert calls == [("backward", SO, 0.5), ("line_search", SO, None),
                     ("backward", GN, 0.5), ("line_search", GN, None)]
    assert (h.step, h.accepted, h.mu) == ("fallback", True, AFTER_ACCEPT)


def test_both_rejected_grows_mu_from_where_the_iteration_started(linear_problem):
    calls, h, _ = scripted(linear_problem, {SO: 2.0, GN: 0.0}, {SO: False, GN: False})
    # the second-order pass needed mu 0.5 -> 0.8 -> 2.048; Gauss-Newton restarts at 0.5
    assert [c[2] for c in calls if c[0] == "backward"] == [0.5, 0.8, pytest.approx(2.048), 0.5]
    assert (h.step, h.accepted, h.mu) == ("fallback", False, AFTER_REJECT)


def test_second_order_pass_indefinite_up_to_fallback_mu_falls_back(linear_problem):
    calls, h, _ = scripted(linear_problem, {SO: 1e7, GN: 0.0}, {SO: True, GN: True},
                           fallback_mu=1e6)
    second = [c[2] for c in calls if c[:2] == ("backward", SO)]
    assert len(second) > 3 and max(second) <= 1e6 < 1e7
    assert calls[-2:] == [("backward", GN, 0.5), ("line_search", GN, None)]
    assert (h.step, h.accepted, h.mu) == ("fallback", True, AFTER_ACCEPT)
    # the same pass is kept when fallback_mu allows the regularisation it needs
    calls, h, _ = scripted(linear_problem, {SO: 1e7, GN: 0.0}, {SO: True, GN: True},
                           fallback_mu=1e9)
    assert all(c[1] == SO for c in calls) and h.step == "second_order" and h.mu > 1e7 / 1.6


def test_without_the_fallback_second_order_failures_only_grow_mu(linear_problem):
    calls, h, _ = scripted(linear_problem, {SO: 0.0, GN: 0.0}, {SO: False, GN: True},
                           gauss_newton_fallback=False)
    assert calls == [("backward", SO, 0.5), ("line_search", SO, None)]
    assert (h.step, h.accepted, h.mu) == ("second_order", False, AFTER_REJECT)
    _, _, res = scripted(linear_problem, {SO: 1e12, GN: 0.0}, {SO: True, GN: True},
                         gauss_newton_fallback=False)
    assert res.stop_reason == "regularization_limit" and not res.history


def test_gauss_newton_option_never_uses_second_order(linear_problem):
    calls, h, _ = scripted(linear_problem, {SO: 1e12, GN: 0.0}, {SO: True, GN: False},
                           second_order=False)
    assert calls == [("backward", GN, 0.5), ("line_search", GN, None)]
    assert (h.step, h.accepted) == ("gauss_newton", False)


@pytest.fixture(scope="module")
def quadrotor():
    make, x0, target, w, u_ref = CASES["quadrotor"]
    model = make()
    problem = tracking_problem(model, TrackingWeights(**w, q_beta=1e-2),
                               barrier=BarrierOptions())
    x0, target = np.array(x0), np.array(target)
    ref = x0 + np.linspace(0.0, 1.0, T + 1)[:, None] * (target - x0)
    P = problem.cost.params(T, x_ref=ref, beta_ref=problem.model.lift(target)[model.nx:],
                            u_ref=np.full(model.nu, u_ref))
    return problem, x0, np.full((T, model.nu), u_ref), P


def test_default_reaches_ipopt_on_the_quadrotor_faster_than_gauss_newton(quadrotor):
    """Measured: default 14 iterations (11 second order, 3 fallbacks), cost = IPOPT's to 1e-15;
    Gauss-Newton 32; plain DDP stops at 82.3 (IPOPT 48.2)."""
    problem, x0, U0, P = quadrotor
    default = ilqg(problem, x0, U0, P, OPTIONS)
    gn = ilqg(problem, x0, U0, P, dataclasses.replace(OPTIONS, second_order=False))
    ddp = ilqg(problem, x0, U0, P, dataclasses.replace(OPTIONS, gauss_newton_fallback=False))
    oracle = solve_ipopt(problem, x0, U0, P)
    assert default.converged and oracle.success
    assert abs(default.cost - oracle.cost) / oracle.cost < 1e-7
    assert default.iterations < gn.iterations
    counts = default.step_counts
    assert counts["fallback"] >= 1 and counts["second_order"] > counts["fallback"]
    assert counts["gauss_newton"] == 0 and default.history[0].step == "fallback"
    assert ddp.step_counts["fallback"] == 0 and ddp.cost > 1.5 * oracle.cost


def test_compiled_outer_loop_takes_the_same_fallbacks(quadrotor):
    problem, x0, U0, P = quadrotor
    a = ilqg(problem, x0, U0, P, OPTIONS)
    b = ilqg(problem, x0, U0, P, dataclasses.replace(OPTIONS, outer_loop="python"))
    assert a.step_counts["fallback"] >= 1
    for field in ("step", "accepted", "alpha", "mu"):
        assert [getattr(h, field) for h in a.history] == [getattr(h, field) for h in b.history]
    np.testing.assert_allclose(a.cost, b.cost, rtol=1e-12)


def test_fallback_never_acts_on_the_tracking_scene(scene):
    """Tracking, T = 150: the default takes plain DDP's 40 second-order steps. With a small
    fallback_mu the indefinite passes of the early phase (which need mu ~1.5e3) fall back, and
    the compiled and Python loops agree on which."""
    problem, P = bas_tracking_problem(scene)
    U0 = np.zeros((scene.horizon, 2))
    default = ilqg(problem, scene.start, U0, P)
    ddp = ilqg(problem, scene.start, U0, P, ILQGOptions(gauss_newton_fallback=False))
    assert default.step_counts == {"gauss_newton": 0, "second_order": ddp.iterations,
                                   "fallback": 0}
    assert default.iterations == ddp.iterations <= 45 and default.cost == ddp.cost
    low = [ilqg(problem, scene.start, U0, P, ILQGOptions(fallback_mu=10.0, outer_loop=loop))
           for loop in ("compiled", "python")]
    assert low[0].step_counts["fallback"] > 0
    assert [h.step for h in low[0].history] == [h.step for h in low[1].history]

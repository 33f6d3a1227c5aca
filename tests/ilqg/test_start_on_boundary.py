"""A start on an obstacle's boundary is an error about x0 (which obstacle, its margin), not
about the initial guess U0; a rollout that crashes from a safe start says where."""

from __future__ import annotations

import numpy as np
import pytest

from workbench.ilqg import ILQGOptions, ilqg
from workbench.ilqg.bas import bas_ilqg, tracking_params, tracking_problem
from workbench.ilqg.solver import MAX_ITERATIONS
from workbench.problem.models import double_integrator
from workbench.problem.obstacles import Circle

T = 20
TARGET = np.array([4.0, 4.0, 0.0, 0.0])
NUMPY = ILQGOptions(backend="numpy", max_iter=30)


def _plain(obstacle: Circle):
    model = double_integrator(obstacles=(obstacle,), u_limit=5.0)
    problem = tracking_problem(model)
    return model, problem, tracking_params(problem, np.tile(TARGET, (T + 1, 1)), TARGET)


def test_a_start_on_the_boundary_up_to_rounding_names_x0_not_the_initial_guess():
    """(1.7, 2) lies on the circle of radius 0.3 about (2, 2); rounding leaves h = 2.8e-17 > 0.
    Before: 'U0 = [[0. 0.] ...] is invalid: neither the initial guess nor zero controls give a
    safe, finite rollout'."""
    model, problem, P = _plain(Circle((2.0, 2.0), 0.3))
    x0 = np.array([1.7, 2.0, 0.0, 0.0])
    h = model.margins(x0)[0]
    assert 0 < h < 1e-15
    with pytest.raises(ValueError) as exc:
        ilqg(problem, x0, np.zeros((T, 2)), P, NUMPY)
    msg = str(exc.value)
    assert msg.startswith("x0 = [1.7 2.  0.  0. ] is invalid: lies within 1e-15 of the "
                          f"boundary of obstacle 0 (h[0] = {h:.4g} <= 1e-15): on the boundary "
                          "up to rounding (min h = 0)")
    assert "U0" not in msg and "initial guess" not in msg


@pytest.mark.parametrize("solver", ["ilqg", "bas_ilqg"])
def test_a_start_exactly_on_the_boundary_says_on_the_boundary(solver):
    """Before: 'starts inside obstacle 0 (h[0] = 0 <= 0)'."""
    model, problem, P = _plain(Circle((2.0, 2.0), 0.5))
    x0 = np.array([2.5, 2.0, 0.0, 0.0])
    assert model.margins(x0)[0] == 0.0
    expected = (r"^x0 = \[2\.5 2\.  0\.  0\. \] is invalid: lies on the boundary of obstacle 0 "
                r"\(h\[0\] = 0\); the start must be strictly safe \(every h > 0\)$")
    with pytest.raises(ValueError, match=expected):
        if solver == "ilqg":
            ilqg(problem, x0, np.zeros((T, 2)), P, NUMPY)
        else:
            bas_ilqg(model, x0, np.tile(TARGET, (T + 1, 1)), TARGET, options=NUMPY)


def test_a_bas_start_within_the_barrier_crash_margin_names_x0_and_eps_h():
    """h = 1e-9 <= eps_h = 1e-6: the lifted barrier state is already beta_max (a crash).
    Before: the U0 error of the initial guess."""
    model = double_integrator(obstacles=(Circle((2.0, 2.0), 0.5),), u_limit=5.0)
    x0 = np.array([2.5 + 1e-9, 2.0, 0.0, 0.0])
    with pytest.raises(ValueError, match=r"^x0 = .* is invalid: lies within 1e-06 of the "
                       r"boundary of obstacle 0 \(h\[0\] = 1e-09 <= 1e-06\): within "
                       r"BarrierOptions\.eps_h of the boundary the barrier state counts as a "
                       r"crash; the start must have every h > eps_h$"):
        bas_ilqg(model, x0, np.tile(TARGET, (T + 1, 1)), TARGET, options=NUMPY)
    # just outside eps_h the same start solves
    res, _ = bas_ilqg(model, [2.5 + 1e-3, 2.0, 0.0, 0.0], np.tile(TARGET, (T + 1, 1)),
                      TARGET, options=NUMPY)
    assert np.all(np.isfinite(res.X)) and not res.initial_guess_replaced


def test_a_start_inside_is_still_named_inside():
    _, problem, P = _plain(Circle((2.0, 2.0), 0.5))
    with pytest.raises(ValueError, match=r"^x0 = .* lies inside obstacle 0 \(h\[0\] = -0\.25 "
                       r"< 0\)"):
        ilqg(problem, [2.0, 2.0, 0.0, 0.0], np.zeros((T, 2)), P, NUMPY)


def test_a_doomed_safe_start_says_where_the_zero_control_rollout_crashes():
    """A safe start moving fast into the obstacle: both rollouts crash, the message says at
    which step and margin (before: no step, no margin)."""
    _, problem, P = _plain(Circle((2.0, 2.0), 0.5))
    with pytest.raises(ValueError, match=r"(?s)^U0 = .* is invalid: neither the initial guess nor "
                       r"zero controls give a safe, finite rollout from x0 = \[ 1\.  2\. 20\.  "
                       r"0\.\] \(the zero-control rollout crashes at step 2: h\[0\] = -0\.21\)"):
        ilqg(problem, [1.0, 2.0, 20.0, 0.0], np.zeros((T, 2)), P, NUMPY)


def test_the_iteration_limit_is_bounded():
    """Before: max_iter = 10**12 was accepted; the compiled loop then allocated a history of
    10**12 rows."""
    with pytest.raises(ValueError, match=rf"^ILQGOptions\.max_iter = {10**12} is invalid: "
                       rf"must be an integer in \[1, {MAX_ITERATIONS}\]$"):
        ILQGOptions(max_iter=10**12)
    with pytest.raises(ValueError, match=r"^ILQGOptions\.max_iter = True is invalid"):
        ILQGOptions(max_iter=True)
    assert ILQGOptions(max_iter=MAX_ITERATIONS).max_iter == 10**6

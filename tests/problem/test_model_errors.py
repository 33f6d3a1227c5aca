"""A model without controls or states is refused where it is built, naming the field; counts
and numbers of the model builders refuse bools and absurd sizes."""

from __future__ import annotations

import dataclasses

import casadi as ca
import numpy as np
import pytest

from workbench.problem.costs import Cost, quadratic_tracking
from workbench.problem.models import (
    MAX_SCENE_SLOTS,
    Model,
    double_integrator,
    margin_violation,
    single_integrator,
)
from workbench.problem.obstacles import Circle

NO_CONTROLS = (r"^u = 'SX of shape \(0, 1\)' is invalid: has no entries: a model needs at "
               r"least one control \(nu >= 1\); iLQG, the samplers and the safety filters all "
               r"optimise over the controls$")


def test_a_model_with_zero_controls_is_refused_at_construction():
    """Before: built; then quadratic_tracking failed inside NumPy ("zero-size array to
    reduction operation minimum"), the NumPy iLQG inside its gradient norm, and the compiled
    iLQG returned 'line_search_failed' as if it had tried."""
    x = ca.SX.sym("x", 2)
    with pytest.raises(ValueError, match=NO_CONTROLS):
        Model.from_expressions("drift", x, ca.SX.sym("u", 0), 0.9 * x, dt=0.1,
                               u_min=np.zeros(0), u_max=np.zeros(0))


def test_a_model_with_zero_states_is_refused_at_construction():
    x = ca.SX.sym("x", 0)
    with pytest.raises(ValueError, match=r"^x = 'SX of shape \(0, 1\)' is invalid: has no "
                       r"entries: a model needs at least one state \(nx >= 1\)$"):
        Model.from_expressions("empty", x, ca.SX.sym("u", 1), x, dt=0.1, u_min=[-1],
                               u_max=[1])


def test_a_model_built_directly_or_replaced_checks_the_sizes_too():
    m = double_integrator()
    with pytest.raises(ValueError, match=r"^Model\.u = 'SX of shape \(0, 1\)' is invalid: has "
                       "no entries"):
        dataclasses.replace(m, u=ca.SX.sym("u", 0), u_min=np.zeros(0), u_max=np.zeros(0),
                            control_names=())
    with pytest.raises(ValueError, match=r"^Model\.x = 'SX of shape \(0, 1\)' is invalid"):
        dataclasses.replace(m, x=ca.SX.sym("x", 0))
    assert dataclasses.replace(m, name="copy").nu == 2  # a valid model still replaces


def test_a_cost_horizon_is_an_integer_within_the_step_limit():
    cost = quadratic_tracking(double_integrator(), Q=np.ones(4), R=np.ones(2), S=np.ones(4))
    assert cost.params(3).shape == (4, 6)
    with pytest.raises(ValueError, match=r"^T = True is invalid: must be an integer in \[0, "
                       r"10000000\]$"):
        cost.params(True)
    with pytest.raises(ValueError, match=r"^T = 1000000000000 is invalid: must be an integer "
                       r"in \[0, 10000000\]$"):
        cost.params(10**12)  # before: np.zeros((10**12 + 1, 6)), MemoryError
    with pytest.raises(ValueError, match=r"^T = 2\.5 is invalid"):
        Cost(stage=ca.SX(0), terminal=ca.SX(0), p=ca.SX.sym("p", 0)).params(2.5)


@pytest.mark.parametrize(("u_limit", "message"), [
    (True, r"^u_limit = True is invalid: must be a number or \+inf$"),
    ("5", r"^u_limit = '5' is invalid: must be a number > 0 \(np\.inf for no limits\)$"),
    (-1.0, r"^u_limit = -1\. is invalid: must be a number > 0"),
])
def test_a_control_limit_is_a_positive_number(u_limit, message):
    """Before: True gave |u| <= 1 and "5" gave |u| <= 5, silently."""
    with pytest.raises(ValueError, match=message):
        double_integrator(u_limit=u_limit)
    assert single_integrator(u_limit=np.float64(2.0)).u_max.tolist() == [2.0, 2.0]
    assert double_integrator(u_limit=np.array(3.0)).u_max.tolist() == [3.0, 3.0]


def test_scene_slots_are_bounded():
    with pytest.raises(ValueError, match=rf"^scene_capacity = {10**9} is invalid: must be an "
                       rf"integer in \[1, {MAX_SCENE_SLOTS}\]$"):
        double_integrator(obstacles=(Circle((1.0, 1.0), 0.5),), scene_capacity=10**9)
    with pytest.raises(ValueError, match=r"^scene_capacity = True is invalid"):
        double_integrator(scene_capacity=True)
    assert double_integrator(scene_capacity=3).n_scene == 9


def test_margin_violation_words():
    m = double_integrator(obstacles=(Circle((0.0, 0.0), 1.0), Circle((5.0, 0.0), 1.0)))
    assert margin_violation(m, np.array([0.5, 2.0])) is None
    assert margin_violation(m, np.array([0.5, -0.25])) == \
        "lies inside obstacle 1 (h[1] = -0.25 < 0)"
    assert margin_violation(m, np.array([0.0, 3.0])) == \
        "lies on the boundary of obstacle 0 (h[0] = 0)"
    assert margin_violation(m, np.array([1e-9, 3.0]), 1e-6) == \
        "lies within 1e-06 of the boundary of obstacle 0 (h[0] = 1e-09 <= 1e-06)"
    assert margin_violation(m, np.array([1.0, 1.0, -1.0])) == (
        "violates constraint h[2] > 0 of the model (a state limit or a constraint of its h(x)): "
        "h[2] = -1 < 0")


def test_expressions_given_as_lists_are_stacked_and_bad_ones_name_the_field():
    import casadi as ca

    from workbench.problem.models import Model

    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    m = Model.from_expressions("list", x, u, [x[0] + 0.1 * x[1], x[1] + 0.1 * u[0]], dt=0.1,
                               u_min=[-1.0], u_max=[1.0], h=[1.0 - x[0], x[0] + 1.0])
    assert m.nh == 2 and m.x_next.shape == (2, 1)
    assert np.allclose(m.margins(np.array([0.5, 0.0])), [0.5, 1.5])
    with pytest.raises(ValueError, match=r"^h = .* is invalid: must be a CasADi SX expression"):
        Model.from_expressions("bad", x, u, x + ca.vertcat(0, u), dt=0.1, u_min=[-1.0],
                               u_max=[1.0], h=["not an expression"])
    with pytest.raises(ValueError, match=r"^position = .* must be 2 or 3 distinct"):
        Model.from_expressions("bad", x, u, x + ca.vertcat(0, u), dt=0.1, u_min=[-1.0],
                               u_max=[1.0], position=(0, 1, 1))
    with pytest.raises(ValueError, match=r"^position = .* must be 2 or 3 distinct"):
        Model.from_expressions("bad", x, u, x + ca.vertcat(0, u), dt=0.1, u_min=[-1.0],
                               u_max=[1.0], position=(0,))
    for units in (("m",), ("m", 1), "mm"):
        with pytest.raises(ValueError, match=r"^state_units = .* must be 2 strings, one unit "
                           r"per state"):
            Model.from_expressions("bad", x, u, x + ca.vertcat(0, u), dt=0.1, u_min=[-1.0],
                                   u_max=[1.0], state_units=units)


def test_state_units_are_kept_through_embedding_and_default_to_none():
    import casadi as ca

    from workbench.problem.barrier import embed_barrier
    from workbench.problem.models import Model, double_integrator
    from workbench.problem.obstacles import Circle
    from workbench.sampling.planning import physical_model

    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    m = Model.from_expressions("plain", x, u, x + ca.vertcat(0, u), dt=0.1, u_min=[-1.0],
                               u_max=[1.0], state_units=["rad", ""])
    assert m.state_units == ("rad", "")
    assert Model.from_expressions("plain", x, u, x + ca.vertcat(0, u), dt=0.1, u_min=[-1.0],
                                  u_max=[1.0]).state_units is None
    di = double_integrator(obstacles=(Circle((1.0, 1.0), 0.5),))
    assert di.state_units == ("m", "m", "m/s", "m/s")
    emb = embed_barrier(di)
    assert emb.state_units == ("m", "m", "m/s", "m/s", "")
    assert physical_model(emb).state_units == di.state_units

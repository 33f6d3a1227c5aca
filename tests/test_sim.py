"""Plant disturbance models (assumptions §2.3), crash detection on the true plant, plants of other
state sizes."""

from __future__ import annotations

import re

import numpy as np
import pytest

from workbench.problem.models import double_integrator
from workbench.problem.obstacles import Circle
from workbench.sim import Disturbance, closed_loop


@pytest.mark.parametrize(("model", "std"), [
    ("velocity_variance", 0.02 * np.sqrt(10.0)),  # w = dt N(0, 10)
    ("velocity_std", 0.02 * 10.0),  # level read as the std
    ("white_noise", np.sqrt(0.02) * np.sqrt(10.0)),
    ("kick", np.sqrt(10.0)),
])
def test_disturbance_models_have_their_stated_spread(model, std, rng):
    d = Disturbance(10.0, model, velocity_index=(2, 3))
    W = np.array([d.sample(4, 0.02, rng) for _ in range(20000)])
    np.testing.assert_array_equal(W[:, :2], 0.0)  # velocities only
    np.testing.assert_allclose(W[:, 2:].std(axis=0), std, rtol=0.03)


class _Constant:
    def __init__(self, u):
        self.u = np.asarray(u, float)

    def initial_state(self, x0):
        return 0

    def step(self, state, x, rng):
        return state + 1, self.u, {"k": state}


def test_crash_on_the_true_plant_stops_the_episode():
    plant = double_integrator(obstacles=(Circle((1.0, 0.0), 0.5),), u_limit=5.0)
    ep = closed_loop(_Constant([5.0, 0.0]), plant, np.zeros(4), 200, np.random.default_rng(0),
                     np.random.default_rng(1))
    assert ep.crashed and ep.crash_step is not None and len(ep.X) == ep.crash_step + 1
    assert ep.min_margin <= 0 and plant.margins(ep.X[-1]).min() <= 0
    assert [i["k"] for i in ep.infos] == list(range(ep.crash_step))


def test_controls_are_clipped_to_the_plant_box():
    plant = double_integrator(u_limit=2.0)
    ep = closed_loop(_Constant([9.0, -9.0]), plant, np.zeros(4), 5, np.random.default_rng(0),
                     np.random.default_rng(1))
    np.testing.assert_array_equal(ep.U, np.tile([2.0, -2.0], (5, 1)))


# ---------------------------------------------------------------------------------------------
# plants with other state sizes in closed_loop


class _Hold:
    def __init__(self, u):
        self.u = np.asarray(u, float)

    def initial_state(self, x0):
        return 0

    def step(self, state, x, rng):
        return state + 1, self.u, {}


def test_class8_single_integrator_closed_loop_disturbs_the_positions():
    from workbench.problem.models import single_integrator
    from workbench.sim import Disturbance, closed_loop

    plant = single_integrator(dt=0.02, u_limit=5.0)
    u = np.array([1.0, -0.5])
    ep = closed_loop(_Hold(u), plant, np.zeros(2), 4000, np.random.default_rng(0),
                     np.random.default_rng(1), Disturbance(10.0))
    W = np.diff(ep.X, axis=0) - 0.02 * u  # assumptions §2.4: w = dt xi on the position
    np.testing.assert_allclose(W.std(axis=0), 0.02 * np.sqrt(10.0), rtol=0.05)


def test_class8_one_state_plant_runs():
    import casadi as ca

    from workbench.problem.models import Model
    from workbench.sim import Disturbance, closed_loop

    x, u = ca.SX.sym("x", 1), ca.SX.sym("u", 1)
    plant = Model.from_expressions("scalar", x, u, 0.9 * x + 0.1 * u, dt=0.1, u_min=[-1],
                                   u_max=[1], h=1.0 - x**2)
    ep = closed_loop(_Hold([0.0]), plant, [0.0], 20, np.random.default_rng(0),
                     np.random.default_rng(1), Disturbance(0.01, states=("x0",)))
    assert ep.X.shape == (21, 1) and np.any(ep.X[1:] != 0.0)


@pytest.mark.parametrize("index", [(), (-1,), (2, 2), (1.5,)])
def test_class8_bad_disturbance_indices_are_rejected(index):
    from workbench.sim import Disturbance

    with pytest.raises(ValueError, match=r"^Disturbance.velocity_index = "):
        Disturbance(1.0, velocity_index=index)


def test_class8_disturbance_index_out_of_range_for_the_plant_is_named():
    from workbench.problem.models import single_integrator
    from workbench.sim import Disturbance, closed_loop

    with pytest.raises(ValueError, match=r"^Disturbance.velocity_index = .*out of range.*2 states"):
        closed_loop(_Hold([0.0, 0.0]), single_integrator(), np.zeros(2), 3,
                    np.random.default_rng(0), np.random.default_rng(1),
                    Disturbance(1.0, velocity_index=(2, 3)))


def test_class8_double_integrator_default_is_unchanged():
    """Guard (passes before the fix too): the plant-derived indices of the double integrator
    are (2, 3), so default episodes are bit-for-bit those of the explicit velocity indices."""
    from workbench.sim import Disturbance, closed_loop

    plant = double_integrator(u_limit=5.0)
    runs = [closed_loop(_Hold([1.0, 0.5]), plant, np.zeros(4), 50, np.random.default_rng(0),
                        np.random.default_rng(1), d).X
            for d in (Disturbance(10.0), Disturbance(10.0, velocity_index=(2, 3)))]
    np.testing.assert_array_equal(runs[0], runs[1])


@pytest.mark.parametrize(("make", "message"), [
    (lambda: Disturbance(True), "Disturbance.level = True is invalid: must be a finite number"),
    (lambda: Disturbance(1.0, velocity_index=(2, True)),
     "Disturbance.velocity_index = True is invalid: must be an integer >= 0"),
    (lambda: closed_loop(_Hold([0.0, 0.0]), double_integrator(), np.zeros(4), True,
                         np.random.default_rng(0), np.random.default_rng(1)),
     "steps = True is invalid: must be an integer >= 1"),
])
def test_bool_is_neither_an_integer_nor_a_real(make, message):
    with pytest.raises(ValueError, match="^" + re.escape(message)):
        make()


# ---------------------------------------------------------------------------------------------
# disturbances name their states on a model of one's own


def _bicycle():
    import casadi as ca

    from workbench.problem.models import Model

    x, u = ca.SX.sym("x", 4), ca.SX.sym("u", 2)  # px, py, heading, speed; accel, steering
    dt, L = 0.05, 0.5
    x_next = x + dt * ca.vertcat(x[3] * ca.cos(x[2]), x[3] * ca.sin(x[2]),
                                 x[3] / L * ca.tan(u[1]), u[0])
    return Model.from_expressions("bicycle", x, u, x_next, dt=dt, u_min=[-2, -0.5],
                                  u_max=[2, 0.5], state_names=("px", "py", "heading", "v"))


def test_unnamed_disturbance_on_an_own_model_lists_its_states():
    from workbench.sim import disturbed_states

    plant = _bicycle()
    assert disturbed_states(plant) == (2,)  # the old guess: the heading, not the speed
    with pytest.raises(ValueError, match=r"^Disturbance.states = None .*not a built-in planar "
                       r"integrator.*0: 'px', 1: 'py', 2: 'heading', 3: 'v'.*states="):
        closed_loop(_Hold([0.0, 0.0]), plant, np.zeros(4), 3, np.random.default_rng(0),
                    np.random.default_rng(1), Disturbance(1.0))
    # no disturbance: nothing to name, the plant runs undisturbed
    ep = closed_loop(_Hold([1.0, 0.0]), plant, np.zeros(4), 5, np.random.default_rng(0),
                     np.random.default_rng(1))
    np.testing.assert_allclose(ep.X[-1, 3], 5 * 0.05)


@pytest.mark.parametrize("states", [("v",), (3,), "v", 3])
def test_disturbance_names_its_states_by_name_or_index(states):
    plant = _bicycle()
    u = np.array([0.5, 0.1])
    ep = closed_loop(_Hold(u), plant, np.array([0.0, 0.0, 0.0, 1.0]), 200,
                     np.random.default_rng(0), np.random.default_rng(1),
                     Disturbance(10.0, states=states))
    ref = closed_loop(_Hold(u), plant, np.array([0.0, 0.0, 0.0, 1.0]), 200,
                      np.random.default_rng(0), np.random.default_rng(1),
                      Disturbance(10.0, velocity_index=(3,)))
    np.testing.assert_array_equal(ep.X, ref.X)  # by name, by index: the same draws on v
    dv = np.diff(ep.X[:, 3]) - 0.05 * u[0]
    np.testing.assert_allclose(dv.std(), 0.05 * np.sqrt(10.0), rtol=0.15)


@pytest.mark.parametrize(("states", "message"), [
    (("speed",), r"bicycle has no state 'speed'; its states are 0: 'px'.*3: 'v'"),
    ((4,), r"index 4 is out of range for bicycle with 4 states"),
    (("v", 3), r"names the same state twice"),
])
def test_bad_state_names_are_named(states, message):
    with pytest.raises(ValueError, match=r"^Disturbance.states = .*" + message):
        closed_loop(_Hold([0.0, 0.0]), _bicycle(), np.zeros(4), 3, np.random.default_rng(0),
                    np.random.default_rng(1), Disturbance(1.0, states=states))


@pytest.mark.parametrize("states", [(), ("v", "v"), (-1,), (True,), ("v", 1.5)])
def test_bad_states_are_rejected_on_construction(states):
    with pytest.raises(ValueError, match=r"^Disturbance.states = "):
        Disturbance(1.0, states=states)


def test_states_and_velocity_index_are_exclusive():
    with pytest.raises(ValueError, match="either states or velocity_index"):
        Disturbance(1.0, velocity_index=(2,), states=("vx",))


def test_planar_integrators_keep_their_own_states():
    from workbench.problem.barrier import BarrierOptions, embed_barrier
    from workbench.problem.models import single_integrator

    obs = (Circle((1.0, 1.0), 0.3),)
    assert Disturbance(1.0).indices(double_integrator()) == (2, 3)
    assert Disturbance(1.0).indices(single_integrator()) == (0, 1)
    emb = embed_barrier(double_integrator(obstacles=obs), BarrierOptions())
    assert Disturbance(1.0).indices(emb) == (2, 3)
    assert Disturbance(1.0, states=("vx",)).indices(double_integrator()) == (2,)

"""Plant disturbance models (SPEC 2.3) and crash detection on the true plant."""

from __future__ import annotations

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

"""closed_loop records each step's process CPU time beside its wall time: a step that sleeps
costs wall time and almost no CPU time, a step that computes costs both."""

from __future__ import annotations

import time

import numpy as np

from workbench.problem.models import double_integrator
from workbench.sim import closed_loop


class Timed:
    """Zero control; each step sleeps ``sleep_s`` or spins for ``spin_s`` of CPU time."""

    def __init__(self, sleep_s: float = 0.0, spin_s: float = 0.0):
        self.sleep_s, self.spin_s = sleep_s, spin_s

    def initial_state(self, x0=None):
        return None

    def step(self, state, x, rng):
        if self.sleep_s:
            time.sleep(self.sleep_s)
        c = time.process_time()
        while time.process_time() - c < self.spin_s:
            pass
        return state, np.zeros(2), None


def run(ctrl, steps=5):
    plant = double_integrator()
    return closed_loop(ctrl, plant, np.zeros(4), steps, np.random.default_rng(0),
                       np.random.default_rng(1), keep_infos=False)


def test_sleeping_steps_cost_wall_time_not_cpu_time():
    ep = run(Timed(sleep_s=0.02))
    assert ep.step_cpu_s.shape == ep.step_time_s.shape == (5,)
    assert np.all(ep.step_time_s >= 0.02)
    assert np.all(ep.step_cpu_s < 0.005)


def test_computing_steps_cost_cpu_time():
    ep = run(Timed(spin_s=0.01))
    assert np.all(ep.step_cpu_s >= 0.01)
    assert np.all(ep.step_time_s >= 0.9 * ep.step_cpu_s)

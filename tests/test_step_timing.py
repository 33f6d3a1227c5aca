"""closed_loop records each step's process CPU time beside its wall time: a step that sleeps
costs wall time and almost no CPU time, a step that computes costs both."""

from __future__ import annotations

import time

import numpy as np
import pytest

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


class FakeTime:
    """workbench.sim's clock: ``sleep`` and the controller's steps advance it."""

    def __init__(self) -> None:
        self.now, self.sleeps = 10.0, []

    def perf_counter(self) -> float:
        return self.now

    def process_time(self) -> float:
        return self.now

    def sleep(self, s: float) -> None:
        self.sleeps.append(s)
        self.now += s


class Takes:
    """Each step advances the fake clock by the next of ``durations``."""

    def __init__(self, clock: FakeTime, durations: list[float]):
        self.clock, self.durations = clock, list(durations)

    def initial_state(self, x0=None):
        return None

    def step(self, state, x, rng):
        self.clock.now += self.durations.pop(0)
        return state, np.zeros(2), None


def test_a_loop_at_a_rate_starts_each_step_on_its_period_and_never_makes_up_for_a_late_one(
        monkeypatch):
    """period 0.1: steps of 0.03 start at 0, 0.1, 0.2; a step of 0.25 (from 0.2 to 0.45)
    makes the next start late, at 0.45, with no sleep; the period counts from there: the one
    after waits for 0.55 (not for 0.4 or 0.5)."""
    import workbench.sim as sim

    fake = FakeTime()
    monkeypatch.setattr(sim, "time", fake)
    ctrl = Takes(fake, [0.03, 0.03, 0.25, 0.03, 0.03])
    starts = []
    step = ctrl.step

    def recorded(state, x, rng):
        starts.append(fake.now - 10.0)
        return step(state, x, rng)

    ctrl.step = recorded
    ep = closed_loop(ctrl, double_integrator(), np.zeros(4), 5, np.random.default_rng(0),
                     np.random.default_rng(1), keep_infos=False, period_s=0.1)
    np.testing.assert_allclose(starts, [0.0, 0.1, 0.2, 0.45, 0.55], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(fake.sleeps, [0.07, 0.07, 0.07], rtol=1e-9)
    np.testing.assert_allclose(ep.step_time_s, [0.03, 0.03, 0.25, 0.03, 0.03], rtol=1e-9)


@pytest.mark.parametrize("bad", [0.0, -0.05, float("nan"), float("inf"), True, "0.05"])
def test_a_bad_period_is_refused_naming_it(bad):
    with pytest.raises((ValueError, TypeError), match=r"^period_s"):
        closed_loop(Timed(), double_integrator(), np.zeros(4), 2, np.random.default_rng(0),
                    np.random.default_rng(1), period_s=bad)

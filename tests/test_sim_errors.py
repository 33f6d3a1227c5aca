"""closed_loop refuses a start on an obstacle's boundary before the controller sees it;
Disturbance refuses bools and invalid state indices with a message, never an IndexError."""

from __future__ import annotations

import numpy as np
import pytest

from workbench.problem.models import double_integrator
from workbench.problem.obstacles import Circle
from workbench.sim import Disturbance, closed_loop
from workbench.validation import MAX_STEPS


class _Recorder:
    """Holds u = 0 and records whether the episode asked it for anything."""

    def __init__(self):
        self.calls = []

    def set_scene(self, scene):
        self.calls.append("set_scene")

    def initial_state(self, x0=None):
        self.calls.append("initial_state")
        return None

    def step(self, state, x, rng):
        return state, np.zeros(2), None


def _run(ctrl, x0, plant=None, **kw):
    plant = plant or double_integrator(obstacles=(Circle((2.0, 2.0), 0.5),), u_limit=5.0)
    return closed_loop(ctrl, plant, np.asarray(x0, float), 3, np.random.default_rng(0),
                       np.random.default_rng(1), **kw)


def test_a_start_on_the_boundary_is_named_before_the_controller_is_set_up():
    """Before: 'starts inside an obstacle of the scene (min h = 0)', after the controller's
    initial_state had run (a feedback law solving from x0 failed first, confusingly)."""
    ctrl = _Recorder()
    with pytest.raises(ValueError, match=r"^x0 = \[2\.5 2\.  0\.  0\. \] is invalid: lies on "
                       r"the boundary of obstacle 0 \(h\[0\] = 0\) in the scene of step 0 "
                       r"\(min h <= 0 is a crash\); the start must be strictly safe "
                       r"\(every h > 0\)$"):
        _run(ctrl, [2.5, 2.0, 0.0, 0.0], scene=[(2.0, 2.0, 0.5)])
    assert ctrl.calls == []
    with pytest.raises(ValueError, match=r"lies inside obstacle 0 \(h\[0\] = -0\.25 < 0\) in "
                       "the scene of step 0"):
        _run(_Recorder(), [2.0, 2.0, 0.0, 0.0])
    ep = _run(_Recorder(), [2.5 + 1e-9, 2.0, 0.0, 0.0])  # just outside: runs
    assert ep.min_margin > 0 and not ep.crashed


@pytest.mark.parametrize(("call", "message"), [
    (lambda rng: Disturbance(1.0, states=(10,)).sample(4, 0.02, rng),
     r"^Disturbance\.states = '\(10,\)' is invalid: entry 10 is not a state index in \[0, 3\] "
     r"\(the state has nx = 4 entries\)$"),
    (lambda rng: Disturbance(1.0, velocity_index=(9,)).sample(4, 0.02, rng),
     r"^Disturbance\.velocity_index = '\(9,\)' is invalid: entry 9 is not a state index"),
    (lambda rng: Disturbance(1.0).sample(4, 0.02, rng, index=(True,)),
     r"^index = '\(True,\)' is invalid: entry True is not a state index in \[0, 3\]"),
    (lambda rng: Disturbance(1.0).sample(4, 0.02, rng, index=(-1,)),
     r"^index = '\(-1,\)' is invalid: entry -1 is not a state index"),
    (lambda rng: Disturbance(1.0).sample(4, 0.02, rng, index=(2, 2)),
     r"^index = '\(2, 2\)' is invalid: names the same state twice$"),
    (lambda rng: Disturbance(1.0).sample(True, 0.02, rng, index=(0,)),
     r"^nx = True is invalid: must be an integer >= 1$"),
    (lambda rng: Disturbance(1.0).sample(4, 0.0, rng, index=(0,)),
     r"^dt = 0\. is invalid: must be a finite number > 0$"),
])
def test_sample_checks_its_indices(call, message):
    """Before: IndexError / TypeError from NumPy, and index -1 silently disturbed the last
    state."""
    with pytest.raises(ValueError, match=message):
        call(np.random.default_rng(0))


def test_states_accept_numpy_integers_and_refuse_empty_names():
    assert Disturbance(1.0, states=np.int64(2)).states == (2,)  # before: refused
    assert Disturbance(1.0, states=np.array([2, 3])).states == (2, 3)
    with pytest.raises(ValueError, match=r"^Disturbance\.states = \[''\] is invalid: a state "
                       "name must not be empty"):
        Disturbance(1.0, states=("",))  # before: accepted
    with pytest.raises(ValueError, match=r"^Disturbance\.states = True is invalid"):
        Disturbance(1.0, states=np.array([True]))


@pytest.mark.parametrize("field", ["start_step", "duration"])
def test_disturbance_step_counts_are_bounded(field):
    with pytest.raises(ValueError, match=rf"^Disturbance\.{field} = {10**30} is invalid: must "
                       rf"be an integer in \[\d, {MAX_STEPS}\]$"):
        Disturbance(1.0, model="impulse", **{field: 10**30})


def test_stop_at_goal_reads_the_goal_of_a_controller_built_by_hand():
    """Before: ``closed_loop(wb.MPPI(...), stop_at_goal=...)`` failed with "MPPI has no goal
    attribute" although the docstring promised ``controller.goal``."""
    import workbench as wb

    scene = wb.CircleScene(((2.0, 2.0, 0.3),), start=(0.5, 0.5), goal=(1.0, 0.5))
    nav = wb.navigation_setup(scene, mppi=wb.MPPIConfig(n_samples=64, horizon=20,
                                                        sigma=(5.0, 5.0), lam=10.0))
    ctrl = wb.MPPI(nav.problem, nav.goal, nav.mppi)
    assert np.array_equal(ctrl.goal, nav.goal) and not ctrl.goal.flags.writeable
    ep = wb.closed_loop(ctrl, nav.plant, nav.x0, 300, np.random.default_rng(0),
                        np.random.default_rng(1), stop_at_goal=0.1)
    assert len(ep.U) < 300  # it stopped at the goal
    assert np.linalg.norm(ep.X[-1, :2] - nav.goal[:2]) <= 0.1

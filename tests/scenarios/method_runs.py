"""The methods test's check, shared by every test that runs a method by name: it builds, steps
in closed loop under a disturbance, and reports its samples and its mechanism's activity."""

from __future__ import annotations

import numpy as np

import workbench as wb
from workbench.sampling.step_stats import StepStats
from workbench.scenarios.methods import method
from workbench.sim import Controller, StepInfo


def check_method_runs(nav, name: str, steps: int = 3, level: float = 1.0,
                      states=None) -> wb.Episode:
    """Run method ``name`` for ``steps`` steps on ``nav`` and check its step info: sample count,
    collision-free samples, ESS, and its own activity key (the registry's) in [0, 1]."""
    spec = method(name)
    ctrl = nav.controller(name, rule=wb.AlphaRule(kappa=0.1, calibration_steps=10))
    assert isinstance(ctrl, Controller), name  # initial_state, step, set_scene, record_samples
    assert np.array_equal(ctrl.goal, nav.goal), name  # closed_loop(stop_at_goal=) reads it
    ep = wb.closed_loop(ctrl, nav.plant, nav.x0, steps, np.random.default_rng(0),
                        np.random.default_rng(1), wb.Disturbance(level, states=states))
    assert ep.U.shape == (steps, nav.plant.nu) and np.all(np.isfinite(ep.X))
    assert all(isinstance(info, StepInfo) for info in ep.infos)
    st = ep.infos[-1].stats
    assert isinstance(st, StepStats)
    n = nav.mppi.n_samples
    assert st.n_samples == n and 0 <= st.n_collision_free <= n and st.ess >= 1.0
    if spec.activity is not None:
        assert spec.activity in st.activity, (name, dict(st.activity))
    assert all(0.0 <= v <= 1.0 for v in st.activity.values())
    return ep

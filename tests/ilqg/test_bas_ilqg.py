"""BaS-iLQG on the tracking scene of assumptions §3.3 against IPOPT on the same embedded problem."""

from __future__ import annotations

import numpy as np
import pytest

from workbench.ilqg import ILQGOptions
from workbench.ilqg.bas import TrackingWeights, bas_ilqg, tracking_params
from workbench.ilqg.oracle import solve_ipopt
from workbench.problem.barrier import BarrierOptions
from workbench.problem.models import double_integrator


@pytest.mark.parametrize("q_beta", [1e-2, 1.0])
def test_bas_ilqg_tracking_is_safe_and_matches_ipopt(scene, q_beta):
    model = double_integrator(obstacles=(scene.obstacle,), u_limit=scene.u_limit)
    res, problem = bas_ilqg(model, scene.start, scene.reference(), scene.target,
                            weights=TrackingWeights(q_beta=q_beta))
    assert res.converged
    h = np.array([problem.model.margins(x).min() for x in res.X])
    assert h.min() > 0
    assert np.linalg.norm(res.X[-1, :2] - np.array(scene.target[:2])) < 0.1
    # the reference passes through the obstacle: the barrier is what keeps the solution safe
    assert np.min([model.margins(x).min() for x in scene.reference()]) < 0
    P = tracking_params(problem, scene.reference(), scene.target)
    oracle = solve_ipopt(problem, scene.start, np.zeros((scene.horizon, 2)), P)
    assert oracle.success
    assert res.cost == pytest.approx(oracle.cost, rel=1e-3)
    assert abs(res.cost - oracle.cost) / oracle.cost < 1e-5  # what we measure: ~1e-7


def test_bas_ilqg_gains_and_the_barrier_state(scene):
    """With gamma = 0, d beta_{k+1} / d beta_k = 0, so the gains on beta vanish exactly and the
    barrier acts through the gains on x (V_xx carries its curvature); gamma != 0 couples beta."""
    model = double_integrator(obstacles=(scene.obstacle,), u_limit=scene.u_limit)
    opts = ILQGOptions(max_iter=60)
    res, _ = bas_ilqg(model, scene.start, scene.reference(), scene.target, options=opts)
    assert res.K.shape == (scene.horizon, 2, 5)
    np.testing.assert_array_equal(res.K[:, :, 4], 0.0)
    relaxed, _ = bas_ilqg(model, scene.start, scene.reference(), scene.target,
                          barrier=BarrierOptions(gamma=0.5), options=opts)
    assert np.max(np.abs(relaxed.K[:, :, 4])) > 1e-6

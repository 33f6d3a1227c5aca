"""Every controller and filter takes a scene of any kind at run time (assumptions §3.4).

A model built with a :class:`~workbench.problem.scene_layout.SceneLayout` (circles,
half-planes, capsules, moving circles; a signed-distance grid in its own model) is accepted by
MPPI and BaS-MPPI, Robust MPPI with iLQG feedback (SA-RMPPI), BaS-iLQG, the ECBF filter and
the DCBF-based samplers (CBF projection, shield, tube, gatekeeper). After their first step,
a scene change of every kind (new circles, a moved half-plane, a new capsule, new velocities,
a new grid of the same shape) is applied (the next step differs) and builds nothing
(``build_counts`` unchanged).
"""

from __future__ import annotations

import numpy as np
import pytest

import workbench as wb
from workbench.problem.obstacles import Circle
from workbench.problem.scene_kinds import Capsule, HalfSpace, MovingCircle
from workbench.problem.scene_layout import SceneLayout
from workbench.problem.sdf_grid import SignedDistanceGrid
from workbench.sampling.feedback import ILQGFeedback
from workbench.sampling.methods.cbf_projection import CBFProjectionConfig, CBFProjectionMPPI
from workbench.sampling.methods.gatekeeper import Gatekeeper, braking_backup
from workbench.sampling.methods.shield import ShieldConfig, ShieldMPPI
from workbench.sampling.methods.tube import TubeMPPI
from workbench.sampling.mppi import MPPI, MPPIConfig
from workbench.sampling.problem import navigation_costs
from workbench.sampling.robust import RMPPIConfig, RobustMPPI
from workbench.sampling.threshold import ConstantThreshold

LAYOUT = SceneLayout.of(circles=2, halfspaces=2, capsules=1, moving=1)
SCENE = (Circle((1.2, 1.0), 0.4), HalfSpace((0.0, 1.0), -0.6), Capsule((2.0, 0.2), (2.4, 1.4), 0.2),
         MovingCircle((0.6, 1.6), 0.3, (0.2, 0.0)))
# every kind changed: other circles, the half-plane moved, a new capsule, new velocities
CHANGED = (Circle((0.55, 0.5), 0.2), Circle((1.6, 1.3), 0.3), HalfSpace((0.0, 1.0), -0.4),
           Capsule((1.5, -0.2), (1.9, 0.9), 0.25), MovingCircle((0.6, 1.6), 0.3, (-0.4, 0.3)))
X0 = np.array([0.2, 0.3, 0.8, 0.4])
GOAL = np.array([3.0, 1.5, 0.0, 0.0])
REST = np.array([0.2, 0.3, 0.0, 0.0])  # iLQG starts at rest: zero controls stay safe
CFG = MPPIConfig(n_samples=64, horizon=20, sigma=(2.0, 2.0), backend="compiled")


def grid(shift: float) -> SignedDistanceGrid:
    xs, ys = np.arange(12) * 0.4 - 0.6, np.arange(10) * 0.4 - 0.8
    d = np.hypot(xs[:, None] - 1.3 - shift, ys[None, :] - 0.8) - 0.5
    return SignedDistanceGrid(d, (-0.6, -0.8), 0.4)


@pytest.fixture(scope="module")
def models():
    plain = wb.double_integrator(scene_layout=LAYOUT, obstacles=SCENE, u_limit=5.0)
    gl = SceneLayout.of(circles=1, grid=(12, 10))
    gplain = wb.double_integrator(scene_layout=gl, obstacles=[grid(0.0)], u_limit=5.0)
    return plain, wb.embed_barrier(plain), gplain, wb.embed_barrier(gplain)


def controllers(plain, bas):
    sp, phys = navigation_costs(bas), navigation_costs(plain, S=(10.0, 10.0, 1.0, 1.0))
    return {
        "mppi": MPPI(phys, GOAL, CFG),
        "bas_mppi": MPPI(sp, GOAL, CFG),
        "sa_rmppi": RobustMPPI(sp, GOAL, CFG, RMPPIConfig(n_candidates=3),
                               ILQGFeedback(bas, CFG.horizon, bas.nx),
                               ConstantThreshold(1e9)),
        "cbf_projection": CBFProjectionMPPI(phys, GOAL, CFG, CBFProjectionConfig(gamma=0.1)),
        "shield": ShieldMPPI(phys, GOAL, CFG, ShieldConfig(gamma=0.1)),
        "tube": TubeMPPI(phys, GOAL, CFG),
        "gatekeeper": Gatekeeper(MPPI(phys, GOAL, CFG), plain, braking_backup(plain)),
    }


def two_controls(ctrl, scene):
    """The control of a first step, and that of the same step after ``set_scene(scene)``,
    from the same state and random stream."""
    st = ctrl.initial_state(X0)
    _, u0, _ = ctrl.step(st, X0, np.random.default_rng(3))
    ctrl.set_scene(scene)
    _, u1, _ = ctrl.step(ctrl.initial_state(X0), X0, np.random.default_rng(3))
    return u0, u1


def test_sampling_controllers_take_every_kind_at_run_time(models):
    plain, bas, _, _ = models
    ctrls = controllers(plain, bas)
    for ctrl in ctrls.values():  # first steps build what they need
        ctrl.step(ctrl.initial_state(X0), X0, np.random.default_rng(0))
    before = wb.build_counts()
    for name, ctrl in ctrls.items():
        u0, u1 = two_controls(ctrl, CHANGED)
        assert not np.allclose(u0, u1), name  # the new scene is applied
        np.testing.assert_array_equal(ctrl.scene, plain.scene_vector(CHANGED), err_msg=name)
    assert wb.build_counts() == before


def test_bas_ilqg_and_the_ecbf_filter_take_every_kind_at_run_time(models):
    plain, bas, _, _ = models
    weights = wb.TrackingWeights(Q=(1, 1, 0.1, 0.1), R=(0.1, 0.1), S=(10, 10, 1, 1))
    problem = wb.tracking_problem(bas, weights)
    T = 20
    x_ref = np.linspace(REST, GOAL, T + 1)
    P = wb.tracking_params(problem, x_ref, GOAL)
    # moving circles are predicted per step, on the NumPy passes (the compiled ones hold one
    # scene over the horizon): "compiled" is refused for this layout
    with pytest.raises(ValueError, match="compiled iLQG passes hold one scene"):
        wb.ilqg(problem, REST, np.zeros((T, 2)), P,
                wb.ILQGOptions(backend="compiled", max_iter=5))
    opts = wb.ILQGOptions(backend="auto", max_iter=5)
    a = wb.ilqg(problem, REST, np.zeros((T, 2)), P, opts)
    filt = wb.ECBFFilter(plain)
    x, u = np.array([0.9, 0.3, 1.0, 0.5]), np.array([4.0, 3.0])
    f0 = filt(x, u).u
    before = wb.build_counts()
    b = wb.ilqg(problem, REST, np.zeros((T, 2)), P, opts, scene=CHANGED)
    assert not np.allclose(a.X, b.X)
    filt.set_scene(CHANGED)
    assert not np.allclose(filt(x, u).u, f0)
    assert wb.build_counts() == before


def test_a_new_grid_of_the_same_shape_builds_nothing(models):
    """The sampler kernels, BaS-iLQG and the filter all compile the grid."""
    gplain, gbas = models[2], models[3]
    sp = navigation_costs(gbas)
    ctrl = MPPI(sp, GOAL, CFG)
    weights = wb.TrackingWeights(Q=(1, 1, 0.1, 0.1), R=(0.1, 0.1), S=(10, 10, 1, 1))
    problem = wb.tracking_problem(gbas, weights)
    T = 20
    P = wb.tracking_params(problem, np.linspace(REST, GOAL, T + 1), GOAL)
    opts = wb.ILQGOptions(backend="compiled", max_iter=5)
    a = wb.ilqg(problem, REST, np.zeros((T, 2)), P, opts)
    filt = wb.ECBFFilter(gplain)
    x, u = np.array([0.5, 0.6, 1.0, 0.3]), np.array([4.0, 1.0])
    f0 = filt(x, u).u
    ctrl.step(ctrl.initial_state(X0), X0, np.random.default_rng(0))
    before = wb.build_counts()
    moved = [grid(0.3)]
    u0, u1 = two_controls(ctrl, moved)
    assert not np.allclose(u0, u1)
    b = wb.ilqg(problem, REST, np.zeros((T, 2)), P, opts, scene=moved)
    assert not np.allclose(a.X, b.X)
    filt.set_scene(moved)
    assert not np.allclose(filt(x, u).u, f0)
    assert wb.build_counts() == before

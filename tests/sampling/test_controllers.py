"""Closed-loop controllers: navigation through the cluttered map, determinism, bad input."""

from __future__ import annotations

import re

import numpy as np
import pytest

from workbench.sampling.mppi import MPPI, MPPIConfig
from workbench.sampling.robust import RMPPIConfig, RobustMPPI
from workbench.scenarios.navigation import navigation_setup
from workbench.sim import Disturbance, closed_loop


@pytest.fixture(scope="module")
def nav():
    return navigation_setup()


def _run(nav, ctrl, steps, seed=1, level=0.0):
    return closed_loop(ctrl, nav.plant, nav.x0, steps, np.random.default_rng(seed),
                       np.random.default_rng(seed + 100), Disturbance(level))


def test_bas_mppi_reaches_goal_safely_undisturbed(nav):
    ep = _run(nav, MPPI(nav.problem, nav.goal, nav.mppi), 1000)
    assert not ep.crashed and ep.min_margin > 0
    assert np.linalg.norm(ep.X[-1, :2] - nav.goal[:2]) < 0.1


def test_sa_rmppi_reaches_goal_safely_undisturbed(nav):
    ctrl = nav.controller("sa_rmppi")  # default calibrated alpha rule
    ep = _run(nav, ctrl, 1000)
    assert not ep.crashed and ep.min_margin > 0
    assert np.linalg.norm(ep.X[-1, :2] - nav.goal[:2]) < 0.1
    infos = ep.infos
    assert all(i.feedback_ok for i in infos)
    assert infos[0].candidate == 8 and len(infos[1].candidate_free_energy) == 9
    assert set(infos[-1].timing) == {"selection", "k_safe", "sais", "update", "total"}


def test_rmppi_with_plain_ilqg_feedback_runs(nav):
    ctrl = RobustMPPI(nav.problem, nav.goal, nav.mppi, RMPPIConfig(alpha=2e4, applied="real"),
                      nav.feedback("ilqg"))
    ep = _run(nav, ctrl, 20, level=10.0)
    assert ep.U.shape == (20, 2) and np.all(np.isfinite(ep.X))


@pytest.mark.parametrize("kind", ["mppi", "sa_rmppi"])
def test_same_seed_same_trajectory_whatever_the_thread_count(nav, kind):
    def make():
        if kind == "mppi":
            return MPPI(nav.problem, nav.goal, nav.mppi)
        return RobustMPPI(nav.problem, nav.goal, nav.mppi, RMPPIConfig(alpha=2e4))

    a = _run(nav, make(), 25, seed=3, level=50.0)
    ctrl = make()
    ctrl.sampler.lib.set_threads(1)
    try:
        b = _run(nav, ctrl, 25, seed=3, level=50.0)
    finally:
        ctrl.sampler.lib.set_threads(2)
    np.testing.assert_array_equal(a.X, b.X)
    c = _run(nav, make(), 25, seed=4, level=50.0)
    assert not np.array_equal(a.X, c.X)


def test_bad_controller_input_names_the_field(nav):
    ctrl = MPPI(nav.problem, nav.goal, nav.mppi)
    with pytest.raises(ValueError, match="x"):
        ctrl.step(ctrl.initial_state(), [np.nan, 0, 0, 0], np.random.default_rng(0))
    with pytest.raises(ValueError, match="horizon"):
        MPPIConfig(horizon=0)
    with pytest.raises(ValueError, match="n_samples"):
        MPPIConfig(n_samples=0)
    with pytest.raises(ValueError, match="lam"):
        MPPIConfig(lam=0.0)
    with pytest.raises(ValueError, match="sigma"):
        MPPIConfig(sigma=(1.0, -1.0))
    with pytest.raises(ValueError, match="positive definite"):
        MPPIConfig.with_covariance([[1.0, 2.0], [2.0, 1.0]])
    with pytest.raises(ValueError, match="n_candidates"):
        RMPPIConfig(n_candidates=4)
    with pytest.raises(ValueError, match="steps"):
        closed_loop(ctrl, nav.plant, nav.x0, 0, np.random.default_rng(0),
                    np.random.default_rng(1))
    with pytest.raises(ValueError, match=r"Disturbance\.level"):
        Disturbance(-1.0)


def test_plain_mppi_runs_on_the_physical_model(nav):
    from workbench.sampling.problem import navigation_costs

    sp = navigation_costs(nav.plant, S=(10.0, 10.0, 1.0, 1.0))
    ctrl = MPPI(sp, nav.goal, nav.mppi)
    ep = _run(nav, ctrl, 30)
    assert not ep.crashed and ep.U.shape == (30, 2)
    assert np.linalg.norm(ep.X[-1, :2] - nav.x0[:2]) > 0.05  # it moves towards the goal


@pytest.mark.parametrize(("T", "window", "order"), [(100, 9, 2), (37, 5, 3), (11, 11, 0)])
def test_savgol_matrix_equals_scipy_per_element(T, window, order):
    """Both ends (scipy's "interp" polynomial fits) and the interior, per element, relative."""
    from scipy.signal import savgol_filter

    from workbench.sampling.mppi import savgol_matrix

    U = np.random.default_rng(T).normal(0.0, 10.0, (T, 3)) ** 3
    want = savgol_filter(U, window, order, axis=0)
    got = savgol_matrix(T, window, order) @ U
    assert np.all(np.abs(got - want) <= 1e-12 * np.maximum(np.abs(want), 1.0))
    assert not np.allclose(got, U)  # the filter acts


def test_savitzky_golay_smoothing_option(nav):
    from dataclasses import replace

    from scipy.signal import savgol_filter

    rough = MPPI(nav.problem, nav.goal, nav.mppi)
    smooth = MPPI(nav.problem, nav.goal, replace(nav.mppi, smoothing=(9, 2)))
    a, ua, _ = rough.step(rough.initial_state(), nav.x0, np.random.default_rng(7))
    b, ub, _ = smooth.step(smooth.initial_state(), nav.x0, np.random.default_rng(7))
    # the same samples: the smoothed sequence is the filtered update (then shifted)
    expected = savgol_filter(np.vstack([ua, a.U[:-1]]), 9, 2, axis=0)
    np.testing.assert_allclose(ub, expected[0], atol=1e-12)
    np.testing.assert_allclose(b.U[:-1], expected[1:], atol=1e-12)
    with pytest.raises(ValueError, match="smoothing"):
        replace(nav.mppi, smoothing=(8, 2))


@pytest.mark.parametrize(("config", "kw", "message"), [
    (MPPIConfig, {"n_samples": True}, "MPPIConfig.n_samples = True is invalid: must be an integer"),
    (MPPIConfig, {"horizon": np.True_}, "MPPIConfig.horizon = True is invalid: must be an integer"),
    (MPPIConfig, {"smoothing": (True, 0)}, "MPPIConfig.smoothing = True is invalid: must be an "
                                           "integer"),
    (MPPIConfig, {"lam": True}, "MPPIConfig.lam = True is invalid: must be a finite number"),
    (MPPIConfig, {"nu_mix": False}, "MPPIConfig.nu_mix = False is invalid: must be a finite"),
    (RMPPIConfig, {"candidate_samples": True},
     "RMPPIConfig.candidate_samples = True is invalid: must be an integer"),
    (RMPPIConfig, {"alpha": True}, "RMPPIConfig.alpha = True is invalid: must be a number or"),
    (RMPPIConfig, {"clip_in_cost": 1}, "RMPPIConfig.clip_in_cost = 1 is invalid: must be true or"),
    (RMPPIConfig, {"diagnostics": 0}, "RMPPIConfig.diagnostics = 0 is invalid: must be true or"),
])
def test_bool_is_not_a_number_and_a_number_is_not_a_flag(config, kw, message):
    with pytest.raises(ValueError, match="^" + re.escape(message)):
        config(**kw)


def test_numpy_integers_and_plus_inf_are_accepted():
    assert MPPIConfig(n_samples=np.int64(64), horizon=np.int32(20)).n_samples == 64
    assert RMPPIConfig(alpha=np.inf).alpha == np.inf
    assert RMPPIConfig(diagnostics=np.True_).diagnostics

"""Threshold calibration as one explicit, seeded step: the public function, the navigation
set-up's wrapper, and the navigation study calibrating once per run in the coordinator."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from studies.navigation import STUDY
from studies.navigation.tasks import Controllers, Realisation, controller, plan, prepare
from workbench.sampling.calibration import calibrate, calibration_trace
from workbench.sampling.mppi import MPPIConfig
from workbench.sampling.threshold import AlphaRule, ConstantThreshold, ProgressThreshold
from workbench.scenarios.navigation import navigation_setup
from workbench.study.runner import profile_config

RULE = AlphaRule(kappa=0.1, calibration_steps=30)


@pytest.fixture(scope="module")
def nav():
    return navigation_setup(mppi=MPPIConfig(n_samples=128, horizon=30, sigma=(5.0, 5.0),
                                            lam=10.0))


def test_calibrate_equals_the_setup_threshold_and_depends_on_its_seed(nav):
    fb = nav.feedback("bas_ilqg")
    th = calibrate(RULE, nav.problem, nav.goal, nav.plant, nav.x0, nav.mppi, fb)
    assert isinstance(th, ProgressThreshold)
    same = nav.threshold(RULE, "bas_ilqg")
    np.testing.assert_array_equal(th.log_d, same.log_d)
    np.testing.assert_array_equal(th.F, same.F)
    X, F = calibration_trace(nav.problem, nav.goal, nav.plant, nav.x0, nav.mppi, fb, steps=30,
                             seed=5)
    _, F0 = calibration_trace(nav.problem, nav.goal, nav.plant, nav.x0, nav.mppi, fb, steps=30)
    assert X.shape == (30, 4) and F.shape == (30,) and np.isfinite(F).sum() >= 2
    assert not np.array_equal(F, F0)  # the controller's draws follow the seed


def test_a_progress_expression_equal_to_the_distance_gives_the_default_threshold(nav):
    """The progress measure is the distance in the position coordinates by default; the same
    distance given as a CasADi expression is the oracle. A model without positions needs one."""
    import casadi as ca

    fb = nav.feedback("bas_ilqg")
    trace = calibration_trace(nav.problem, nav.goal, nav.plant, nav.x0, nav.mppi, fb, steps=30)
    default = calibrate(RULE, nav.problem, nav.goal, nav.plant, nav.x0, nav.mppi, fb,
                        trace=trace)
    x = nav.plant.x
    dist = ca.sqrt((x[0] - nav.goal[0]) ** 2 + (x[1] - nav.goal[1]) ** 2)
    given = calibrate(RULE, nav.problem, nav.goal, nav.plant, nav.x0, nav.mppi, fb, trace=trace,
                      progress=dist)
    np.testing.assert_allclose(given.log_d, default.log_d, rtol=1e-12)
    np.testing.assert_allclose(given.F, default.F, rtol=1e-12)
    X = trace[0]
    np.testing.assert_allclose(given(X), default(X), rtol=1e-12)
    # a different measure (the squared distance) gives a different curve, same values on X
    sq = calibrate(RULE, nav.problem, nav.goal, nav.plant, nav.x0, nav.mppi, fb, trace=trace,
                   progress=dist**2)
    assert not np.allclose(sq.log_d, default.log_d)
    with pytest.raises(ValueError, match=r"progress.*scalar"):
        calibrate(RULE, nav.problem, nav.goal, nav.plant, nav.x0, nav.mppi, fb, trace=trace,
                  progress=ca.vertcat(dist, dist))
    with pytest.raises(ValueError, match=r"progress.*plant's state"):
        calibrate(RULE, nav.problem, nav.goal, nav.plant, nav.x0, nav.mppi, fb, trace=trace,
                  progress=dist + ca.SX.sym("other"))
    no_position = replace(nav.plant, position=None)
    with pytest.raises(ValueError, match=r"progress.*position coordinates"):
        calibrate(RULE, nav.problem, nav.goal, no_position, nav.x0, nav.mppi, fb, trace=trace)


def test_a_fixed_rule_needs_no_episode_and_bad_steps_name_the_field(nav):
    th = calibrate(AlphaRule(kind="fixed", value=3.0), None, None, None, None, None, None)
    assert isinstance(th, ConstantThreshold) and th.value == 3.0
    for bad in (True, 0, 2.5):
        with pytest.raises(ValueError, match=r"^steps = "):
            calibration_trace(nav.problem, nav.goal, nav.plant, nav.x0, nav.mppi,
                              nav.feedback("ilqg"), steps=bad)


def test_the_study_calibrates_each_rule_once_and_hands_it_to_every_controller():
    cfg = replace(profile_config(STUDY, "tiny"),
                  sampler=MPPIConfig(n_samples=128, horizon=30, sigma=(5.0, 5.0), lam=10.0))
    thresholds = prepare(cfg)
    robust = {(t.controller, t.rule) for t in plan(cfg).tasks
              if isinstance(t, Realisation) and t.controller != "bas_mppi"
              and t.controller != "mppi_crash"}
    c = Controllers.of(cfg)
    assert set(thresholds) == {(c, name, rule) for name, rule in robust}
    for name, rule in robust:
        assert controller(c, name, rule, thresholds).threshold is thresholds[(c, name, rule)]
    again = prepare(replace(cfg, calibration_seed=1))
    key = (c, "sa_rmppi", cfg.rule)
    assert not np.array_equal(again[key].F, thresholds[key].F)

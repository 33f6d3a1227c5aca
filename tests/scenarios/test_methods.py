"""Every safe-sampling method by name on a navigation set-up: each builds, steps, and reports
its mechanism's activity; bad options name the field."""

from __future__ import annotations

import pytest
from method_runs import check_method_runs  # tests/scenarios/method_runs.py

import workbench as wb
from workbench.scenarios.methods import MethodSettings, build, names


@pytest.fixture(scope="module")
def nav():
    return wb.navigation_setup(mppi=wb.MPPIConfig(n_samples=64, horizon=30, sigma=(5.0, 5.0),
                                                  lam=10.0))


@pytest.mark.parametrize("name", names())
def test_every_method_builds_by_name_and_reports_its_mechanism(nav, name):
    check_method_runs(nav, name, steps=4, level=10.0)


def test_robust_method_without_threshold_and_bad_settings_name_the_field(nav):
    with pytest.raises(ValueError, match=r"^threshold"):
        build(nav, "sais_al")
    with pytest.raises(ValueError, match=r"^controller"):
        build(nav, "mppi_magic")
    with pytest.raises(ValueError, match=r"^methods\.braking_gain"):
        MethodSettings(braking_gain=-1.0)
    with pytest.raises(ValueError, match=r"^methods\.tube"):
        MethodSettings(tube=0.5)

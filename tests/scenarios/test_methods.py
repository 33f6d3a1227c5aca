"""Every safe-sampling method by name on a navigation set-up: each builds, steps, and reports
its mechanism's activity; bad options name the field."""

from __future__ import annotations

import numpy as np
import pytest

import workbench as wb
from workbench.scenarios.methods import METHODS, MethodSettings, build

ACTIVITY = {"tube_mppi": "nominal_reset", "cbf_projection": "projected",
            "shield_mppi": "shield_acted", "gatekeeper": "backup_used", "sais_al": "al_active",
            "sais_ecbf": "ecbf_active", "sa_rmppi": "nominal_differs"}


@pytest.fixture(scope="module")
def nav():
    return wb.navigation_setup(mppi=wb.MPPIConfig(n_samples=64, horizon=30, sigma=(5.0, 5.0),
                                                  lam=10.0))


@pytest.mark.parametrize("name", METHODS)
def test_every_method_builds_by_name_and_reports_its_mechanism(nav, name):
    ctrl = nav.controller(name, rule=wb.AlphaRule(kappa=0.1, calibration_steps=20))
    ep = wb.closed_loop(ctrl, nav.plant, nav.x0, 4, np.random.default_rng(0),
                        np.random.default_rng(1), wb.Disturbance(10.0))
    st = ep.infos[-1].stats
    assert st.n_samples == 64 and 0 <= st.n_collision_free <= 64 and st.ess >= 1.0
    if name in ACTIVITY:
        assert ACTIVITY[name] in st.activity
    assert all(0.0 <= v <= 1.0 for v in st.activity.values())


def test_robust_method_without_threshold_and_bad_settings_name_the_field(nav):
    with pytest.raises(ValueError, match=r"^threshold"):
        build(nav, "sais_al")
    with pytest.raises(ValueError, match=r"^controller"):
        build(nav, "mppi_magic")
    with pytest.raises(ValueError, match=r"^methods\.braking_gain"):
        MethodSettings(braking_gain=-1.0)
    with pytest.raises(ValueError, match=r"^methods\.tube"):
        MethodSettings(tube=0.5)

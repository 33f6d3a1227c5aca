"""Fixtures of the gatekeeper tests: the two user models of ``examples/user_models.py`` (a 3-D
point mass among spheres, a torque-driven two-link arm; loaded from the file, since examples is
not a package) and a double integrator whose obstacles are given per run."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

from workbench.problem.models import double_integrator
from workbench.problem.obstacles import Circle

USER_MODELS = Path(__file__).resolve().parents[3] / "examples" / "user_models.py"


@pytest.fixture(scope="session")
def um():
    spec = importlib.util.spec_from_file_location("user_models", USER_MODELS)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="session")
def arm(um):
    return um.two_link_arm()


@pytest.fixture(scope="session")
def point_mass(um):
    return um.point_mass_3d()


@pytest.fixture(scope="session")
def di():
    # run-time obstacles: the scene of each run is given to closed_loop
    return double_integrator(obstacles=(Circle((8.0, 8.0), 0.5),), u_limit=5.0,
                             scene_capacity=4)

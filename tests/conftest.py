"""Shared fixtures: the tracking scene's plain and barrier-embedded problems, seeded generators."""

from __future__ import annotations

import numpy as np
import pytest

from workbench.barrier import BarrierOptions, embed_barrier
from workbench.costs import quadratic_tracking
from workbench.models import double_integrator
from workbench.problem import Problem
from workbench.scenes import TrackingScene

TRACK_Q, TRACK_R, TRACK_S = [10, 10, 1, 1], [1e-3, 1e-3], [1000, 1000, 100, 100]


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


@pytest.fixture(scope="session")
def scene() -> TrackingScene:
    return TrackingScene()


def bas_tracking_problem(scene: TrackingScene, q_beta=1e-2, options: BarrierOptions | None = None):
    """BaS-iLQG problem of SPEC 6.1 on the tracking scene, with its parameter array."""
    model = embed_barrier(double_integrator(obstacles=(scene.obstacle,), u_limit=scene.u_limit),
                          options)
    cost = quadratic_tracking(model, Q=TRACK_Q, R=TRACK_R, S=TRACK_S, q_beta=q_beta, s_beta=0.05)
    problem = Problem.build(model, cost)
    x_ref = scene.reference()
    x_ref[-1] = scene.target
    beta_f = model.lift(scene.target)[model.n_physical:]
    return problem, cost.params(scene.horizon, x_ref=x_ref, beta_ref=beta_f)


@pytest.fixture(scope="session")
def bas_tracking(scene):
    return bas_tracking_problem(scene)


def central_jacobian(fun, x, eps=1e-6):
    """Central finite-difference Jacobian of a NumPy vector function."""
    x = np.asarray(x, float)
    cols = []
    for i in range(x.size):
        e = np.zeros_like(x)
        e[i] = eps
        cols.append((np.ravel(fun(x + e)) - np.ravel(fun(x - e))) / (2 * eps))
    return np.stack(cols, axis=1)

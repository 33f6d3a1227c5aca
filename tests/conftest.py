"""Shared fixtures: the tracking scene's plain and barrier-embedded problems, seeded generators."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from workbench.problem.barrier import BarrierOptions, embed_barrier
from workbench.problem.costs import quadratic_tracking
from workbench.problem.models import double_integrator
from workbench.problem.obstacles import Circle
from workbench.problem.problem import Problem
from workbench.scenarios.scenes import TrackingScene

TRACK_Q, TRACK_R, TRACK_S = [10, 10, 1, 1], [1e-3, 1e-3], [1000, 1000, 100, 100]


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


@pytest.fixture(scope="session")
def scene() -> TrackingScene:
    return TrackingScene()


def bas_tracking_problem(scene: TrackingScene, q_beta=1e-2, options: BarrierOptions | None = None):
    """BaS-iLQG problem of assumptions §6.1 on the tracking scene, with its parameter array."""
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


# the tracking study at a tiny size, as `--set` overrides of the quick profile
TINY_TRACKING_SETS = ("n_rollouts=6", "n_seeds=2", "sweep_rollouts=4", "sweep_seeds=1",
                      "sweep_q_beta=[1e-2, 1.0]", "sweep_pole=[5.0]", "sweep_q_scale=[1.0]",
                      "sweep_noise_std=[10.0]", "radii=[0.3, 0.5, 1.0]")


@pytest.fixture(scope="session")
def cli_reports(tmp_path_factory):
    """A reports directory written through the command line: the tracking demo (quick) and the
    tracking study (tiny), both in this process. Returns (root, [stdout of each run])."""
    import contextlib
    import io

    from workbench.cli import main

    root = tmp_path_factory.mktemp("reports")
    outputs = []
    for argv in (["run", "tracking-demo", "--workers", "0", "--out", str(root / "tracking_demo")],
                 ["run", "tracking", "--workers", "0", "--out", str(root / "tracking_comparison"),
                  *[a for s in TINY_TRACKING_SETS for a in ("--set", s)]]):
        buf = io.StringIO()
        with contextlib.redirect_stdout(buf):
            assert main(argv) == 0
        outputs.append(buf.getvalue())
    return root, outputs


def swap_library(victim, donor) -> None:
    """Put donor's library bytes in victim's place and update victim's manifest hash."""
    import hashlib
    import json
    import os

    data = donor.path.read_bytes()
    tmp = victim.path.with_suffix(".swap")
    tmp.write_bytes(data)
    os.replace(tmp, victim.path)  # never rewrite a mapped library in place
    manifest = victim.path.parent / "manifest.json"
    meta = json.loads(manifest.read_text())
    meta["sha256"] = hashlib.sha256(data).hexdigest()
    manifest.write_text(json.dumps(meta))


# --- the two user models of examples/user_models.py (a 3-D point mass among spheres, a
# torque-driven two-link arm; loaded from the file, since examples is not a package) and a
# double integrator whose obstacles are given per run: the gatekeeper's tests
USER_MODELS = Path(__file__).resolve().parents[1] / "examples" / "user_models.py"


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


def rel_err(a, b) -> float:
    """Largest per-element error |a - b| / max(|a|, |b|, 1) of two arrays of one shape."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    assert a.shape == b.shape
    return float(np.max(np.abs(a - b) / np.maximum(np.maximum(np.abs(a), np.abs(b)), 1.0)))

"""The braking backup derived from the model alone (model_braking_backup): on the Euler double
integrator it is the closed form u = clip(-v / (3 dt)); from random moving states it brings the
double integrator, the 3-D point mass and the torque-driven two-link arm of
``examples/user_models.py`` to rest (checked by rollout), where the position-velocity braking
law leaves the arm moving; bad options name the field."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from conftest import rel_err

from workbench.codegen.fastcall import FastFunction
from workbench.problem.models import Model
from workbench.sampling.methods.gatekeeper import (
    DEFAULT_REST_TOL,
    braking_backup,
    model_braking_backup,
)

RTOL = 1e-10  # per element |a - b| <= RTOL max(|a|, |b|, 1)


def rollout_rates(model: Model, backup, X0, steps: int) -> np.ndarray:
    """(M, steps + 1): the rate max_i |x_k+1 - x_k| / dt of each backup step from each row of
    X0, the model stepped with NumPy inputs (the backup clipped to the box)."""
    f = FastFunction(ca.Function("f", [model.x, model.u], [model.x_next]))
    out = np.zeros((len(X0), steps + 1))
    for i, x in enumerate(np.asarray(X0, float)):
        for k in range(steps + 1):
            xn = f(x, np.clip(backup(x), model.u_min, model.u_max))[0]
            out[i, k] = np.max(np.abs(xn - x)) / model.dt
            x = xn
    return out


def test_model_braking_backup_brings_each_model_to_rest(di, point_mass, arm):
    """From random moving states (the double integrator and the point mass up to 4 and 3 m/s
    per axis, the arm up to 1.5 rad/s per joint anywhere in its range) the derived backup's
    rollout ends at rest within 60 steps (rate <= the gatekeeper's default rest tolerance) and
    keeps slowing (<= 1e-3 after 100 steps). The arm from 3 rad/s needs up to 74 steps at its
    torque limits: nearly at rest after 100. The position-velocity braking law leaves the arm
    moving."""
    rng = np.random.default_rng(3)
    M = 60
    cases = [
        (di, np.column_stack([rng.uniform(0, 10, (M, 2)), rng.uniform(-4, 4, (M, 2))])),
        (point_mass, np.column_stack([rng.uniform(0, 5, (M, 3)), rng.uniform(-3, 3, (M, 3))])),
        (arm, np.column_stack([rng.uniform(-np.pi, np.pi, M), rng.uniform(-2.5, 2.5, M),
                               rng.uniform(-1.5, 1.5, (M, 2))])),
    ]
    for model, X0 in cases:
        rates = rollout_rates(model, model_braking_backup(model), X0, 100)
        assert np.min(rates[:, 0]) > 5 * DEFAULT_REST_TOL, model.name  # every start moves
        assert np.max(rates[:, 60]) <= DEFAULT_REST_TOL, model.name
        assert np.max(rates[:, 100]) <= 1e-3, model.name
    fast = np.column_stack([rng.uniform(-np.pi, np.pi, M), rng.uniform(-2.5, 2.5, M),
                            rng.uniform(-3.0, 3.0, (M, 2))])
    assert np.max(rollout_rates(arm, model_braking_backup(arm), fast, 100)[:, 100]) <= 0.01
    chatter = rollout_rates(arm, braking_backup(arm), cases[2][1][:10], 100)
    assert np.min(chatter[:, 100]) > 1.0  # the torques chatter at their limits


def test_derived_law_on_the_double_integrator_removes_a_third_of_the_speed(di):
    """u = clip(-v / (3 dt)) per axis: the least-squares optimum, which the Gauss-Newton steps
    reach (the damping's error shrinks by its size each step)."""
    law = model_braking_backup(di)
    for v in ([0.3, -0.6], [0.01, 0.0], [4.0, -0.2], [0.09, 0.2]):
        want = np.clip(-np.asarray(v) / (3.0 * di.dt), -5.0, 5.0)
        assert rel_err(law([1.0, 2.0, *v]), want) <= RTOL
    assert np.all(law([1.0, 2.0, 0.0, 0.0]) == 0.0)  # at rest: no control
    scaled = model_braking_backup(di, scale=(1.0, 1.0, np.inf, np.inf))  # positions only
    np.testing.assert_allclose(scaled([0.0, 0.0, 0.05, 0.0]), [-2.5, 0.0])  # deadbeat
    np.testing.assert_allclose(scaled([0.0, 0.0, 1.0, 0.0]), [-5.0, 0.0])  # clipped


def test_bad_derived_backups_name_the_field(arm):
    for kw, field in (({"lookahead": 1}, "lookahead"), ({"lookahead": 2.0}, "lookahead"),
                      ({"iterations": 0}, "iterations"), ({"scale": (1.0,) * 3}, "scale"),
                      ({"scale": (1.0, -1.0, 1.0, 1.0)}, "scale")):
        with pytest.raises(ValueError, match=rf"^{field} = "):
            model_braking_backup(arm, **kw)

"""Discrete (high-order) CBF (workbench.problem.dcbf): the orders found from the discrete
models, the constraint against hand-written closed forms per element, its u-Jacobian against
central finite differences, gamma as a run-time input, and bad input naming the field."""

from __future__ import annotations

import re

import casadi as ca
import numpy as np
import pytest

from workbench.problem.barrier import embed_barrier
from workbench.problem.dcbf import MAX_ORDER, check_gamma, discrete_cbf
from workbench.problem.models import Model, double_integrator, single_integrator
from workbench.problem.obstacles import Circle

OBST = (Circle((2.0, 2.0), 0.8), Circle((3.5, 1.0), 0.5), Circle((1.0, 3.2), 0.6))
DT = 0.02


def rel_err(a, b, scale=None) -> float:
    """max |a - b| / max(|a|, |b|, scale, 1) per element. ``scale``: the size of the terms a
    closed form cancels (c is a small difference of margins of up to ~1e16 for inert slots),
    which bounds its rounding."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    assert a.shape == b.shape
    ref = np.maximum(np.maximum(np.abs(a), np.abs(b)), 1.0)
    if scale is not None:
        ref = np.maximum(ref, scale)
    return float(np.max(np.abs(a - b) / ref))


def h_closed(p, scene) -> np.ndarray:
    """Squared-distance margins |p - c_i|^2 - r_i^2 of the scene's circles."""
    C = np.asarray(scene, float).reshape(-1, 3)
    return (p[0] - C[:, 0]) ** 2 + (p[1] - C[:, 1]) ** 2 - C[:, 2] ** 2


def c_double(x, u, gamma, scene, dt=DT, terms=False) -> np.ndarray:
    """Order 2, Euler: h(p + 2 dt v + dt^2 u) - 2 (1 - g) h(p + dt v) + (1 - g)^2 h(p)
    (``terms``: the sum of the three terms' magnitudes instead)."""
    p, v, k = x[:2], x[2:4], 1.0 - gamma
    t = (h_closed(p + 2 * dt * v + dt**2 * u, scene), -2 * k * h_closed(p + dt * v, scene),
         k**2 * h_closed(p, scene))
    return sum(np.abs(a) for a in t) if terms else t[0] + t[1] + t[2]


def c_single(x, u, gamma, scene, dt=DT) -> np.ndarray:
    """Order 1: h(p + dt u) - (1 - g) h(p)."""
    return h_closed(x + dt * u, scene) - (1.0 - gamma) * h_closed(x, scene)


def random_cases(rng, n_state, M=200):
    X = np.column_stack([rng.uniform(-1.0, 5.0, (M, 2)), rng.uniform(-5.0, 5.0, (M, n_state - 2))])
    return X, rng.uniform(-5.0, 5.0, (M, 2)), rng.uniform(1e-3, 1.0, M)


def test_orders_follow_the_discrete_relative_degree():
    assert discrete_cbf(double_integrator(obstacles=OBST)).orders == (2, 2, 2)
    assert discrete_cbf(single_integrator(obstacles=OBST)).orders == (1, 1, 1)
    # zero-order hold: u_k enters p_{k+1} (dt^2/2 u), so one step suffices
    assert discrete_cbf(double_integrator(obstacles=OBST, integrator="zoh")).orders == (1, 1, 1)
    assert discrete_cbf(embed_barrier(double_integrator(obstacles=OBST))).orders == (2, 2, 2)


@pytest.mark.parametrize("moved", [False, True])
def test_double_integrator_constraint_equals_closed_form(moved):
    model = double_integrator(obstacles=OBST, scene_capacity=4)
    cbf = discrete_cbf(model)
    rng = np.random.default_rng(3)
    scene = (model.scene_vector([Circle((1.5, 0.5), 0.9), Circle((3.0, 3.0), 0.3),
                                 Circle((0.0, 2.0), 0.4), Circle((4.0, 1.0), 0.7)])
             if moved else model.scene_value)
    X, U, G = random_cases(rng, 4)
    got = np.array([cbf.values(x, u, g, scene) for x, u, g in zip(X, U, G, strict=True)])
    want = np.array([c_double(x, u, g, scene) for x, u, g in zip(X, U, G, strict=True)])
    size = np.array([c_double(x, u, g, scene, terms=True) for x, u, g in zip(X, U, G,
                                                                             strict=True)])
    # per element, relative to the terms c cancels (measured 1.3e-15); the inert slot (slot 4
    # when not moved) has terms of ~2e16 and c ~ gamma^2 2e16 > 0
    assert rel_err(got, want, size) <= 1e-12
    if not moved:
        assert np.all(got[:, 3] > 0)
    assert np.any(got[:, :3] < 0) and np.any(got[:, :3] > 0)


def test_single_integrator_constraint_equals_closed_form():
    model = single_integrator(obstacles=OBST)
    cbf = discrete_cbf(model)
    X, U, G = random_cases(np.random.default_rng(4), 2)
    got = np.array([cbf.values(x, u, g) for x, u, g in zip(X, U, G, strict=True)])
    want = np.array([c_single(x, u, g, model.scene_value) for x, u, g in zip(X, U, G,
                                                                              strict=True)])
    assert rel_err(got, want) <= 1e-12


def test_barrier_embedded_model_uses_the_physical_margins():
    """Same constraint as the plain model's at the lifted state; a physical state is lifted."""
    plain = double_integrator(obstacles=OBST)
    emb = embed_barrier(plain)
    cp, ce = discrete_cbf(plain), discrete_cbf(emb)
    X, U, G = random_cases(np.random.default_rng(5), 4, 50)
    X = X[np.array([np.min(plain.margins(x)) > 0.05 for x in X])]
    for x, u, g in zip(X, U, G, strict=False):
        a = cp.values(x, u, g)
        assert rel_err(ce.values(emb.lift(x), u, g), a) <= 1e-12
        assert rel_err(ce.values(x, u, g), a) <= 1e-12


@pytest.mark.parametrize("make", [double_integrator, single_integrator])
def test_u_jacobian_equals_central_differences(make):
    model = make(obstacles=OBST)
    cbf = discrete_cbf(model)
    X, U, G = random_cases(np.random.default_rng(6), model.nx, 60)
    step = 1e-3
    worst = 0.0
    for x, u, g in zip(X, U, G, strict=True):
        J = cbf.jacobian_values(x, u, g)
        assert J.shape == (3, 2)
        fd = np.column_stack([(cbf.values(x, u + step * e, g) - cbf.values(x, u - step * e, g))
                              / (2 * step) for e in np.eye(2)])
        # c is quadratic in u here: central differences are exact but for rounding (~1e-11)
        worst = max(worst, float(np.max(np.abs(J - fd))) / float(np.max(np.abs(J))))
    assert worst <= 1e-6, worst


def test_gamma_is_a_run_time_input():
    model = double_integrator(obstacles=OBST)
    cbf = discrete_cbf(model)
    assert cbf.c.name_in() == ["x", "u", "gamma", "scene"]
    assert cbf.jacobian.size_out(0) == (3, 2)
    x, u = np.array([1.0, 1.0, 1.0, 0.5]), np.array([1.0, 2.0])
    a, b = cbf.values(x, u, 0.1), cbf.values(x, u, 0.9)
    assert not np.allclose(a, b)
    assert rel_err(b, c_double(x, u, 0.9, model.scene_value)) <= 1e-12
    # psi_{r-1}(x) of the Euler double integrator: h(p + dt v) - (1 - g) h(p)
    psi = np.asarray(cbf.psi(x, 0.1, model.scene_value)).ravel()
    want = h_closed(x[:2] + DT * x[2:], model.scene_value) - 0.9 * h_closed(x[:2],
                                                                          model.scene_value)
    assert rel_err(psi, want) <= 1e-12


@pytest.mark.parametrize("gamma", [0.0, -0.1, 1.5, float("nan"), float("inf"), True, "0.1"])
def test_bad_gamma_names_the_field(gamma):
    cbf = discrete_cbf(double_integrator(obstacles=OBST))
    with pytest.raises(ValueError, match=re.escape("gamma = ")):
        cbf.values(np.zeros(4) + 0.1, np.zeros(2), gamma)
    with pytest.raises(ValueError, match=re.escape("Cfg.gamma = ")):
        check_gamma("Cfg.gamma", gamma)


def test_bad_models_name_the_field():
    with pytest.raises(ValueError, match=r"^model = .*no safety margins"):
        discrete_cbf(double_integrator())
    # a margin on a state the control never reaches
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    m = Model.from_expressions("lazy", x, u, ca.vertcat(x[0] + u, x[1]), dt=0.1, u_min=[-1],
                               u_max=[1], h=ca.vertcat(x[0], x[1]))
    with pytest.raises(ValueError, match=re.escape("model.h[1] = ") + f".*{MAX_ORDER} steps"):
        discrete_cbf(m)
    with pytest.raises(ValueError, match=r"^model = "):
        discrete_cbf("double_integrator")
    cbf = discrete_cbf(double_integrator(obstacles=OBST))
    with pytest.raises(ValueError, match=r"^u = "):
        cbf.values(np.zeros(4), np.zeros(3), 0.5)
    with pytest.raises(ValueError, match=r"^x = "):
        cbf.values(np.zeros(3), np.zeros(2), 0.5)

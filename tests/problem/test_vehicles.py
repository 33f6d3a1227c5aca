"""The vehicle models against independent NumPy closed forms (one Euler step), their limits,
names, position coordinates and margins; bad options name the field."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from workbench.problem.obstacles import Circle
from workbench.problem.vehicles import kinematic_bicycle, planar_quadrotor, unicycle

DT = 0.02
OBST = (Circle((1.0, 0.5), 0.4), Circle((-0.5, 1.2), 0.3))
N_POINTS = 64


def unicycle_np(x, u, dt=DT, drop=()):
    px, py, th = x
    v, w = u
    c, s = (np.sin(th), np.cos(th)) if "swap_trig" in drop else (np.cos(th), np.sin(th))
    return np.array([px + dt * v * c, py + dt * v * s, th + dt * w])


def bicycle_np(x, u, dt=DT, L=0.5, drop=()):
    px, py, th, v = x
    a, d = u
    turn = v * (d if "tan" in drop else np.tan(d)) / L
    return np.array([px + dt * v * np.cos(th), py + dt * v * np.sin(th), th + dt * turn,
                     v + dt * a])


# the 2D quadrotor of safe-control-gym, constants typed from cf2x.urdf / base_aviary.py
M, ARM, IYY, G = 0.027, 0.0397, 1.4e-5, 9.8


def quadrotor_np(x, u, dt=DT, drop=(), offset=0.0):
    X, Xd, Z, Zd, th, thd = x
    T1, T2 = u[0] + offset, u[1] + offset
    torque = ARM * (T2 - T1) / IYY / (1.0 if "sqrt2" in drop else np.sqrt(2.0))
    return np.array([X + dt * Xd, Xd + dt * np.sin(th) * (T1 + T2) / M, Z + dt * Zd,
                     Zd + dt * (np.cos(th) * (T1 + T2) / M - G), th + dt * thd,
                     thd + dt * torque])


def _step(model):
    f = ca.Function("f", [model.x, model.u], [model.x_next])
    return lambda x, u: np.asarray(f(x, u)).ravel()


def _points(model, rng, n=N_POINTS):
    X = rng.normal(0.0, 2.0, (n, model.nx))
    U = rng.uniform(model.u_min, model.u_max, (n, model.nu))
    return X, U


def _close(a, b, tol=1e-12) -> bool:
    return bool(np.all(np.abs(a - b) <= tol * np.maximum(np.maximum(np.abs(a), np.abs(b)), 1)))


CASES = {
    "unicycle": (lambda: unicycle(obstacles=OBST), unicycle_np),
    "bicycle": (lambda: kinematic_bicycle(obstacles=OBST), bicycle_np),
    "quadrotor": (lambda: planar_quadrotor(obstacles=OBST), quadrotor_np),
}
MUTATIONS = {"unicycle": "swap_trig", "bicycle": "tan", "quadrotor": "sqrt2"}


@pytest.mark.parametrize("name", sorted(CASES))
def test_one_step_matches_the_numpy_closed_form_and_a_broken_one_fails(name, rng):
    make, closed = CASES[name]
    model = make()
    f = _step(model)
    X, U = _points(model, rng)
    ref = np.array([closed(x, u) for x, u in zip(X, U, strict=True)])
    got = np.array([f(x, u) for x, u in zip(X, U, strict=True)])
    err = np.abs(got - ref) / np.maximum(np.maximum(np.abs(got), np.abs(ref)), 1)
    assert err.max() <= 1e-12  # measured: ~1e-16 (rounding)
    broken = np.array([closed(x, u, drop=(MUTATIONS[name],))
                       for x, u in zip(X, U, strict=True)])
    assert not _close(got, broken)
    assert np.abs(got - broken).max() > 1e-4  # by orders of magnitude above the tolerance


def test_quadrotor_hover_offset_inputs_and_hover():
    plain, shifted = planar_quadrotor(), planar_quadrotor(hover_offset=True)
    hover = M * G / 2
    np.testing.assert_allclose(shifted.u_min, plain.u_min - hover, rtol=0, atol=1e-15)
    np.testing.assert_allclose(shifted.u_max, plain.u_max - hover, rtol=0, atol=1e-15)
    assert shifted.control_names == ("dT1", "dT2") and plain.control_names == ("T1", "T2")
    rng = np.random.default_rng(3)
    f, g = _step(plain), _step(shifted)
    for _ in range(N_POINTS):
        x, du = rng.normal(0, 1, 6), rng.uniform(shifted.u_min, shifted.u_max)
        assert _close(g(x, du), quadrotor_np(x, du, offset=hover))
        assert _close(g(x, du), f(x, du + hover), tol=1e-12)
    x = np.array([0.3, 0.0, 1.0, 0.0, 0.0, 0.0])  # level, at rest: u = 0 hovers exactly
    np.testing.assert_allclose(g(x, np.zeros(2)), x, rtol=0, atol=1e-15)


def test_quadrotor_constants_and_state_limits_are_safe_control_gyms():
    m = planar_quadrotor(obstacles=OBST)
    # cf2x.urdf: kf 3.16e-10, pwm2rpm 0.2685 pwm + 4070.3, pwm in [20000, 65535]; 2 motors/input
    lo = 3.16e-10 * 2 * (0.2685 * 20000 + 4070.3) ** 2
    hi = 3.16e-10 * 2 * (0.2685 * 65535 + 4070.3) ** 2
    np.testing.assert_allclose(m.u_min, [lo, lo], rtol=1e-15)
    np.testing.assert_allclose(m.u_max, [hi, hi], rtol=1e-15)
    assert 0.0563 < lo < 0.0564 and 0.2966 < hi < 0.2967 and lo < M * G / 2 < hi
    assert m.state_names == ("x", "x_dot", "z", "z_dot", "theta", "theta_dot")
    assert m.position == (0, 2) and m.nh == len(OBST) + 6
    box = np.array([[-2, 2], [-30, 30], [-0.05, 2], [-30, 30],
                    [-np.deg2rad(85), np.deg2rad(85)], [-np.deg2rad(500), np.deg2rad(500)]])
    rng = np.random.default_rng(5)
    for _ in range(N_POINTS):
        x = rng.uniform(1.2 * box[:, 0], 1.2 * box[:, 1])
        h = m.margins(x)
        circles = [(x[0] - c.center[0]) ** 2 + (x[2] - c.center[1]) ** 2 - c.radius ** 2
                   for c in OBST]
        limits = (box[:, 1] - x) * (x - box[:, 0])
        assert _close(h, np.array(circles + list(limits)))
        inside = np.all((x >= box[:, 0]) & (x <= box[:, 1]))
        assert inside == bool(np.all(limits >= 0))
    assert planar_quadrotor(obstacles=OBST, state_limits=False).nh == len(OBST)


def test_ground_robots_limits_names_position_and_margins():
    u = unicycle(obstacles=OBST)
    assert u.state_names == ("px", "py", "theta") and u.control_names == ("v", "omega")
    np.testing.assert_array_equal(u.u_min, [-0.5, -2.0])
    np.testing.assert_array_equal(u.u_max, [2.0, 2.0])
    assert u.position == (0, 1) and u.nh == len(OBST) and u.n_scene == 3 * len(OBST)
    b = kinematic_bicycle(obstacles=OBST, a_limit=2.0, steer_limit=0.4, scene_capacity=5)
    assert b.state_names == ("px", "py", "theta", "v") and b.control_names == ("a", "delta")
    np.testing.assert_array_equal(b.u_min, [-2.0, -0.4])
    np.testing.assert_array_equal(b.u_max, [2.0, 0.4])
    assert b.position == (0, 1) and b.nh == 5
    x = np.array([1.0, 0.0, 0.3, 1.0])
    np.testing.assert_allclose(b.margins(x)[:2], [0.25 - 0.16, 1.5 ** 2 + 1.2 ** 2 - 0.09])
    assert b.margins(x)[2:].min() > 1e15  # inert slots
    baked = unicycle(obstacles=OBST, runtime_obstacles=False)
    assert baked.n_scene == 0
    np.testing.assert_allclose(baked.margins([1.0, 0.0, 0.0]), u.margins([1.0, 0.0, 0.0]))
    assert unicycle(v_limit=1.5).u_min[0] == -1.5


@pytest.mark.parametrize(("make", "field"), [
    (lambda: unicycle(v_limit=(0.5, 2.0)), "v_limit"),
    (lambda: unicycle(v_limit=(-1.0, 0.0)), "v_limit"),
    (lambda: unicycle(omega_limit=0.0), "omega_limit"),
    (lambda: unicycle(dt=0.0), "dt"),
    (lambda: unicycle(h_form="cube"), "h_form"),
    (lambda: kinematic_bicycle(wheelbase=-1.0), "wheelbase"),
    (lambda: kinematic_bicycle(steer_limit=1.6), "steer_limit"),
    (lambda: kinematic_bicycle(a_limit=np.inf), "a_limit"),
    (lambda: planar_quadrotor(state_limits=1), "state_limits"),
    (lambda: planar_quadrotor(hover_offset="yes"), "hover_offset"),
    (lambda: planar_quadrotor(obstacles=OBST, scene_capacity=1), "scene_capacity"),
])
def test_bad_options_name_the_field(make, field):
    with pytest.raises(ValueError, match=rf"^{field} = "):
        make()

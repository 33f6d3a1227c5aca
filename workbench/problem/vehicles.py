"""Vehicle models as CasADi SX expressions: a kinematic unicycle, a kinematic bicycle and the
planar quadrotor of safe-control-gym, all with explicit Euler steps and circular obstacles
around their position (:func:`~workbench.problem.models.circle_scene`, run-time scene as for
the built-in integrators).

Position coordinates (``Model.position``): (0, 1) for the ground robots; (0, 2), i.e. (x, z),
for the quadrotor, whose map lives in the vertical x-z plane.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from workbench.problem.models import Model, circle_scene
from workbench.problem.obstacles import Circle, HForm
from workbench.problem.scene_layout import SceneLayout
from workbench.validation import as_array, fail, flag, real

# safe-control-gym, utiasDSL/safe-control-gym at commit e39a569 (2025-11-06):
# safe_control_gym/envs/gym_pybullet_drones/assets/cf2x.urdf (Crazyflie 2.x) and
# base_aviary.py / quadrotor.py (Yuan, Hall, Zhou, Brunke, Greeff, Panerati, Schoellig,
# "safe-control-gym: a Unified Benchmark Suite for Safe Learning-based Control and
# Reinforcement Learning in Robotics", IEEE RA-L 2022, arXiv:2109.06325).
QUAD_MASS = 0.027  # kg, cf2x.urdf <mass value="0.027"/>
QUAD_ARM = 0.0397  # m, cf2x.urdf arm="0.0397" (self.L)
QUAD_IYY = 1.4e-5  # kg m^2, cf2x.urdf iyy="1.4e-5"
QUAD_GRAVITY = 9.8  # m/s^2, base_aviary.py GRAVITY_ACC
_KF = 3.16e-10  # cf2x.urdf kf
_PWM2RPM_SCALE, _PWM2RPM_CONST = 0.2685, 4070.3  # cf2x.urdf pwm2rpm_scale, pwm2rpm_const
_PWM_MIN, _PWM_MAX = 20000.0, 65535.0  # cf2x.urdf pwm_min, pwm_max
_N_MOT = 2.0  # quadrotor.py _set_action_space: n_mot = 4 / action_dim, two inputs in 2D
# quadrotor.py _set_action_space: a_low/high = KF n_mot (PWM2RPM_SCALE pwm + PWM2RPM_CONST)^2
QUAD_THRUST_MIN = _KF * _N_MOT * (_PWM2RPM_SCALE * _PWM_MIN + _PWM2RPM_CONST) ** 2  # ~0.0563 N
QUAD_THRUST_MAX = _KF * _N_MOT * (_PWM2RPM_SCALE * _PWM_MAX + _PWM2RPM_CONST) ** 2  # ~0.2967 N
QUAD_HOVER_THRUST = QUAD_MASS * QUAD_GRAVITY / 2  # per input, 0.1323 N
# quadrotor.py _set_observation_space (the benchmark's default state constraint,
# constraints.py DefaultConstraint on the state space): x, x_dot, z, z_dot, theta, theta_dot;
# z from GROUND_PLANE_Z = -0.05 (base_aviary.py) to z_threshold = 2
QUAD_STATE_LIMITS: tuple[tuple[float, float], ...] = (
    (-2.0, 2.0), (-30.0, 30.0), (-0.05, 2.0), (-30.0, 30.0),
    (-np.deg2rad(85.0), np.deg2rad(85.0)), (-np.deg2rad(500.0), np.deg2rad(500.0)))
QUAD_STATE_NAMES = ("x", "x_dot", "z", "z_dot", "theta", "theta_dot")


def box_margins(s: ca.SX, limits) -> ca.SX:
    """Margins (hi - s_i)(s_i - lo) >= 0 of a state box, one per entry of ``s``: lim^2 - s^2
    for a symmetric box, in the square units of the state (like the squared circle margins)."""
    return ca.vertcat(*[(hi - s[i]) * (s[i] - lo) for i, (lo, hi) in enumerate(limits)])


def _limit(name: str, value) -> tuple[float, float]:
    """(lo, hi) with lo <= 0 < hi (stopping is always allowed), from a pair or a scalar > 0."""
    if np.ndim(value) == 0:
        v = real(name, value, 0.0, strict=True)
        return -v, v
    lo, hi = as_array(name, value, (2,))
    if not lo <= 0.0 < hi:
        raise fail(name, value, "need (low, high) with low <= 0 < high")
    return float(lo), float(hi)


def _scene(p, obstacles, h_form, inflation, scene_capacity, runtime_obstacles,
           scene_layout=None) -> dict:
    return circle_scene(p, tuple(obstacles), h_form, inflation, scene_capacity,
                        runtime_obstacles, scene_layout)


def unicycle(*, dt: float = 0.02, obstacles: tuple[Circle, ...] = (),
             v_limit: float | tuple[float, float] = (-0.5, 2.0), omega_limit: float = 2.0,
             h_form: HForm = "squared", inflation: float = 0.0,
             scene_capacity: int | None = None, runtime_obstacles: bool = True,
             scene_layout: SceneLayout | None = None) -> Model:
    """Kinematic unicycle (Dubins-type car with reverse) x = [px, py, theta], u = [v, omega]:
    px+ = px + dt v cos(theta), py+ = py + dt v sin(theta), theta+ = theta + dt omega.

    ``v_limit``: (low, high) with low <= 0 < high, or a scalar v for (-v, v); ``omega_limit``
    > 0 bounds |omega|. Obstacles as in :func:`~workbench.problem.models.double_integrator`."""
    real("dt", dt, 0.0, strict=True)
    vlo, vhi = _limit("v_limit", v_limit)
    w = real("omega_limit", omega_limit, 0.0, strict=True)
    x, u = ca.SX.sym("x", 3), ca.SX.sym("u", 2)
    th, v = x[2], u[0]
    x_next = ca.vertcat(x[0] + dt * v * ca.cos(th), x[1] + dt * v * ca.sin(th), th + dt * u[1])
    return Model.from_expressions(
        "unicycle", x, u, x_next, dt=dt, u_min=[vlo, -w], u_max=[vhi, w],
        state_names=("px", "py", "theta"), control_names=("v", "omega"), position=(0, 1),
        state_units=("m", "m", "rad"),
        **_scene(x[:2], obstacles, h_form, inflation, scene_capacity, runtime_obstacles,
                 scene_layout))


def kinematic_bicycle(*, dt: float = 0.02, wheelbase: float = 0.5, a_limit: float = 3.0,
                      steer_limit: float = 0.5, obstacles: tuple[Circle, ...] = (),
                      h_form: HForm = "squared", inflation: float = 0.0,
                      scene_capacity: int | None = None,
                      runtime_obstacles: bool = True,
                      scene_layout: SceneLayout | None = None) -> Model:
    """Kinematic bicycle about the rear axle, x = [px, py, theta, v], u = [a, delta]:
    px' = v cos(theta), py' = v sin(theta), theta' = v tan(delta) / L, v' = a (Euler, L the
    ``wheelbase``). |a| <= ``a_limit``, |delta| <= ``steer_limit`` < pi/2.

    Its dynamics are not affine in delta (tan): filters that need control-affine dynamics (the
    ECBF filter) cannot take it as it is."""
    real("dt", dt, 0.0, strict=True)
    L = real("wheelbase", wheelbase, 0.0, strict=True)
    a = real("a_limit", a_limit, 0.0, strict=True)
    d = real("steer_limit", steer_limit, 0.0, strict=True)
    if not d < np.pi / 2:
        raise fail("steer_limit", steer_limit, "must be in (0, pi/2) rad (tan(delta) finite)")
    x, u = ca.SX.sym("x", 4), ca.SX.sym("u", 2)
    th, v = x[2], x[3]
    x_next = ca.vertcat(x[0] + dt * v * ca.cos(th), x[1] + dt * v * ca.sin(th),
                        th + dt * v * ca.tan(u[1]) / L, v + dt * u[0])
    return Model.from_expressions(
        "kinematic_bicycle", x, u, x_next, dt=dt, u_min=[-a, -d], u_max=[a, d],
        state_names=("px", "py", "theta", "v"), control_names=("a", "delta"), position=(0, 1),
        state_units=("m", "m", "rad", "m/s"),
        **_scene(x[:2], obstacles, h_form, inflation, scene_capacity, runtime_obstacles,
                 scene_layout))


def planar_quadrotor(*, dt: float = 0.02, obstacles: tuple[Circle, ...] = (),
                     h_form: HForm = "squared", inflation: float = 0.0,
                     scene_capacity: int | None = None, runtime_obstacles: bool = True,
                     scene_layout: SceneLayout | None = None,
                     state_limits: bool = True, hover_offset: bool = False) -> Model:
    """The 2D quadrotor of safe-control-gym (Yuan et al. 2022, arXiv:2109.06325; quadrotor.py,
    QuadType.TWO_D symbolic model): x = [x, x_dot, z, z_dot, theta, theta_dot] (pitch theta),
    u = [T1, T2] (thrusts, N), Euler steps of

        x'' = sin(theta) (T1 + T2) / m,  z'' = cos(theta) (T1 + T2) / m - g,
        theta'' = l (T2 - T1) / (Iyy sqrt(2)),

    with the Crazyflie constants of its cf2x.urdf (m = 0.027 kg, l = 0.0397 m, Iyy = 1.4e-5
    kg m^2, g = 9.8 m/s^2) and its thrust box per input (:data:`QUAD_THRUST_MIN` ~0.0563 N to
    :data:`QUAD_THRUST_MAX` ~0.2967 N; hover 0.1323 N each). The obstacles are circles in the
    x-z plane (``position = (0, 2)``).

    ``state_limits`` (default True) adds the benchmark's state constraint (its default state
    space: |x| <= 2, -0.05 <= z <= 2, |x_dot|, |z_dot| <= 30, |theta| <= 85 deg, |theta_dot|
    <= 500 deg/s) as six more margins (hi - s)(s - lo) after the circles (:func:`box_margins`):
    leaving the box counts as unsafe for every controller, as a constraint violation does in
    safe-control-gym, and the barrier states see it. False: circles only.

    ``hover_offset`` (default False): True makes the inputs the thrusts minus the hover thrust,
    u_i = T_i - m g / 2 (the box shifted alike; control names dT1, dT2), so that u = 0 hovers,
    like safe-control-gym's normalised action space, which is centred on the hover thrust.
    Samplers that start from u = 0 and whose control cost pulls towards it (MPPI) need it: with
    absolute thrusts their first plans sit at the lower thrust bound and the quadrotor falls."""
    real("dt", dt, 0.0, strict=True)
    flag("state_limits", state_limits)
    flag("hover_offset", hover_offset)
    x, u = ca.SX.sym("x", 6), ca.SX.sym("u", 2)
    m, g, th = QUAD_MASS, QUAD_GRAVITY, x[4]
    off = QUAD_HOVER_THRUST if hover_offset else 0.0
    T1, T2 = u[0] + off, u[1] + off
    thrust = T1 + T2
    xdot = ca.vertcat(x[1], ca.sin(th) * thrust / m, x[3], ca.cos(th) * thrust / m - g, x[5],
                      QUAD_ARM * (T2 - T1) / QUAD_IYY / np.sqrt(2))
    kw = _scene(ca.vertcat(x[0], x[2]), obstacles, h_form, inflation, scene_capacity,
                runtime_obstacles, scene_layout)
    if state_limits:
        kw["h"] = ca.vertcat(kw["h"], box_margins(x, QUAD_STATE_LIMITS))
    return Model.from_expressions(
        "planar_quadrotor", x, u, x + dt * xdot, dt=dt,
        u_min=[QUAD_THRUST_MIN - off] * 2, u_max=[QUAD_THRUST_MAX - off] * 2,
        state_names=QUAD_STATE_NAMES, state_units=("m", "m/s", "m", "m/s", "rad", "rad/s"),
        control_names=("dT1", "dT2") if hover_offset else ("T1", "T2"), position=(0, 2), **kw)


__all__ = ["QUAD_ARM", "QUAD_GRAVITY", "QUAD_HOVER_THRUST", "QUAD_IYY", "QUAD_MASS",
           "QUAD_STATE_LIMITS", "QUAD_STATE_NAMES", "QUAD_THRUST_MAX", "QUAD_THRUST_MIN",
           "box_margins", "kinematic_bicycle", "planar_quadrotor", "unicycle"]

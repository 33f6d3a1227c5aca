"""Two models the workbench does not ship, written as a user would write their own.

- :func:`point_mass_3d`: a point mass in 3-D (px, py, pz, vx, vy, vz; accelerations as
  controls) among spheres, above a floor and below a ceiling: three position coordinates and
  constraints that are not circles.
- :func:`two_link_arm`: a torque-driven planar two-link arm (joint angles and rates) whose
  elbow and hand must keep clear of a disc in the workspace, with an elbow joint limit: no
  planar position at all, constraints written through forward kinematics.

Each has a start and a goal (:data:`POINT_MASS_START` ...); :func:`point_mass_system` and
:func:`arm_system` turn them into systems every registered method builds on by name (a study
config names them as ``system = "examples/user_models.py:arm_system"``).
``python examples/user_models.py`` prints their sizes, their margins at the start and the
settings derived for them.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

import workbench as wb

# --- a point mass in 3-D ----------------------------------------------------------------------

POINT_MASS_DT = 0.05
SPHERES = (((2.0, 0.0, 1.0), 0.6), ((3.4, 1.0, 1.2), 0.5))  # (centre, radius) in m
FLOOR, CEILING = 0.1, 2.5  # m
POINT_MASS_START = np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
POINT_MASS_GOAL = np.array([5.0, 0.6, 1.2, 0.0, 0.0, 0.0])


def point_mass_3d() -> wb.Model:
    """x = (px, py, pz, vx, vy, vz), u = accelerations within +-4 m/s^2, explicit Euler;
    h = (||p - c||^2 - r^2 per sphere, pz - floor, ceiling - pz)."""
    x = ca.SX.sym("x", 6)
    u = ca.SX.sym("u", 3)
    dt = POINT_MASS_DT
    x_next = ca.vertcat(x[:3] + dt * x[3:], x[3:] + dt * u)
    p = x[:3]
    h = [ca.sumsqr(p - ca.DM(c)) - r**2 for c, r in SPHERES] + [x[2] - FLOOR, CEILING - x[2]]
    return wb.Model.from_expressions(
        "point_mass_3d", x, u, x_next, dt=dt, u_min=[-4.0] * 3, u_max=[4.0] * 3, h=h,
        state_names=("px", "py", "pz", "vx", "vy", "vz"), control_names=("ax", "ay", "az"),
        position=(0, 1, 2), state_units=("m", "m", "m", "m/s", "m/s", "m/s"))


# --- a torque-driven two-link arm ---------------------------------------------------------------

ARM_DT = 0.02
LINKS = (0.6, 0.5)  # m
MASSES = (1.0, 0.8)  # kg, point masses at the elbow and the hand
DAMPING = 0.2  # N m s per rad
DISC = ((0.65, 0.65), 0.2)  # workspace obstacle: centre (m), radius (m)
ELBOW_LIMIT = 2.6  # rad, |q2| < ELBOW_LIMIT
ARM_START = np.array([0.0, 0.3, 0.0, 0.0])
ARM_GOAL = np.array([1.5, 0.3, 0.0, 0.0])


def arm_points(q):
    """Elbow and hand positions of joint angles ``q`` (forward kinematics; CasADi or NumPy)."""
    l1, l2 = LINKS
    cos, sin = (ca.cos, ca.sin) if isinstance(q, ca.SX | ca.MX) else (np.cos, np.sin)
    elbow = (l1 * cos(q[0]), l1 * sin(q[0]))
    hand = (elbow[0] + l2 * cos(q[0] + q[1]), elbow[1] + l2 * sin(q[0] + q[1]))
    return elbow, hand


def two_link_arm() -> wb.Model:
    """x = (q1, q2, dq1, dq2), u = joint torques within +-3 N m; point-mass two-link dynamics
    M(q) ddq + C(q, dq) dq + DAMPING dq = u in the horizontal plane (no gravity), semi-implicit
    Euler. h: the elbow's and the hand's squared distance to the disc minus its radius squared,
    and the elbow limit ELBOW_LIMIT^2 - q2^2."""
    x = ca.SX.sym("x", 4)
    u = ca.SX.sym("u", 2)
    q, dq = x[:2], x[2:]
    (l1, l2), (m1, m2) = LINKS, MASSES
    c2, s2 = ca.cos(q[1]), ca.sin(q[1])
    m11 = (m1 + m2) * l1**2 + m2 * l2**2 + 2 * m2 * l1 * l2 * c2
    m12 = m2 * l2**2 + m2 * l1 * l2 * c2
    m22 = m2 * l2**2
    hc = m2 * l1 * l2 * s2
    bias = ca.vertcat(-hc * (2 * dq[0] * dq[1] + dq[1] ** 2), hc * dq[0] ** 2)
    M = ca.vertcat(ca.horzcat(m11, m12), ca.horzcat(m12, m22))
    ddq = ca.solve(M, u - bias - DAMPING * dq)
    dq_next = dq + ARM_DT * ddq
    x_next = ca.vertcat(q + ARM_DT * dq_next, dq_next)
    (cx, cy), r = DISC
    h = [(px - cx) ** 2 + (py - cy) ** 2 - r**2 for px, py in arm_points(q)]
    h.append(ELBOW_LIMIT**2 - q[1] ** 2)
    return wb.Model.from_expressions(
        "two_link_arm", x, u, x_next, dt=ARM_DT, u_min=[-3.0, -3.0], u_max=[3.0, 3.0], h=h,
        state_names=("q1", "q2", "dq1", "dq2"), control_names=("tau1", "tau2"),
        state_units=("rad", "rad", "rad/s", "rad/s"))




# --- as systems: every registered method builds on them by name ----------------------------------

def point_mass_system() -> wb.System:
    """:func:`point_mass_3d` from its start to its goal, every setting derived from the model
    (``System.origins`` says how)."""
    return wb.system_from_model(point_mass_3d(), POINT_MASS_START, POINT_MASS_GOAL,
                                entry="examples/user_models.py:point_mass_system")


def arm_system() -> wb.System:
    """:func:`two_link_arm` from its start to its goal, every setting derived from the model."""
    return wb.system_from_model(two_link_arm(), ARM_START, ARM_GOAL,
                                entry="examples/user_models.py:arm_system")


if __name__ == "__main__":
    for make, start, system in ((point_mass_3d, POINT_MASS_START, point_mass_system),
                                (two_link_arm, ARM_START, arm_system)):
        m = make()
        print(f"{m.name}: {m.nx} states, {m.nu} controls, {m.nh} constraints; "
              f"margins at the start {np.round(m.margins(start), 3)}")
        s = system()
        print(f"  horizon {s.horizon}, sigma {s.sigma}, lambda {s.lam:.3g}, disturbed "
              f"{s.disturbed} (level x {s.level_scale:.3g}), goal radius {s.goal_radius:.3g}")

"""Discrete-time (high-order) control barrier functions of a model's safety margins.

Agrawal & Sreenath, "Discrete Control Barrier Functions for Safety-Critical Control of Discrete
Systems with Application to Bipedal Robot Navigation", RSS 2017 (the condition
h(x_{k+1}) >= (1 - gamma) h(x_k)); Xiong, Zhai, Wang, Zhang, Xu, "Discrete-Time Control Barrier
Function: High-Order Case and Adaptive Case", IEEE TCYB 2022, arXiv:2102.01415 (its high-order
form, used here with one rate gamma for every order).

For each margin h_i of the model (h_i >= 0 is safe), with the discrete dynamics x+ = f(x, u):

    psi_0(x) = h_i(x)
    psi_{j+1}(x) = psi_j(f(x, 0)) - (1 - gamma) psi_j(x)   while psi_j(f(x, u)) does not
                                                           depend on u (ca.depends_on)

The first j at which psi_j(f(x, u)) depends on u gives the order r_i = j + 1 (the discrete
relative degree: 2 for the Euler double integrator, whose position at x_{k+1} does not depend
on u_k; 1 for the single integrator), and the constraint on u is

    c_i(x, u) = psi_{r-1}(f(x, u)) - (1 - gamma) psi_{r-1}(x) >= 0.

For the Euler double integrator (x = [p, v], p+ = p + dt v, v+ = v + dt u) this is
c_i = h_i(p + 2 dt v + dt^2 u) - 2 (1 - gamma) h_i(p + dt v) + (1 - gamma)^2 h_i(p).
The orders are found symbolically (on the model's expressions, with the scene symbolic), at
most :data:`MAX_ORDER`. The rate gamma in (0, 1] is a run-time input of every Function here,
so tuning it never recompiles anything; gamma = 1 asks only that psi_{r-1} be >= 0 at the next
state, smaller values make the set shrink towards its boundary more slowly (more cautious).

Barrier-embedded models: the dynamics are the model's own on the full state (the barrier state
included, so the Functions take the full state), the margins the physical part's,
``model.margins_function(x[:n_physical], scene)``.

Inert scene slots (radius 0 far away) give c_i of about gamma^2 * 2e16 > 0 (squared margins),
which never binds for gamma >= 1e-6; their rounding (~10 in those units) would make them look
violated only for smaller gamma.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from workbench.problem.models import Model
from workbench.validation import as_array, fail, real

MAX_ORDER = 4
# [A] an assumed default for the navigation double integrator (dt = 0.02 s, |u_i| <= 5 m/s^2,
# speeds up to ~5 m/s, squared-distance margins in m^2). alpha = gamma / dt is the continuous
# class-K rate of the high-order condition (h'' + 2 alpha h' + alpha^2 h >= 0 as dt -> 0):
# psi_1 >= 0 lets the robot approach an obstacle of radius r at |d'| <= alpha (d^2 - r^2)/(2 d)
# (d the centre distance), and on that boundary keeping the condition needs a deceleration of
# about |d'| (alpha - |d'| / d). gamma = 0.1 (alpha = 5 /s) admits the top speed 5 m/s from
# ~1.5 m of clearance (r = 0.3 .. 0.9); the price is that on the boundary beyond ~0.3-0.5 m of
# clearance the condition asks for more than the box's 5 m/s^2, where the projection reports
# infeasible steps. gamma = 0.03 (alpha = 1.5 /s) would be feasible everywhere on the map, but
# measured on it (200-500 steps, velocity disturbance 1) the robot then crawls (< 1.5 m/s) and
# stalls; with 0.1 it reaches the goal, the projection/shield acting on ~10-40 % of the steps
# and ~3 % of the sample-steps infeasible; with 0.3 the shield is almost idle.
DEFAULT_GAMMA = 0.1


def check_gamma(field: str, gamma: object) -> float:
    """A numeric class-K rate: a finite number in (0, 1] (ValueError naming ``field``)."""
    return real(field, gamma, 0.0, strict=True, maximum=1.0)


@dataclass(frozen=True, eq=False)
class DiscreteCBF:
    """The discrete CBF constraints of a model (see module docstring).

    ``c`` (x, u, gamma, scene) -> c (nh,): the constraint values (>= 0 admissible);
    ``jacobian`` (x, u, gamma, scene) -> dc/du (nh, nu); ``psi`` (x, gamma, scene) -> the
    highest-order barrier psi_{r_i - 1}(x) of each margin (nh,); ``orders`` r_i per margin.
    x is the model's full state (nx), the scene its run-time scene (``model.n_scene``)."""

    model: Model
    orders: tuple[int, ...]
    c: ca.Function
    jacobian: ca.Function
    psi: ca.Function

    @property
    def nh(self) -> int:
        return len(self.orders)

    def _args(self, x, u, gamma, scene) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
        m = self.model
        s = m.scene_vector(scene)
        xa = np.asarray(x, dtype=float).ravel()
        if xa.size == m.n_physical and m.nx != xa.size:
            xa = m.lift(xa, s)
        xa = as_array("x", xa, (m.nx,))
        ua = as_array("u", u, (m.nu,))
        return xa, ua, check_gamma("gamma", gamma), s

    def values(self, x, u, gamma: float, scene=None) -> np.ndarray:
        """c(x, u) (nh,) at a full (or physical, lifted in ``scene``) state; ``scene`` None: the
        model's own. gamma must be a number in (0, 1]."""
        return np.asarray(self.c(*self._args(x, u, gamma, scene))).ravel()

    def jacobian_values(self, x, u, gamma: float, scene=None) -> np.ndarray:
        """dc/du (nh, nu) at (x, u); arguments as in :meth:`values`."""
        return np.asarray(self.jacobian(*self._args(x, u, gamma, scene)))


def discrete_cbf(model: Model) -> DiscreteCBF:
    """The discrete (high-order) CBF of every margin of ``model`` (see module docstring).

    Raises ValueError when the model has no margins, or when u does not reach a margin within
    :data:`MAX_ORDER` steps."""
    if not isinstance(model, Model):
        raise fail("model", type(model).__name__, "must be a workbench Model")
    if not model.nh:
        raise fail("model", model.name, "has no safety margins h(x): no barrier to build")
    n = model.n_physical
    x, u, s = model.x, model.u, model.scene
    gamma = ca.SX.sym("gamma")
    keep = 1.0 - gamma
    f_u = model.x_next
    f_0 = ca.substitute(f_u, u, ca.SX.zeros(model.nu))
    h = model.margins_function(x[:n], s)
    cs, psis, orders = [], [], []
    for i in range(model.nh):
        psi = h[i]
        for r in range(1, MAX_ORDER + 1):
            psi_next = ca.substitute(psi, x, f_u)
            if ca.depends_on(psi_next, u):
                cs.append(psi_next - keep * psi)
                psis.append(psi)
                orders.append(r)
                break
            psi = ca.substitute(psi, x, f_0) - keep * psi
        else:
            raise fail(f"model.h[{i}]", model.name,
                       f"the control does not reach this margin within {MAX_ORDER} steps "
                       "(discrete relative degree above MAX_ORDER, or no dependence on u): "
                       "no discrete CBF constraint on u")
    c = ca.vertcat(*cs)
    names = ["x", "u", "gamma", "scene"]
    opts = {"cse": True}
    return DiscreteCBF(
        model=model, orders=tuple(orders),
        c=ca.Function("dcbf", [x, u, gamma, s], [c], names, ["c"], opts),
        jacobian=ca.Function("dcbf_jac", [x, u, gamma, s], [ca.densify(ca.jacobian(c, u))],
                             names, ["dc_du"], opts),
        psi=ca.Function("dcbf_psi", [x, gamma, s], [ca.vertcat(*psis)],
                        ["x", "gamma", "scene"], ["psi"], opts))


__all__ = ["DEFAULT_GAMMA", "MAX_ORDER", "DiscreteCBF", "check_gamma", "discrete_cbf"]

"""The sampling problem: model, state costs and crash rule shared by MPPI, RMPPI and SA-RMPPI.

Costs (assumptions §8.2): running state cost q(x, p) evaluated on post-step states k = 1..T,
terminal
phi(x_T, p), plus the crash cost C_crash at every step from a sample's first crash on
(min_i h_i(p) <= eps_h, assumptions §4.6). ``p`` holds run-time values (the goal); crash cost,
sampling
std, temperature and limits are run-time inputs of the kernels. eps_h is compiled in: it is the
barrier's own crash margin, so the kernel's crash test and the barrier state's share one
computation.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import casadi as ca
import numpy as np

from workbench.problem.costs import Cost
from workbench.problem.models import Model
from workbench.problem.problem import Problem
from workbench.validation import as_array, fail, real


@dataclass(frozen=True, eq=False)
class SamplingProblem:
    """The sampler's view of a :class:`~workbench.problem.Problem` whose stage cost is a
    state cost q(x, p) (no control term: MPPI's control cost is its likelihood ratio) and whose
    terminal cost is phi(x, p). Dynamics, margins and costs are the Problem's own Functions."""

    problem: Problem
    description: str = ""
    weights: dict[str, np.ndarray] | None = None  # set by navigation_costs, goal_costs (twins)

    def __post_init__(self) -> None:
        if ca.depends_on(self.problem.cost.stage, self.problem.model.u):
            raise fail("cost.stage", "depends on u", "a sampling cost is a state cost q(x, p); "
                       "MPPI adds the control cost through its likelihood ratio")

    @classmethod
    def from_costs(cls, model: Model, q, phi, p, description: str = "",
                   weights: dict | None = None) -> SamplingProblem:
        """Build from state-cost expressions q(x, p), phi(x, p) in the model's x and ``p``."""
        for name, expr in (("q", q), ("phi", phi)):
            if ca.SX(expr).shape != (1, 1):
                raise fail(f"SamplingProblem.{name}", ca.SX(expr).shape, "must be a scalar")
        cost = Cost(stage=ca.SX(q), terminal=ca.SX(phi), p=ca.SX(p),
                    param_layout=(("p", int(ca.SX(p).numel())),), description=description)
        return cls(Problem.build(model, cost), description, weights)

    @property
    def model(self) -> Model:
        return self.problem.model

    @property
    def eps_h(self) -> float:
        """Crash margin: the barrier's eps_h for embedded models, else 1e-6 (assumptions §4.6)."""
        spec = self.model.barrier
        return float(spec.options.eps_h) if spec is not None else 1e-6

    @property
    def nx(self) -> int:
        return self.model.nx

    @property
    def nu(self) -> int:
        return self.model.nu

    @property
    def n_p(self) -> int:
        return self.problem.n_p

    def functions(self) -> dict[str, ca.Function]:
        """dyn (x,u)->x_next, margins (x)->h, q (x,p)->q, phi (x,p)->phi: the Problem's."""
        return self._functions

    @functools.cached_property
    def _functions(self) -> dict[str, ca.Function]:
        f, m = self.problem.functions, self.model
        x, p = ca.SX.sym("x", m.nx), ca.SX.sym("p", self.n_p)
        q = f["stage"](x, ca.SX.zeros(m.nu), p)
        return {"dyn": f["dyn"], "margins": f["margins"],
                "q": ca.Function("q", [x, p], [q], ["x", "p"], ["q"]),
                "phi": ca.Function("phi", [x, p], [f["term"](x, p)], ["x", "p"], ["phi"])}

    def fingerprint(self) -> str:
        return self.problem.fingerprint


def navigation_costs(model: Model, *, Qp=(1.0, 1.0), Qv=(0.1, 0.1), q_beta: float = 1.0,
                     S=(10.0, 10.0, 1.0, 1.0, 1.0)) -> SamplingProblem:
    """assumptions §8.2 [A]: q = |p-p_g|²_Qp + |v|²_Qv + q_beta |beta-beta_g|², phi = |x-x_g|²_S.

    Parameter p = the goal's full state x_g (physical goal lifted, so beta_g = B(h(p_g))).
    """
    n = model.n_physical
    if n != 4 or model.position != (0, 1):
        raise fail("model", model.name, "navigation_costs expects a planar double integrator")
    Qp, Qv = as_array("Qp", Qp, (2,)), as_array("Qv", Qv, (2,))
    S = as_array("S", S, (model.nx,))
    for name, w in (("Qp", Qp), ("Qv", Qv), ("S", S)):
        if not np.all(np.isfinite(w)) or np.any(w < 0):
            raise fail(name, w, "weights must be finite numbers >= 0")
    real("q_beta", q_beta, 0.0)
    x, g = model.x, ca.SX.sym("goal", model.nx)
    ep, v = x[:2] - g[:2], x[2:4]
    q = ca.dot(Qp * ep, ep) + ca.dot(Qv * v, v)
    if model.nx > n:
        eb = x[n:] - g[n:]
        q += q_beta * ca.dot(eb, eb)
    e = x - g
    weights = {"Qp": Qp, "Qv": Qv, "q_beta": float(q_beta), "S": S}
    return SamplingProblem.from_costs(model, q, ca.dot(S * e, e), g,
                                      description="navigation (assumptions §8.2)", weights=weights)


ANGLE_STATES = ("theta", "heading", "psi", "yaw")  # names goal_costs wraps by default


def goal_costs(model: Model, *, Q, S, q_beta: float = 1.0, s_beta: float = 1.0,
               angles: tuple[int, ...] | None = None) -> SamplingProblem:
    """Goal-reaching state costs for any model (the navigation costs of other systems):

        q = |x - g|²_Q + q_beta |beta - beta_g|²,   phi = |x - g|²_S (the barrier states too),

    ``Q`` one weight per physical state; ``S`` one weight per state of ``model`` (barrier
    states included), or per physical state, the barrier states then weighted ``s_beta``.
    The parameter p is the goal's full state x_g (physical goal lifted, beta_g = B(h(g))),
    as in :func:`navigation_costs`.

    Angles: for the states in ``angles`` (default: those named theta, heading, psi or yaw) the
    error e enters as 2 (1 - cos e) instead of e², equal to second order at the goal, smooth,
    and the same for e and e + 2 pi (a heading that has turned once more is at the goal).
    """
    n = model.n_physical
    Q = as_array("Q", Q, (n,))
    S = np.asarray(S, dtype=float)
    if S.shape == (n,) and model.nx > n:
        S = np.concatenate([S, np.full(model.nx - n, real("s_beta", s_beta, 0.0))])
    S = as_array("S", S, (model.nx,))
    for name, w in (("Q", Q), ("S", S)):
        if np.any(w < 0):
            raise fail(name, w, "weights must be finite numbers >= 0")
    real("q_beta", q_beta, 0.0)
    if angles is None:
        angles = tuple(i for i, s in enumerate(model.state_names[:n]) if s in ANGLE_STATES)
    if not isinstance(angles, tuple | list) or any(
            isinstance(i, bool) or not isinstance(i, int | np.integer) or not 0 <= i < n
            for i in angles) or len(set(angles)) != len(angles):
        raise fail("angles", angles, f"need distinct physical state indices in [0, {n - 1}]")
    angles = tuple(int(i) for i in angles)
    x, g = model.x, ca.SX.sym("goal", model.nx)
    e2 = [2.0 * (1.0 - ca.cos(x[i] - g[i])) if i in angles else (x[i] - g[i]) ** 2
          for i in range(n)]
    e2 += [(x[i] - g[i]) ** 2 for i in range(n, model.nx)]
    q = sum((Q[i] * e2[i] for i in range(n)), ca.SX(0))
    if model.nx > n:
        q += q_beta * sum(e2[n:], ca.SX(0))
    phi = sum((S[i] * e2[i] for i in range(model.nx)), ca.SX(0))
    weights = {"Q": Q, "S": S, "q_beta": float(q_beta), "angles": np.array(angles, dtype=int)}
    return SamplingProblem.from_costs(model, q, phi, g, description="goal reaching",
                                      weights=weights)

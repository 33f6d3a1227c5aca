"""The sampling problem: model, state costs and crash rule shared by MPPI, RMPPI and SA-RMPPI.

Costs (SPEC 8.2): running state cost q(x, p) evaluated on post-step states k = 1..T, terminal
phi(x_T, p), plus the crash cost C_crash at every step from a sample's first crash on
(min_i h_i(p) <= eps_h, SPEC 4.6). ``p`` holds run-time values (the goal); crash cost, sampling
std, temperature and limits are run-time inputs of the kernels. eps_h is compiled in: it is the
barrier's own crash margin, so the kernel's crash test and the barrier state's share one
computation.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import casadi as ca
import numpy as np

from workbench.models import Model
from workbench.validation import as_array, fail


@dataclass(frozen=True, eq=False)
class SamplingProblem:
    """Model (usually barrier-embedded) with state costs q(x, p) and phi(x, p)."""

    model: Model
    q: ca.SX
    phi: ca.SX
    p: ca.SX
    description: str = ""
    weights: dict[str, np.ndarray] | None = None  # set by navigation_costs (for the NumPy twin)

    def __post_init__(self) -> None:
        known = {s.name() for s in ca.symvar(ca.vertcat(self.model.x, self.p))}
        for name in ("q", "phi"):
            expr = ca.SX(getattr(self, name))
            if expr.shape != (1, 1):
                raise fail(f"SamplingProblem.{name}", expr.shape, "must be a scalar")
            extra = [s.name() for s in ca.symvar(expr) if s.name() not in known]
            if extra:
                raise fail(f"SamplingProblem.{name}", extra, "may depend only on x and p")

    @property
    def eps_h(self) -> float:
        """Crash margin: the barrier's eps_h for embedded models, else 1e-6 (SPEC 4.6)."""
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
        return int(self.p.numel())

    def functions(self) -> dict[str, ca.Function]:
        """dyn (x,u)->x_next, margins (x)->h, q (x,p)->q, phi (x,p)->phi (CasADi VM)."""
        m = self.model
        return {
            "dyn": ca.Function("dyn", [m.x, m.u], [m.x_next]),
            "margins": ca.Function("margins", [m.x], [m.h]),
            "q": ca.Function("q", [m.x, self.p], [self.q]),
            "phi": ca.Function("phi", [m.x, self.p], [self.phi]),
        }

    def fingerprint(self) -> str:
        h = hashlib.sha256()
        for f in self.functions().values():
            h.update(f.serialize().encode())
        h.update(np.ascontiguousarray([*self.model.u_min, *self.model.u_max]).tobytes())
        return h.hexdigest()[:16]


def navigation_costs(model: Model, *, Qp=(1.0, 1.0), Qv=(0.1, 0.1), q_beta: float = 1.0,
                     S=(10.0, 10.0, 1.0, 1.0, 1.0)) -> SamplingProblem:
    """SPEC 8.2 [A]: q = |p-p_g|²_Qp + |v|²_Qv + q_beta |beta-beta_g|², phi = |x-x_g|²_S.

    Parameter p = the goal's full state x_g (physical goal lifted, so beta_g = B(h(p_g))).
    """
    n = model.n_physical
    if n != 4 or model.position != (0, 1):
        raise fail("model", model.name, "navigation_costs expects a planar double integrator")
    Qp, Qv = as_array("Qp", Qp, (2,)), as_array("Qv", Qv, (2,))
    S = as_array("S", S, (model.nx,))
    for name, w in (("Qp", Qp), ("Qv", Qv), ("S", S), ("q_beta", np.array([q_beta]))):
        if not np.all(np.isfinite(w)) or np.any(w < 0):
            raise fail(name, w, "weights must be finite numbers >= 0")
    x, g = model.x, ca.SX.sym("goal", model.nx)
    ep, v = x[:2] - g[:2], x[2:4]
    q = ca.dot(Qp * ep, ep) + ca.dot(Qv * v, v)
    if model.nx > n:
        eb = x[n:] - g[n:]
        q += q_beta * ca.dot(eb, eb)
    e = x - g
    weights = {"Qp": Qp, "Qv": Qv, "q_beta": float(q_beta), "S": S}
    return SamplingProblem(model, q, ca.dot(S * e, e), g, description="navigation (SPEC 8.2)",
                           weights=weights)

"""System models as CasADi SX expressions (SPEC 2): x_{k+1} = F(x_k, u_k), safety margins h(x).

A :class:`Model` is a description, not a solver object: symbols, the one-step map, control box,
safety margins (h >= 0 is safe) and names. Users bring their own system with
:meth:`Model.from_expressions`; the built-in planar double and single integrators use it too.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Literal

import casadi as ca
import numpy as np

from workbench.codegen.fastcall import FastFunction
from workbench.problem.obstacles import Circle, HForm, circle_margins
from workbench.validation import as_array, bounds, fail, integer, one_of, real

Integrator = Literal["euler", "zoh"]
INTEGRATORS: tuple[str, ...] = ("euler", "zoh")


@dataclass(frozen=True, eq=False)
class Model:
    """A discrete-time model with a control box and safety margins.

    Shapes: ``x`` (nx,1) and ``u`` (nu,1) SX symbols; ``x_next`` (nx,1) in x, u; ``h`` (nh,1) in x.
    ``n_physical`` counts the leading states that are physical (the rest are barrier states).
    ``lift`` maps a physical state to the full state (identity for plain models).
    """

    name: str
    x: ca.SX
    u: ca.SX
    x_next: ca.SX
    h: ca.SX
    dt: float
    u_min: np.ndarray
    u_max: np.ndarray
    state_names: tuple[str, ...]
    control_names: tuple[str, ...]
    position: tuple[int, int] | None = None
    obstacles: tuple[Circle, ...] = ()
    n_physical: int = -1
    barrier: object | None = None  # workbench.problem.barrier.BarrierSpec for embedded models
    lift_expr: ca.SX | None = field(default=None, repr=False)  # full state in physical symbols

    @property
    def nx(self) -> int:
        return int(self.x.numel())

    @property
    def nu(self) -> int:
        return int(self.u.numel())

    @property
    def nh(self) -> int:
        return int(self.h.numel())

    @classmethod
    def from_expressions(
        cls,
        name: str,
        x: ca.SX,
        u: ca.SX,
        x_next: ca.SX,
        *,
        dt: float,
        u_min,
        u_max,
        h: ca.SX | None = None,
        state_names: tuple[str, ...] | None = None,
        control_names: tuple[str, ...] | None = None,
        position: tuple[int, int] | None = None,
        obstacles: tuple[Circle, ...] = (),
    ) -> Model:
        """Validate and wrap user CasADi expressions into a Model (the user-model entry point)."""
        for fname, sym in (("x", x), ("u", u)):
            if not isinstance(sym, ca.SX) or not sym.is_valid_input() or sym.size2() != 1:
                raise fail(fname, str(sym), "must be a column vector of CasADi SX symbols")
        nx, nu = x.numel(), u.numel()
        x_next = ca.SX(x_next)
        if x_next.shape != (nx, 1):
            raise fail("x_next", str(x_next.shape), f"must have shape ({nx}, 1) like x")
        h = ca.SX(0, 1) if h is None else ca.SX(h)
        if h.numel() and h.size2() != 1:
            h = ca.vec(h)
        known = {s.name() for s in ca.symvar(ca.vertcat(x, u))}
        known_x = {s.name() for s in ca.symvar(x)}
        for fname, expr, allowed in (("x_next", x_next, known), ("h", h, known_x)):
            extra = [s.name() for s in ca.symvar(expr) if s.name() not in allowed]
            if extra:
                raise fail(fname, extra, "may depend only on the model's own symbols "
                           + ("x and u" if fname == "x_next" else "x"))
        real("dt", dt, 0.0, strict=True)
        lo = as_array("u_min", u_min, (nu,), finite=False)
        hi = as_array("u_max", u_max, (nu,), finite=False)
        bounds("u_min", lo, "u_max", hi)
        sn = state_names or tuple(f"x{i}" for i in range(nx))
        cn = control_names or tuple(f"u{i}" for i in range(nu))
        if len(sn) != nx:
            raise fail("state_names", sn, f"need {nx} names")
        if len(cn) != nu:
            raise fail("control_names", cn, f"need {nu} names")
        if position is not None:
            for i in position:
                integer("position", i, 0, nx - 1)
        return cls(
            name=name, x=x, u=u, x_next=x_next, h=h, dt=float(dt), u_min=lo, u_max=hi,
            state_names=tuple(sn), control_names=tuple(cn), position=position,
            obstacles=tuple(obstacles), n_physical=nx, lift_expr=x,
        )

    @functools.cached_property
    def lift_function(self) -> ca.Function:
        return ca.Function("lift", [self.x[: self.n_physical]], [self.lift_expr])

    @functools.cached_property
    def margins_function(self) -> ca.Function:
        return ca.Function("h", [self.x[: self.n_physical]], [self.h])

    @functools.cached_property
    def _fast_lift(self) -> FastFunction:
        return FastFunction(self.lift_function)

    @functools.cached_property
    def _fast_margins(self) -> FastFunction:
        return FastFunction(self.margins_function)

    def lift(self, x_phys) -> np.ndarray:
        """Full state (physical state plus barrier states, if any) from a physical state."""
        xp = as_array("x", x_phys, (self.n_physical,))
        if self.lift_expr is None or self.n_physical == self.nx:
            return xp.copy()
        return self._fast_lift(xp)[0]

    def margins(self, x) -> np.ndarray:
        """Safety margins h(x) at a full (or physical) state; NumPy in, NumPy out."""
        xa = np.asarray(x, dtype=float).ravel()
        if xa.size not in (self.n_physical, self.nx):
            raise fail("x", xa, f"expected {self.n_physical} or {self.nx} entries")
        return self._fast_margins(xa[: self.n_physical])[0]


def double_integrator(
    *,
    dt: float = 0.02,
    integrator: Integrator = "euler",
    obstacles: tuple[Circle, ...] = (),
    u_limit: float | tuple[float, float] = 15.0,
    h_form: HForm = "squared",
    inflation: float = 0.0,
) -> Model:
    """Planar double integrator x = [px, py, vx, vy], u = [ax, ay] (SPEC 2.1-2.2)."""
    one_of("integrator", integrator, INTEGRATORS)
    x = ca.SX.sym("x", 4)
    u = ca.SX.sym("u", 2)
    p, v = x[:2], x[2:]
    p_next = p + dt * v + (0.5 * dt**2 * u if integrator == "zoh" else 0)
    x_next = ca.vertcat(p_next, v + dt * u)
    lo, hi = _box(u_limit, 2)
    return Model.from_expressions(
        "double_integrator", x, u, x_next, dt=dt, u_min=lo, u_max=hi,
        h=circle_margins(p, obstacles, h_form, inflation),
        state_names=("px", "py", "vx", "vy"), control_names=("ax", "ay"),
        position=(0, 1), obstacles=obstacles,
    )


def single_integrator(
    *,
    dt: float = 0.02,
    obstacles: tuple[Circle, ...] = (),
    u_limit: float | tuple[float, float] = 15.0,
    h_form: HForm = "squared",
    inflation: float = 0.0,
) -> Model:
    """Planar single integrator x = [px, py], u = [vx, vy] (SPEC 2.4)."""
    x = ca.SX.sym("x", 2)
    u = ca.SX.sym("u", 2)
    lo, hi = _box(u_limit, 2)
    return Model.from_expressions(
        "single_integrator", x, u, x + dt * u, dt=dt, u_min=lo, u_max=hi,
        h=circle_margins(x, obstacles, h_form, inflation),
        state_names=("px", "py"), control_names=("vx", "vy"), position=(0, 1),
        obstacles=obstacles,
    )


def _box(u_limit, nu: int) -> tuple[np.ndarray, np.ndarray]:
    if np.ndim(u_limit) == 0:
        lim = float(u_limit)
        if not lim > 0:  # np.inf is allowed: no control limits
            raise fail("u_limit", u_limit, "must be > 0 (np.inf for no limits)")
        return -lim * np.ones(nu), lim * np.ones(nu)
    lo, hi = as_array("u_limit", u_limit, (2,), finite=False)
    return lo * np.ones(nu), hi * np.ones(nu)

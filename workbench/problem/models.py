"""System models as CasADi SX expressions (assumptions §2): x_{k+1} = F(x_k, u_k), safety margins
h(x).

A :class:`Model` is a description, not a solver object: symbols, the one-step map, control box,
safety margins (h >= 0 is safe) and names. Users bring their own system with
:meth:`Model.from_expressions`; the built-in planar double and single integrators use it too.

Obstacles are run-time inputs: the margins are expressions in x and a ``scene`` symbol (for the
built-in models, ``scene_capacity`` circle slots of (x, y, radius)), so one compiled kernel or
solver serves every map with at most that many circles and a scene may change between steps.
``scene_value`` is the scene the model was built with (its default). ``runtime_obstacles=False``
bakes the circles into the expressions as constants instead (the old behaviour; compared in
``make bench``).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal

import casadi as ca
import numpy as np

from workbench.codegen.fastcall import FastFunction

if TYPE_CHECKING:
    from workbench.problem.barrier import BarrierSpec
from workbench.problem.obstacles import (
    INERT_SLOT,
    Circle,
    HForm,
    circle_margins,
    scene_symbol,
    scene_vector,
    slot_margins,
    slots_valid,
)
from workbench.problem.scene_layout import SceneLayout
from workbench.validation import (
    as_array,
    bounds,
    fail,
    flag,
    integer,
    one_of,
    real,
    real_or_inf,
)

Integrator = Literal["euler", "zoh"]
INTEGRATORS: tuple[str, ...] = ("euler", "zoh")
MAX_SCENE_SLOTS = 10**4  # circle slots of one run-time scene (3 symbols each)


@dataclass(frozen=True, eq=False)
class Model:
    """A discrete-time model with a control box and safety margins.

    Shapes: ``x`` (nx,1) and ``u`` (nu,1) SX symbols; ``x_next`` (nx,1) in x, u (and the scene,
    for barrier-embedded models); ``h`` (nh,1) in x and the scene; ``scene`` (ns,1) SX symbol
    (ns = 0: no run-time scene), ``scene_value`` (ns,) its default value.
    ``n_physical`` counts the leading states that are physical (the rest are barrier states).
    ``lift`` maps a physical state to the full state (identity for plain models).
    ``state_units``: one unit per state ("m", "rad/s"; "" for none), or None when unknown; the
    plots label an axis "name [unit]".
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
    position: tuple[int, ...] | None = None
    obstacles: tuple[Circle, ...] = ()
    n_physical: int = -1
    barrier: BarrierSpec | None = None  # for barrier-embedded models
    lift_expr: ca.SX | None = field(default=None, repr=False)  # full state in physical symbols
    scene: ca.SX = field(default_factory=lambda: ca.SX(0, 1), repr=False)
    scene_value: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    scene_capacity: int = 0  # circle slots of a circle-only scene (0: none, or a layout)
    state_units: tuple[str, ...] | None = None
    scene_layout: SceneLayout | None = None  # obstacles of several kinds (scene_capacity 0)

    def __post_init__(self) -> None:
        _check_sizes(self.x, self.u, "Model.")

    @property
    def nx(self) -> int:
        return int(self.x.numel())

    @property
    def nu(self) -> int:
        return int(self.u.numel())

    @property
    def nh(self) -> int:
        return int(self.h.numel())

    @property
    def n_scene(self) -> int:
        """Size of the scene input (0: the model has none)."""
        return int(self.scene.numel())

    def scene_vector(self, scene=None) -> np.ndarray:
        """The scene input for ``scene``: None (the model's own), circles (a sequence of
        :class:`Circle` or (x, y, radius) triples, or an (n, 3) array, n <= scene_capacity; the
        other slots inert), or a flat array of size ``n_scene`` (with circle slots: each a
        circle of radius > 0 or exactly the unused slot ``INERT_SLOT``)."""
        if scene is None:
            return self.scene_value
        if self.scene_capacity:
            return scene_vector(scene, self.scene_capacity)
        if self.scene_layout is not None:
            return self.scene_layout.vector(scene)
        v = as_array("scene", scene, (self.n_scene,))
        return v.copy()

    def _scene_input(self, scene) -> np.ndarray:
        """:meth:`scene_vector` for read-only use (no copy). A float64 vector of the right
        size, finite, every circle slot valid (what :meth:`scene_vector` returns) takes a fast
        path: the
        controllers pass their validated scene on every step."""
        if scene is None:
            return self.scene_value
        if (isinstance(scene, np.ndarray) and scene.dtype == np.float64
                and scene.shape == (self.n_scene,) and np.isfinite(scene).all()
                and (not self.scene_capacity or slots_valid(scene))
                and (self.scene_layout is None or self.scene_layout.valid(scene))):
            return scene
        return self.scene_vector(scene)

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
        position: tuple[int, ...] | None = None,
        obstacles: tuple[Circle, ...] = (),
        scene: ca.SX | None = None,
        scene_value=None,
        scene_capacity: int = 0,
        state_units: tuple[str, ...] | None = None,
        scene_layout: SceneLayout | None = None,
    ) -> Model:
        """Validate and wrap user CasADi expressions into a Model (the user-model entry point).

        ``h`` may depend on x and a ``scene`` symbol (run-time obstacle data, given as
        ``scene_value`` by default and changed per call by the controllers; with
        ``scene_capacity`` slots the default has every slot unused); build a circle scene
        with :func:`~workbench.problem.obstacles.scene_symbol` and
        :func:`~workbench.problem.obstacles.slot_margins` (``scene_capacity`` = its slots),
        or obstacles of several kinds with a
        :class:`~workbench.problem.scene_layout.SceneLayout` (``scene_layout``; ``scene`` its
        ``symbol()``, ``h`` from its ``margins``; the default has every slot unused).
        ``state_units``: one string per state ("" for a state without a unit), used to label
        plots; None (default) labels them by name alone."""
        for fname, sym in (("x", x), ("u", u)):
            if not isinstance(sym, ca.SX) or not sym.is_valid_input() or sym.size2() != 1:
                raise fail(fname, str(sym), "must be a column vector of CasADi SX symbols")
        _check_sizes(x, u)
        nx, nu = x.numel(), u.numel()
        x_next = _column("x_next", x_next)
        if x_next.shape != (nx, 1):
            raise fail("x_next", str(x_next.shape), f"must have shape ({nx}, 1) like x")
        h = ca.SX(0, 1) if h is None else _column("h", h)
        if h.numel() and h.size2() != 1:
            h = ca.vec(h)
        scene = ca.SX(0, 1) if scene is None else scene
        if scene.numel() and (not scene.is_valid_input() or scene.size2() != 1):
            raise fail("scene", str(scene), "must be a column vector of CasADi SX symbols")
        integer("scene_capacity", scene_capacity, 0)
        if scene_capacity and 3 * scene_capacity != scene.numel():
            raise fail("scene_capacity", scene_capacity,
                       f"a circle scene has 3 entries per slot; the scene has {scene.numel()}")
        if scene_layout is not None:
            if not isinstance(scene_layout, SceneLayout):
                raise fail("scene_layout", scene_layout, "must be a SceneLayout")
            if scene_capacity:
                raise fail("scene_capacity", scene_capacity, "give either scene_capacity "
                           "(circles) or scene_layout (its circles are SceneLayout slots)")
            if scene_layout.size != scene.numel():
                raise fail("scene_layout", scene_layout, f"describes {scene_layout.size} "
                           f"scene entries; the scene has {scene.numel()}")
            sv = (scene_layout.inert() if scene_value is None
                  else scene_layout.vector(scene_value, "scene_value"))
        elif scene_capacity:  # circles, or every slot unused (never a point at the origin)
            sv = (np.tile(INERT_SLOT, scene_capacity) if scene_value is None
                  else _circle_scene_value(scene_value, scene_capacity))
        else:
            sv = (np.zeros(scene.numel()) if scene_value is None
                  else as_array("scene_value", scene_value, (scene.numel(),)))
        known = {s.name() for s in ca.symvar(ca.vertcat(x, u))}
        known_x = {s.name() for s in ca.symvar(ca.vertcat(x, scene))}
        for fname, expr, allowed in (("x_next", x_next, known), ("h", h, known_x)):
            extra = [s.name() for s in ca.symvar(expr) if s.name() not in allowed]
            if extra:
                raise fail(fname, extra, "may depend only on the model's own symbols "
                           + ("x and u" if fname == "x_next" else "x and the scene"))
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
        if state_units is not None:
            if (not isinstance(state_units, tuple | list) or len(state_units) != nx
                    or not all(isinstance(s, str) for s in state_units)):
                raise fail("state_units", state_units, f"must be {nx} strings, one unit per "
                           "state (\"\" for a state without one), or None")
            state_units = tuple(state_units)
        if position is not None:
            if (not isinstance(position, tuple | list) or len(position) not in (2, 3)
                    or len(set(position)) != len(position)):
                raise fail("position", position, "must be 2 or 3 distinct state indices (the "
                           "planar or spatial position), or None")
            for i in position:
                integer("position", i, 0, nx - 1)
            position = tuple(int(i) for i in position)
        return cls(
            name=name, x=x, u=u, x_next=x_next, h=h, dt=float(dt), u_min=lo, u_max=hi,
            state_names=tuple(sn), control_names=tuple(cn), position=position,
            obstacles=tuple(obstacles), n_physical=nx, lift_expr=x, scene=scene,
            scene_value=sv, scene_capacity=int(scene_capacity), state_units=state_units,
            scene_layout=scene_layout,
        )

    @functools.cached_property
    def lift_function(self) -> ca.Function:
        """(x_physical, scene) -> full state."""
        if self.lift_expr is None:
            raise fail("Model.lift_expr", None, "must be the full state in the physical "
                       "symbols to build the lift (Model.from_expressions sets it)")
        return ca.Function("lift", [self.x[: self.n_physical], self.scene], [self.lift_expr],
                           ["x", "scene"], ["x_full"])

    @functools.cached_property
    def margins_function(self) -> ca.Function:
        """(x_physical, scene) -> h."""
        return ca.Function("h", [self.x[: self.n_physical], self.scene], [self.h],
                           ["x", "scene"], ["h"])

    @functools.cached_property
    def _fast_lift(self) -> FastFunction:
        return FastFunction(self.lift_function)

    @functools.cached_property
    def _fast_margins(self) -> FastFunction:
        return FastFunction(self.margins_function)

    def lift(self, x_phys, scene=None) -> np.ndarray:
        """Full state (physical state plus barrier states, if any) from a physical state, in
        ``scene`` (default: the model's own; see :meth:`scene_vector`)."""
        xp = as_array("x", x_phys, (self.n_physical,))
        if self.lift_expr is None or self.n_physical == self.nx:
            return xp.copy()
        return self._fast_lift(xp, self._scene_input(scene))[0]

    def margins(self, x, scene=None) -> np.ndarray:
        """Safety margins h(x) at a full (or physical) state in ``scene`` (default: the
        model's own); NumPy in, NumPy out."""
        xa = np.asarray(x, dtype=float).ravel()
        if xa.size not in (self.n_physical, self.nx):
            raise fail("x", xa, f"expected {self.n_physical} or {self.nx} entries")
        return self._fast_margins(xa[: self.n_physical], self._scene_input(scene))[0]


def margin_violation(model: Model, h: np.ndarray, eps: float = 0.0) -> str | None:
    """Where the margins ``h`` of ``model`` at one state fail ``h > eps``, in words ("lies
    inside obstacle 2 (h[2] = -0.31 < 0)", "lies on the boundary of obstacle 0 (h[0] = 0)",
    "lies within 1e-06 of the boundary of ..."), naming the first failing margin; None when
    every margin passes. Margins past the circle slots are other constraints (state limits)."""
    h = np.asarray(h, dtype=float).ravel()
    bad = np.flatnonzero(~(h > eps))
    if not bad.size:
        return None
    i = int(bad[np.argmin(np.nan_to_num(h[bad], nan=-np.inf))])
    v = h[i]
    n_obstacles = (model.scene_layout.n_margins if model.scene_layout is not None
                   else model.scene_capacity or len(model.obstacles))
    obstacle = i < n_obstacles
    what = (f"obstacle {i}" if obstacle else
            f"constraint h[{i}] > 0 of the model (a state limit or a constraint of its h(x))")
    if np.isnan(v):
        return f"has an undefined margin h[{i}] = nan ({what})"
    if v < 0:
        return (f"lies inside {what} (h[{i}] = {v:.4g} < 0)" if obstacle
                else f"violates {what}: h[{i}] = {v:.4g} < 0")
    if v == 0:
        return f"lies on the boundary of {what} (h[{i}] = 0)"
    return f"lies within {eps:g} of the boundary of {what} (h[{i}] = {v:.4g} <= {eps:g})"


def _column(field: str, value) -> ca.SX:
    """``value`` as a CasADi SX column: an SX expression, or a list or tuple of SX expressions
    and numbers (stacked); anything else is a ValueError naming ``field``."""
    try:
        if isinstance(value, list | tuple):
            return ca.vertcat(*[ca.SX(v) for v in value]) if value else ca.SX(0, 1)
        return ca.SX(value)
    except (NotImplementedError, TypeError, RuntimeError) as exc:
        raise fail(field, value, "must be a CasADi SX expression in the model's symbols, or "
                   "a list of them (stacked into a column)") from exc


def _check_sizes(x: ca.SX, u: ca.SX, prefix: str = "") -> None:
    """A model needs at least one state and one control: every method here optimises over u
    (iLQG, the samplers, the safety filters), and a model without states has nothing to
    steer. A system without inputs is simulated, not controlled: give it a control that
    does not enter x_next (and a zero control cost) if it must run through these tools."""
    if x.numel() == 0:
        raise fail(f"{prefix}x", f"SX of shape {x.shape}", "has no entries: a model needs at "
                   "least one state (nx >= 1)")
    if u.numel() == 0:
        raise fail(f"{prefix}u", f"SX of shape {u.shape}", "has no entries: a model needs at "
                   "least one control (nu >= 1); iLQG, the samplers and the safety filters all "
                   "optimise over the controls")


def double_integrator(
    *,
    dt: float = 0.02,
    integrator: Integrator = "euler",
    obstacles: tuple[Circle, ...] = (),
    u_limit: float | tuple[float, float] = 15.0,
    h_form: HForm = "squared",
    inflation: float = 0.0,
    scene_capacity: int | None = None,
    runtime_obstacles: bool = True,
    scene_layout: SceneLayout | None = None,
) -> Model:
    """Planar double integrator x = [px, py, vx, vy], u = [ax, ay] (assumptions §2.1-§2.2).

    The obstacles are the default scene of ``scene_capacity`` circle slots (default: one per
    obstacle); ``runtime_obstacles=False`` bakes them in as constants; ``scene_layout`` holds
    obstacles of several kinds (half-planes, capsules, a signed-distance grid, ...)."""
    one_of("integrator", integrator, INTEGRATORS)
    x = ca.SX.sym("x", 4)
    u = ca.SX.sym("u", 2)
    p, v = x[:2], x[2:]
    p_next = p + dt * v + (0.5 * dt**2 * u if integrator == "zoh" else 0)
    x_next = ca.vertcat(p_next, v + dt * u)
    lo, hi = _box(u_limit, 2)
    return Model.from_expressions(
        "double_integrator", x, u, x_next, dt=dt, u_min=lo, u_max=hi,
        state_names=("px", "py", "vx", "vy"), control_names=("ax", "ay"),
        position=(0, 1), state_units=("m", "m", "m/s", "m/s"),
        **circle_scene(p, obstacles, h_form, inflation, scene_capacity, runtime_obstacles,
                       scene_layout),
    )


def single_integrator(
    *,
    dt: float = 0.02,
    obstacles: tuple[Circle, ...] = (),
    u_limit: float | tuple[float, float] = 15.0,
    h_form: HForm = "squared",
    inflation: float = 0.0,
    scene_capacity: int | None = None,
    runtime_obstacles: bool = True,
    scene_layout: SceneLayout | None = None,
) -> Model:
    """Planar single integrator x = [px, py], u = [vx, vy] (assumptions §2.4); obstacles as in
    :func:`double_integrator`."""
    x = ca.SX.sym("x", 2)
    u = ca.SX.sym("u", 2)
    lo, hi = _box(u_limit, 2)
    return Model.from_expressions(
        "single_integrator", x, u, x + dt * u, dt=dt, u_min=lo, u_max=hi,
        state_names=("px", "py"), control_names=("vx", "vy"), position=(0, 1),
        state_units=("m", "m"),
        **circle_scene(x, obstacles, h_form, inflation, scene_capacity, runtime_obstacles,
                       scene_layout),
    )


def circle_scene(p, obstacles, h_form: HForm = "squared", inflation: float = 0.0,
                 scene_capacity: int | None = None, runtime_obstacles: bool = True,
                 scene_layout: SceneLayout | None = None) -> dict:
    """Keyword arguments of :meth:`Model.from_expressions` for circular obstacles around the
    position ``p`` (2 SX entries): ``h``, ``obstacles`` and, with run-time obstacles, the
    ``scene`` symbol of ``scene_capacity`` slots (default: one per obstacle; at most
    :data:`MAX_SCENE_SLOTS`) and its value. With ``scene_layout`` the scene holds obstacles of
    several kinds (``obstacles`` then any that fit it, see
    :class:`~workbench.problem.scene_layout.SceneLayout`)."""
    flag("runtime_obstacles", runtime_obstacles)
    if scene_layout is not None:
        if not isinstance(scene_layout, SceneLayout):
            raise fail("scene_layout", scene_layout, "must be a SceneLayout")
        if scene_capacity is not None or not runtime_obstacles:
            raise fail("scene_layout", scene_layout, "is a run-time scene: give it without "
                       "scene_capacity and with runtime_obstacles=True")
        if p.numel() != scene_layout.dim:
            raise fail("scene_layout.dim", scene_layout.dim,
                       f"must be the position's dimension, {p.numel()}")
        s = scene_layout.symbol()
        value = scene_layout.vector(list(obstacles), "obstacles")
        return {"h": scene_layout.margins(p, s, h_form, inflation),
                "obstacles": tuple(o for o in obstacles if isinstance(o, Circle)),
                "scene": s, "scene_value": value, "scene_layout": scene_layout}
    obstacles = tuple(obstacles)
    if not runtime_obstacles:
        if scene_capacity is not None:
            raise fail("scene_capacity", scene_capacity,
                       "baked obstacles (runtime_obstacles=False) have no scene slots")
        return {"h": circle_margins(p, obstacles, h_form, inflation), "obstacles": obstacles}
    if len(obstacles) > MAX_SCENE_SLOTS:
        raise fail("obstacles", f"{len(obstacles)} circles",
                   f"at most {MAX_SCENE_SLOTS} circles fit a run-time scene")
    cap = len(obstacles) if scene_capacity is None else integer(
        "scene_capacity", scene_capacity, len(obstacles), MAX_SCENE_SLOTS)
    s = scene_symbol(cap)
    return {"h": slot_margins(p, s, h_form, inflation), "obstacles": obstacles, "scene": s,
            "scene_value": scene_vector(obstacles, cap), "scene_capacity": cap}


def _circle_scene_value(value, capacity: int) -> np.ndarray:
    """``scene_value`` of a circle scene (circles or a flat vector, see :func:`scene_vector`),
    its errors named ``scene_value``."""
    try:
        return scene_vector(value, capacity)
    except ValueError as exc:
        raise fail("scene_value", value, f"must be a circle scene ({exc})") from exc


def _box(u_limit, nu: int) -> tuple[np.ndarray, np.ndarray]:
    if np.ndim(u_limit) == 0:
        v = u_limit.item() if isinstance(u_limit, np.ndarray) else u_limit  # 0-d array
        lim = np.nan if isinstance(v, str) else real_or_inf("u_limit", v)
        if not lim > 0:  # np.inf is allowed: no control limits
            raise fail("u_limit", u_limit, "must be a number > 0 (np.inf for no limits)")
        return -lim * np.ones(nu), lim * np.ones(nu)
    lo, hi = as_array("u_limit", u_limit, (2,), finite=False)
    return lo * np.ones(nu), hi * np.ones(nu)

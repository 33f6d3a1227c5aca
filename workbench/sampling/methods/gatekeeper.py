"""Gatekeeper: a backup shield around any controller.

Gurriet, Mote, Singletary, Nilsson, Feron, Ames, "A Scalable Safety Critical Control Framework
for Nonlinear Systems", IEEE Access 2020 (backup set method); Agrawal, Chen, Panagou,
"gatekeeper: Online Safety Verification and Control for Nonlinear Systems in Dynamic
Environments", arXiv:2211.14361 (2023).

Each step the inner controller proposes u. The shield predicts x1 = f(x, u) with the
noise-free model and rolls the backup policy out from x1 for ``horizon`` steps. If x1 and every
state of that rollout are safe (min over states and margins of h > ``margin``) and the rollout
ends at rest (its last step moves no state faster than ``rest_tol``, see
:class:`GatekeeperConfig`), u is applied; otherwise the backup policy's control at the current
state x is applied (clipped to the box). The whole check (rollout, margins, running minimum,
final rate) is ONE CasADi Function, a fold over the horizon, evaluated in place
(:class:`~workbench.codegen.fastcall.FastFunction`); the obstacles are its run-time input, so
:meth:`Gatekeeper.set_scene` costs microseconds.

The check is exact for the model it is given: when the plant is that model and undisturbed,
once a proposal has passed the check, a step that applies the backup follows a rollout verified
earlier that stays safe and ends at rest, so the state stays safe. A safe set is invariant
under the backup only if the backup ends in a safe equilibrium, hence the rest check; at the
start of an episode (:meth:`Gatekeeper.initial_state`) the shield also checks that its backup
brings the plant to rest from a moving state, and refuses a backup that does not
(:meth:`Gatekeeper.check_backup_rests`). Disturbances void the argument, and the rest tolerance
weakens it to "nearly at rest" (assumptions §8.4). A backup derived from the model alone,
which brakes any model whose moving states the controls reach within a few steps:
:func:`model_braking_backup` (assumptions §8.5).

Moving circles (a scene with moving slots) are predicted over the check's horizon
(:func:`backup_check_function`); a rest state is then safe only as long as no circle's predicted
path reaches it, so the invariance argument above covers the checked horizon only.

``Gatekeeper.record_samples(k)`` switches the inner controller's recording on
(:mod:`workbench.sampling.samples`); ``GatekeeperInfo.samples`` is the inner step's.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import casadi as ca
import numpy as np

from workbench.codegen.fastcall import FastFunction
from workbench.problem.models import Model
from workbench.problem.prediction import predicts, scene_sx_at
from workbench.sampling.feedback.effect import differs
from workbench.sampling.planning import physical_model
from workbench.sampling.samples import Keep, SampleTrajectories
from workbench.sampling.step_stats import StepStats
from workbench.validation import as_array, fail, integer, real, real_or_inf

# [A] assumed defaults for the navigation double integrator (|u_i| <= 5 m/s^2, speeds up to
# ~5 m/s, dt = 0.02 s): the deadbeat braking gain 1/dt stops each axis exactly, in
# ceil(|v_i| / (5 * 0.02)) <= 50 steps from 5 m/s; a 60-step horizon (1.2 s) covers that stop
# plus 10 steps at rest.
DEFAULT_HORIZON = 60
# the check is one fold over the horizon whose scene input is repeated per step (horizon x
# n_scene symbolic entries): 10 000 steps (200 s at dt = 0.02 s) bound that allocation
MAX_HORIZON = 10_000
# [A] assumptions §8.4: a rollout ends at rest when its last step changes no state faster than
# 0.1 of its units per second (SI: 10 cm/s, 0.1 rad/s, 0.1 m/s^2). Deadbeat braking and the
# unicycle's stop end exactly at rest; the quadrotor's hover loop ends the start check at 0.042;
# a braking law that chatters on a torque-driven arm ends at 73
DEFAULT_REST_TOL = 0.1
# [A] assumptions §8.4: the start check's moving states: the start state after 10 steps of a
# control a quarter and three quarters of the way across the box
REST_PUSH_STEPS = 10
REST_PUSH_FRACTION = 0.5
# Levenberg damping of model_braking_backup's Gauss-Newton steps (in box units, where the
# normal matrix has entries of order 1): keeps a control that moves nothing within the
# lookahead at its start value
GN_DAMPING = 1e-9


@dataclass(frozen=True)
class GatekeeperConfig:
    """Shield settings: ``horizon`` backup steps checked after x1, in [1, 10 000]
    (:data:`MAX_HORIZON`; default 60, an assumed value: see :func:`braking_backup`),
    ``margin`` >= 0 that every h_i must exceed (in the units of the model's margins; 0: plain
    safety h > 0).

    The rest check (assumptions §8.4): the backup rollout ends at rest when its last step moves
    every state i by at most ``rest_tol * rest_scale[i] * dt``, i.e. the final rate
    max_i |x_{H+1,i} - x_{H,i}| / (dt rest_scale[i]) <= ``rest_tol``. ``rest_tol`` > 0 (default
    0.1 per second; ``inf`` switches the check off and with it the guarantee);
    ``rest_scale``: one rate unit per physical state, > 0 (``inf`` ignores a state, e.g. a
    clock), default None: the backup's own (:attr:`BackupPolicy.rest_scale`), else 1 for every
    state."""

    horizon: int = DEFAULT_HORIZON
    margin: float = 0.0
    rest_tol: float = DEFAULT_REST_TOL
    rest_scale: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        integer("GatekeeperConfig.horizon", self.horizon, 1, MAX_HORIZON)
        real("GatekeeperConfig.margin", self.margin, 0.0)
        allowed = "must be a number > 0 (inf switches the rest check off)"
        try:
            tol = real_or_inf("GatekeeperConfig.rest_tol", self.rest_tol)
        except ValueError as exc:
            raise fail("GatekeeperConfig.rest_tol", self.rest_tol, allowed) from exc
        if not tol > 0:
            raise fail("GatekeeperConfig.rest_tol", self.rest_tol, allowed)
        object.__setattr__(self, "rest_tol", tol)
        if self.rest_scale is not None:
            object.__setattr__(self, "rest_scale", _rate_units(
                "GatekeeperConfig.rest_scale", self.rest_scale, None))


def _rate_units(field: str, value, n: int | None) -> tuple[float, ...]:
    """``value`` as a tuple of rate units, each > 0 or inf, ``n`` of them (None: any number)."""
    allowed = ("must be numbers > 0 (inf ignores a state)"
               + ("" if n is None else f", one per physical state ({n})"))
    if isinstance(value, str | bytes) or any(isinstance(v, bool | np.bool_) for v in
                                             np.ravel(np.asarray(value, dtype=object))):
        raise fail(field, value, allowed)
    try:
        s = as_array(field, value, (None,) if n is None else (n,), finite=False)
    except ValueError as exc:
        raise fail(field, value, allowed) from exc
    if not s.size or np.any(np.isnan(s)) or np.any(s <= 0):
        raise fail(field, value, allowed)
    return tuple(float(v) for v in s)


@dataclass(frozen=True, eq=False)
class BackupPolicy:
    """A state-feedback backup law: ``function`` maps the physical state (n,) to a control
    (nu,) already clipped to the model's box. ``rest_scale``: the rate units in which the
    gatekeeper's rest check measures each state when its config gives none (None: 1 each; see
    :class:`GatekeeperConfig`). Build one with :func:`model_braking_backup`,
    :func:`braking_backup` or :func:`backup_from_expression`."""

    function: ca.Function
    name: str = "backup"
    rest_scale: tuple[float, ...] | None = None

    @functools.cached_property
    def _fast(self) -> FastFunction:
        return FastFunction(self.function)

    def __call__(self, x) -> np.ndarray:
        """The backup control at ``x`` (NumPy)."""
        return self._fast(np.asarray(x, dtype=float))[0]


def backup_from_expression(model: Model, expr, name: str = "backup",
                           rest_scale: Sequence[float] | None = None) -> BackupPolicy:
    """A backup law u = clip(expr(x)) from a CasADi expression in the model's physical state
    symbols ``model.x[:n_physical]`` (nu entries); ``rest_scale``: see
    :class:`BackupPolicy`."""
    m = model if model.nx == model.n_physical else physical_model(model)
    try:
        e = ca.SX(expr)
    except (NotImplementedError, TypeError, RuntimeError) as exc:
        raise fail("expr", expr, "must be a CasADi SX expression") from exc
    if e.numel() != m.nu:
        raise fail("expr", e.shape, f"must have {m.nu} entries (one per control of {m.name})")
    known = ca.symvar(m.x)
    extra = [s.name() for s in ca.symvar(e) if not any(ca.is_equal(s, k) for k in known)]
    if extra:
        raise fail("expr", extra, f"may depend only on the physical state symbols of {m.name}")
    u = ca.fmin(ca.fmax(ca.vec(e), m.u_min), m.u_max)
    sc = None if rest_scale is None else _rate_units("rest_scale", rest_scale, m.nx)
    return BackupPolicy(ca.Function(name, [m.x], [u], ["x"], ["u"]), name, sc)


def braking_backup(model: Model, velocity: Sequence[int] = (2, 3),
                   gain: float | None = None) -> BackupPolicy:
    """Braking for position-velocity models: u_i = clip(-gain * x[velocity[i]]), control i
    accelerating state ``velocity[i]``. The default gain is 1/dt: with the Euler double
    integrator each axis then reaches zero speed exactly (full braking, then one step that
    cancels the rest), within ceil(|v_i| / (u_max dt)) steps."""
    m = model if model.nx == model.n_physical else physical_model(model)
    idx = tuple(velocity) if isinstance(velocity, Sequence) else (velocity,)
    allowed = (f"need {m.nu} distinct state indices in [0, {m.nx - 1}] (one velocity per "
               f"control of {m.name})")
    if len(idx) != m.nu or len(set(idx)) != len(idx):
        raise fail("velocity", velocity, allowed)
    for i in idx:
        try:
            integer("velocity", i, 0, m.nx - 1)
        except ValueError as exc:
            raise fail("velocity", velocity, allowed) from exc
    g = 1.0 / m.dt if gain is None else real("gain", gain, 0.0, strict=True)
    expr = ca.vertcat(*[-g * m.x[i] for i in idx])
    return backup_from_expression(m, expr, name="braking")


def model_braking_backup(model: Model, *, lookahead: int = 2, iterations: int = 3,
                         scale: Sequence[float] | None = None,
                         name: str = "model_braking") -> BackupPolicy:
    """A braking law derived from the model alone (assumptions §8.5): the control u, held
    constant over ``lookahead`` >= 2 steps, that makes the state move least,
    u(x) = argmin_u sum_{j<L} sum_i w_i (x_{j+1,i} - x_{j,i})^2 / dt^2, from ``iterations``
    Gauss-Newton steps from u = clip(0) in the units of the box (each step clipped to the
    box), as one CasADi expression; ``lookahead`` in [2, 50], ``iterations`` in [1, 20].

    Weights: ``scale`` (one rate unit per physical state, inf ignores a state) gives
    w_i = 1 / scale_i^2. By default w_i = 1 / a_i^2, a_i the authority of the controls over
    state i's rate within the lookahead (the largest norm over j of d rate_{j,i} / du times the
    box half-widths, at u = clip(0)): every state's motion is measured against how much the
    controls can change it, so the law does not depend on the units of states or controls;
    states the controls cannot reach within the lookahead (a_i = 0) are left out. With L = 2 the
    Euler double integrator gets u = clip(-v / (3 dt)) (each step removes a third of the
    speed); a one-step lookahead cannot brake it (its position's first change does not depend
    on u). It brakes models whose moving states the controls reach within the lookahead
    (positions and velocities of fully actuated mechanical models); it does not brake an
    underactuated one (a quadrotor's horizontal motion needs a tilt first)."""
    m = model if model.nx == model.n_physical else physical_model(model)
    L = integer("lookahead", lookahead, 2, 50)
    iters = integer("iterations", iterations, 1, 20)
    n, nu, dt = m.nx, m.nu, m.dt
    lo, hi = m.u_min, m.u_max
    half = np.ones(nu)  # the units of the Gauss-Newton steps: the box's half-widths
    bounded = np.isfinite(lo) & np.isfinite(hi)
    half[bounded] = 0.5 * (hi[bounded] - lo[bounded])
    u0 = np.clip(0.0, lo, hi)
    x, u = m.x, ca.SX.sym("u", nu)
    f = ca.Function("f", [m.x, m.u], [m.x_next])
    xs, rates = x, []
    for _ in range(L):
        xn = f(xs, u)
        rates.append((xn - xs) / dt)
        xs = xn
    R = ca.vertcat(*rates)  # (L n): the rates of the L steps, step by step
    rates_jac = ca.Function("rates", [x, u], [R, ca.jacobian(R, u) @ ca.diag(half)])
    if scale is None:
        _, J0 = rates_jac(x, ca.DM(u0))
        w = []
        for i in range(n):
            a = ca.mmax(ca.vertcat(*[ca.norm_2(J0[j * n + i, :]) for j in range(L)]))
            w.append(ca.if_else(a > 0, 1.0 / (a * a), 0.0))
        wv = ca.vertcat(*w)
    else:
        sc = np.asarray(_rate_units("scale", scale, n))
        wv = ca.SX(ca.DM(np.where(np.isinf(sc), 0.0, 1.0 / sc**2)))
    W = ca.repmat(wv, L, 1)
    uk = ca.SX(ca.DM(u0))
    for _ in range(iters):
        r, J = rates_jac(x, uk)
        JW = (J * ca.repmat(W, 1, nu)).T
        dz = -ca.solve(JW @ J + GN_DAMPING * ca.SX.eye(nu), JW @ r)
        uk = ca.fmin(ca.fmax(uk + ca.DM(half) * dz, lo), hi)
    return backup_from_expression(m, uk, name=name)


def backup_check_function(plant: Model, backup: BackupPolicy, horizon: int,
                          rest_scale: Sequence[float] | np.ndarray | None = None) -> ca.Function:
    """(x1, scene) -> (min_margin, x_final, rest_rate): roll the backup out from x1 for
    ``horizon`` steps (controls clipped to the box) and return the smallest margin over x1 and
    the ``horizon`` rollout states, the last state x_H, and the rate of one more backup step,
    max_i |x_{H+1,i} - x_{H,i}| / (dt rest_scale[i]) (``rest_scale``: one rate unit per state,
    inf ignores a state; default 1 each). One fold over the horizon. With moving circles in the
    scene (a layout with moving slots) each state's margins see them where they are predicted
    at its time: x1 at dt, the j-th rollout state at (j + 1) dt (c + v t)."""
    n, ns = plant.nx, plant.n_scene
    integer("horizon", horizon, 1, MAX_HORIZON)
    scale = np.ones(n) if rest_scale is None else np.asarray(
        _rate_units("rest_scale", rest_scale, n))
    f = ca.Function("f", [plant.x, plant.u], [plant.x_next])
    h = ca.Function("h", [plant.x, plant.scene], [plant.h])
    x = ca.SX.sym("x", n)
    u = ca.fmin(ca.fmax(backup.function(x), plant.u_min), plant.u_max)
    bstep = ca.Function("backup_step", [x], [f(x, u)])
    carry, s = ca.SX.sym("carry", n + 1), ca.SX.sym("scene", ns)
    xn = bstep(carry[:n])
    step = ca.Function("backup_fold_step", [carry, s],
                       [ca.vertcat(xn, ca.fmin(carry[n], ca.mmin(h(xn, s))))])
    folded = step.fold(horizon)
    x1, sc = ca.SX.sym("x1", n), ca.SX.sym("scene", ns)
    if predicts(plant):  # x1 at dt from now, rollout state j at (j + 2) dt
        s1 = scene_sx_at(plant, sc, plant.dt)
        scenes = ca.horzcat(*(scene_sx_at(plant, sc, (j + 2) * plant.dt)
                              for j in range(horizon)))
    else:
        s1, scenes = sc, ca.repmat(sc, 1, horizon)
    cT = folded(ca.vertcat(x1, ca.mmin(h(x1, s1))), scenes)
    xH = cT[:n]
    inv = ca.DM(np.where(np.isinf(scale), 0.0, 1.0 / (plant.dt * scale)))
    rate = ca.mmax(ca.fabs(bstep(xH) - xH) * inv)
    return ca.Function("backup_check", [x1, sc], [cT[n], xH, rate], ["x1", "scene"],
                       ["min_margin", "x_final", "rest_rate"])


class BackupCheck(NamedTuple):
    """One backup check: the smallest margin over x1 and the rollout, the rollout's last
    state, and its final rate (see :func:`backup_check_function`)."""

    min_margin: float
    x_final: np.ndarray
    rest_rate: float


@dataclass(frozen=True)
class GatekeeperState:
    inner: object  # the inner controller's state
    rest_checked: bool = False  # the start check (Gatekeeper.check_backup_rests) has run


@dataclass(frozen=True, kw_only=True)
class GatekeeperInfo:
    inner: object  # the inner controller's step info
    backup_used: bool  # the check refused the proposal and the backup's control was sent
    # the proposal's backup stayed safe but did not end at rest, so it was refused for that
    # alone (a step the shield would have committed to without the rest check)
    not_at_rest: bool
    backup_min_margin: float  # min margin over x1 = f(x, u_proposed) and its backup rollout
    backup_rest_rate: float  # the final rate of that rollout (GatekeeperConfig.rest_tol)
    proposed: np.ndarray  # the inner controller's control, clipped to the box
    applied: np.ndarray  # the control sent: the proposal, or the backup's
    time_s: float  # the whole step, the inner controller's included

    @property
    def samples(self) -> SampleTrajectories | None:
        """The inner step's sample trajectories (:meth:`Gatekeeper.record_samples`), or None."""
        return getattr(self.inner, "samples", None)

    @property
    def stats(self) -> StepStats:
        """The inner controller's stats with activity plus ``backup_used`` (an effect,
        :mod:`workbench.sampling.feedback.effect`: 1 when the backup's control was sent and
        differs from the proposal, 0 when it equals it, e.g. both braking at the box limit)
        and ``backup_not_at_rest`` (an event, 0/1: the proposal was refused only because its
        backup did not end at rest)."""
        changed = self.backup_used and bool(differs(self.applied, self.proposed))
        act = {"backup_used": float(changed),
               "backup_not_at_rest": float(self.not_at_rest)}
        s = getattr(self.inner, "stats", None)
        if s is None:
            return StepStats(n_samples=0, n_collision_free=0, ess=float("nan"), activity=act)
        return StepStats(n_samples=s.n_samples, n_collision_free=s.n_collision_free,
                         ess=s.ess, activity={**s.activity, **act})


def push_controls(model: Model) -> tuple[np.ndarray, np.ndarray]:
    """The two fixed controls of the start check (assumptions §8.4): a quarter and three
    quarters of the way across the box, c -+ h/2 (c the box centre, h its half-width; for a
    control unbounded on either side c = clip(0) and h = 1)."""
    lo, hi = model.u_min, model.u_max
    bounded = np.isfinite(lo) & np.isfinite(hi)
    c, h = np.clip(0.0, lo, hi), np.ones_like(lo)
    c[bounded] = 0.5 * (lo[bounded] + hi[bounded])
    h[bounded] = 0.5 * (hi[bounded] - lo[bounded])
    d = REST_PUSH_FRACTION * h
    return np.clip(c - d, lo, hi), np.clip(c + d, lo, hi)


class Gatekeeper:
    """Backup shield around ``inner`` (any controller with ``initial_state`` and
    ``step(state, x, rng)``) for the plant model ``plant`` (its physical part is used; the
    measured state is the plant's). Refuses, at the start of an episode, a backup that does not
    bring the plant to rest (:meth:`check_backup_rests`)."""

    def __init__(self, inner, plant: Model, backup: BackupPolicy,
                 config: GatekeeperConfig = GatekeeperConfig()):
        if not callable(getattr(inner, "step", None)) or not callable(
                getattr(inner, "initial_state", None)):
            raise fail("inner", type(inner).__name__,
                       "must be a controller with initial_state(x0) and step(state, x, rng)")
        if not isinstance(plant, Model):
            raise fail("plant", type(plant).__name__, "must be a workbench Model")
        if not isinstance(backup, BackupPolicy):
            raise fail("backup", type(backup).__name__, "must be a BackupPolicy "
                       "(model_braking_backup(...), braking_backup(...) or "
                       "backup_from_expression(...))")
        if not isinstance(config, GatekeeperConfig):
            raise fail("config", config, "must be a GatekeeperConfig")
        m = plant if plant.nx == plant.n_physical else physical_model(plant)
        if not m.nh:
            raise fail("plant", m.name, "has no safety margins h(x): nothing to keep safe")
        fn = backup.function
        if (fn.n_in() != 1 or fn.n_out() != 1 or fn.numel_in(0) != m.nx
                or fn.numel_out(0) != m.nu):
            raise fail("backup", backup.name,
                       f"its function must map the state ({m.nx},) to a control ({m.nu},)")
        for where, sc in (("GatekeeperConfig.rest_scale", config.rest_scale),
                          ("backup.rest_scale", backup.rest_scale)):
            if sc is not None and len(sc) != m.nx:
                raise fail(where, sc, f"needs {m.nx} entries, one per state of {m.name} "
                           f"{m.state_names}")
        self.inner, self.plant, self.backup, self.cfg = inner, m, backup, config
        self.sampler = getattr(inner, "sampler", None)
        sc = config.rest_scale if config.rest_scale is not None else backup.rest_scale
        self.rest_scale = np.ones(m.nx) if sc is None else np.asarray(sc, dtype=float)
        self.check_function = backup_check_function(m, backup, config.horizon,
                                                    self.rest_scale)
        self._check = FastFunction(self.check_function)
        self._f = FastFunction(ca.Function("f", [m.x, m.u], [m.x_next]))
        self._scene = m.scene_vector(None)

    @property
    def goal(self) -> np.ndarray | None:
        """The inner controller's goal (None when it has none)."""
        return getattr(self.inner, "goal", None)

    @property
    def scene(self) -> np.ndarray:
        """The current scene vector of the check."""
        return self._scene

    def set_scene(self, scene) -> None:
        """Check against ``scene`` from the next step on (see
        :meth:`~workbench.problem.Model.scene_vector`) and pass it to the inner controller."""
        self._scene = self.plant.scene_vector(scene)
        set_inner = getattr(self.inner, "set_scene", None)
        if set_inner is not None:
            set_inner(scene)

    def record_samples(self, k: int = 64, keep: Keep = "spread") -> None:
        """Record the inner controller's samples (its ``record_samples``; see
        :mod:`workbench.sampling.samples`): ``info.samples`` is then the inner step's."""
        rec = getattr(self.inner, "record_samples", None)
        if rec is None:
            raise fail("inner", type(self.inner).__name__,
                       "has no record_samples: it does not sample, so there is nothing to show")
        rec(k, keep)

    def backup_check(self, x1) -> BackupCheck:
        """The check of the backup rollout from x1: (min margin over x1 and the rollout, the
        rollout's last state, its final rate)."""
        m, xT, rate = self._check(as_array("x1", x1, (self.plant.nx,)), self._scene)
        return BackupCheck(float(m[0]), xT, float(rate[0]))

    def check_backup_rests(self, x0) -> float:
        """Check that the backup brings the plant to rest from a moving state: from ``x0`` (its
        first ``nx`` entries), ``REST_PUSH_STEPS`` steps of each of the two
        :func:`push_controls`, then the ``horizon``-step backup rollout must end with a rate
        <= ``rest_tol`` (assumptions §8.4). Returns the larger of the two final rates (NaN when
        ``rest_tol`` is inf: no check); raises ValueError naming the backup, the model and the
        rate when it is above ``rest_tol``."""
        m, tol = self.plant, self.cfg.rest_tol
        x0 = np.asarray(x0, dtype=float).ravel()
        if x0.size < m.nx or not np.all(np.isfinite(x0[:m.nx])):
            raise fail("x0", x0, f"the start state must be finite with (at least) {m.nx} "
                       "entries, the plant's state first")
        if tol == np.inf:  # the rest check is off
            return np.nan
        worst = 0.0
        for u in push_controls(m):
            x = x0[:m.nx]
            for _ in range(REST_PUSH_STEPS):
                x = self._f(x, u)[0]
            check = self.backup_check(x) if np.all(np.isfinite(x)) else None
            rate = np.nan if check is None else check.rest_rate
            if not rate <= tol:
                moving = ("" if check is None
                          else f", {self._fastest(check.x_final)} changing fastest")
                raise fail("backup", self.backup.name, (
                    f"does not bring {m.name} to rest: from the start state after "
                    f"{REST_PUSH_STEPS} steps of u = {np.round(u, 6).tolist()}, its "
                    f"{self.cfg.horizon}-step rollout ends moving at rate {rate:.4g} per "
                    f"second (|x_H+1 - x_H| / (dt rest_scale){moving}), above "
                    f"GatekeeperConfig.rest_tol = {tol:g}. Pass "
                    "model_braking_backup(plant) (a braking law derived from the model), a "
                    f"backup that stops {m.name}, or a longer GatekeeperConfig.horizon"))
            worst = max(worst, rate)
        return float(worst)

    def _fastest(self, xH: np.ndarray) -> str:
        """The state that the backup's step from ``xH`` changes fastest (in rest_scale units)."""
        m = self.plant
        x1 = self._f(xH, np.clip(self.backup(xH), m.u_min, m.u_max))[0]
        r = np.abs(x1 - xH) / self.rest_scale
        return m.state_names[int(np.nanargmax(r))] if np.any(np.isfinite(r)) else "no state"

    def initial_state(self, x0=None) -> GatekeeperState:
        """The inner controller's initial state; with ``x0``, after the start check
        (:meth:`check_backup_rests`; without it the first step runs it on the measured
        state)."""
        if x0 is not None:
            self.check_backup_rests(x0)
        return GatekeeperState(inner=self.inner.initial_state(x0), rest_checked=x0 is not None)

    def step(self, state: GatekeeperState, x, rng: np.random.Generator):
        t0 = time.perf_counter()
        if not isinstance(state, GatekeeperState):
            raise fail("state", type(state).__name__, "must be a GatekeeperState "
                       "(from Gatekeeper.initial_state)")
        xa = np.asarray(x, dtype=float).ravel()
        n, lo, hi = self.plant.nx, self.plant.u_min, self.plant.u_max
        if xa.size < n or not np.all(np.isfinite(xa)):
            raise fail("x", xa, f"the measured state must be finite with (at least) {n} "
                       "entries, the plant's state first")
        xp = xa[:n]
        if not state.rest_checked:
            self.check_backup_rests(xp)
        inner_state, u, info = self.inner.step(state.inner, x, rng)
        u = np.asarray(u, dtype=float).ravel()
        if u.shape != (self.plant.nu,):
            raise fail("inner control", u, f"expected {self.plant.nu} entries")
        proposed = np.clip(u, lo, hi)
        if np.all(np.isfinite(proposed)):
            m, _, rate = self.backup_check(self._f(xp, proposed)[0])
        else:
            m, rate = -np.inf, np.inf
        safe = m > self.cfg.margin
        at_rest = rate <= self.cfg.rest_tol
        use_backup = not (safe and at_rest)
        applied = np.clip(self.backup(xp), lo, hi) if use_backup else proposed
        ginfo = GatekeeperInfo(inner=info, backup_used=bool(use_backup),
                               not_at_rest=bool(safe and not at_rest), backup_min_margin=m,
                               backup_rest_rate=rate, proposed=proposed, applied=applied,
                               time_s=time.perf_counter() - t0)
        return GatekeeperState(inner=inner_state, rest_checked=True), applied, ginfo


__all__ = ["MAX_HORIZON", "BackupCheck", "BackupPolicy", "Gatekeeper", "GatekeeperConfig",
           "GatekeeperInfo", "GatekeeperState", "backup_check_function", "backup_from_expression",
           "braking_backup", "model_braking_backup", "push_controls"]

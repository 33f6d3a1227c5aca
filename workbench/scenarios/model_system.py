"""A system from any model: :func:`system_from_model` turns a user's CasADi model (its
constraints in h(x), a start and a goal state) into the :class:`~workbench.scenarios.systems.System`
record the built-in systems use, so that every registered method builds on it by name and
every study that takes a system runs on it.

Every default it derives is recorded with where it came from (``System.origins``); a value
passed by the caller is used as given and recorded as such. The rules (assumptions §8.3):

- horizon T = round(2 s / dt), within [20, 100];
- state scales s_i: |goal_i - start_i| where the goal changes state i (one scale, the norm of
  the difference, for the position coordinates), else the spread (standard deviation over 64
  seeded rollouts of T steps, each holding one random control of the box) of state i; floored
  at 1e-3 of the largest scale;
- goal costs Q_i = 1 / s_i^2 on the states the goal changes, 0.1 / s_i^2 on the others (rates,
  like the built-in systems' weights), terminal S = 10 Q, barrier-state weight
  q_beta = 0.01 mean(Q);
- sampler sigma_j = a quarter of control j's range; lambda = :data:`LAMBDA_SHARE` times the
  cost spread of the best 1 % of the first batch from the start, the median over
  :data:`LAMBDA_DRAWS` draws (:func:`calibrate_lambda`);
- disturbed states: those the controls move directly (rows of dF/du at the start whose largest
  entry is at least a tenth of the largest), the level scaled by (authority / 5)^2, authority
  the mean rate at which full control moves a disturbed state (5: the double integrator's
  5 m/s^2, in whose units levels are given);
- feedback (tracking) weights Q_i = 5e4 / s_i^2, R_j = (5 / half-range_j)^2;
- goal radius: a tenth of the start's distance to the goal;
- the gatekeeper's backup: :func:`~workbench.sampling.methods.gatekeeper.model_braking_backup`
  (the gatekeeper refuses it by name if it does not bring the model to rest).
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import casadi as ca
import numpy as np

from workbench.problem.models import Model
from workbench.problem.obstacles import Circle
from workbench.sampling.feedback import FeedbackWeights
from workbench.sampling.methods.gatekeeper import model_braking_backup
from workbench.sampling.mppi import MPPI, MPPIConfig
from workbench.sampling.planning import full_state
from workbench.sampling.problem import goal_costs
from workbench.scenarios.systems import SYSTEMS, System
from workbench.validation import as_array, fail, integer, real

LAMBDA_SHARE = 0.01  # assumptions §8.3: lambda per cost spread of the first batch's best 1 %
LAMBDA_DRAWS = 8  # first batches whose median spread sets lambda
DI_AUTHORITY = 5.0  # m/s^2: the double integrator's control authority (levels' units)
HORIZON_S = 2.0  # s


@dataclass(frozen=True, eq=False)
class ModelScene:
    """The scene of a system built from a model: its start and goal states, its time step and
    its own constraints (the circles of ``obstacles()``; others live in the model's h)."""

    start: np.ndarray
    goal: np.ndarray
    dt: float
    circles: tuple[Circle, ...] = ()
    u_limit: None = None

    def obstacles(self) -> tuple[Circle, ...]:
        return self.circles


@dataclass(frozen=True)
class _Own:
    """The model factory of a model system: the model itself, on its own scene only."""

    model: Model = field(repr=False)

    def __call__(self, *, obstacles, dt, u_limit, scene_capacity, runtime_obstacles) -> Model:
        m = self.model
        if tuple(obstacles) != tuple(m.obstacles):
            raise fail("scene", obstacles, f"a system built from the model {m.name!r} runs on "
                       "its own constraints; maps of circles are for the map systems")
        if dt != m.dt:
            raise fail("scene.dt", dt, f"must be the model's dt = {m.dt}")
        if scene_capacity not in (None, m.scene_capacity):
            raise fail("scene_capacity", scene_capacity,
                       f"the model {m.name!r} has {m.scene_capacity} run-time slots")
        if not runtime_obstacles and m.scene_capacity:
            raise fail("runtime_obstacles", runtime_obstacles,
                       f"the model {m.name!r} has run-time slots; it is used as written")
        return m


@dataclass(frozen=True)
class _AtState:
    """state_at of a model system: the scene's points are the model's full states."""

    nx: int

    def __call__(self, point, heading: float = 0.0) -> np.ndarray:
        return as_array("state", point, (self.nx,))


def _derived_backup(plant, gain):
    """The gatekeeper's backup of a model system given none: the braking law derived from the
    model (the gatekeeper checks at its start that it stops the plant, and refuses it by name
    otherwise; ``gain`` does not apply to it)."""
    if gain is not None:
        raise fail("braking_gain", gain, "the derived braking law has no gain; leave it unset "
                   "or pass system_from_model(..., backup=f) with a law that takes one")
    return model_braking_backup(plant)


def _step(model: Model) -> ca.Function:
    return ca.Function("F", [model.x, model.u], [model.x_next])


def _rest_control(model: Model) -> np.ndarray:
    lo, hi = np.asarray(model.u_min, float), np.asarray(model.u_max, float)
    return np.clip(np.zeros(model.nu), lo, hi)


def state_scales(model: Model, start: np.ndarray, goal: np.ndarray, horizon: int,
                 sigma=None, rollouts: int = 64, seed: int = 0) -> np.ndarray:
    """Per-state scale s_i (see the module docstring): |goal_i - start_i| (the norm of the
    difference over the position coordinates, when the model has them) where that is > 0,
    else the spread of seeded constant-control rollouts (controls uniform in the box; an
    unbounded side at 2 ``sigma``); floored at 1e-3 of the largest."""
    lo, hi = np.asarray(model.u_min, float), np.asarray(model.u_max, float)
    if sigma is not None:
        two = 2.0 * np.asarray(sigma, float)
        lo, hi = np.where(np.isfinite(lo), lo, -two), np.where(np.isfinite(hi), hi, two)
    F = _step(model).map(rollouts)
    rng = np.random.default_rng(seed)
    U = rng.uniform(lo[:, None], hi[:, None], size=(model.nu, rollouts))
    X = np.repeat(start[:, None], rollouts, axis=1)
    for _ in range(horizon):
        X = np.asarray(F(X, U))
        if not np.all(np.isfinite(X)):
            raise fail("model", model.name, "a rollout within the control box left the finite "
                       f"numbers within {horizon} steps; pass state_scale")
    d = np.abs(goal - start)
    if model.position is not None:  # one scale for the position coordinates: isotropic
        idx = list(model.position)
        d[idx] = np.linalg.norm(d[idx])
    s = np.where(d > 0, d, X.std(axis=1))
    if not np.any(s > 0):
        raise fail("model", model.name, "no state moves under the controls and start equals "
                   "goal; pass state_scale")
    return np.maximum(s, 1e-3 * s.max())


def authority(model: Model, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rows the controls move directly, every state's rate under full control) at ``x``:
    rows of dF/du whose largest entry is at least a tenth of the largest; rate of state i
    ||dF_i/du * half-range|| / dt."""
    B = np.asarray(ca.Function("B", [model.x, model.u],
                               [ca.jacobian(model.x_next, model.u)])(x, _rest_control(model)))
    half = 0.5 * (np.asarray(model.u_max, float) - np.asarray(model.u_min, float))
    big = np.abs(B).max(axis=1)
    rows = np.flatnonzero(big >= 0.1 * big.max()) if big.max() > 0 else np.zeros(0, int)
    return rows, np.linalg.norm(B * half, axis=1) / model.dt


def first_batches(problem, goal: np.ndarray, x0: np.ndarray, config: MPPIConfig,
                  seeds) -> list:
    """The sampler's first batch from ``x0`` (zero plan) for each seed of ``seeds``, drawn by
    one controller."""
    ctrl = MPPI(problem, goal, config)
    xb = full_state(problem, x0, ctrl.consts.scene)
    U = ctrl.initial_state().U
    return [ctrl.sampler.mppi(xb, U, config.n_samples, ctrl.consts,
                              int(np.random.default_rng(seed).integers(0, 2**63)))
            for seed in seeds]


def calibrate_lambda(problem, goal: np.ndarray, x0: np.ndarray, config: MPPIConfig,
                     draws: int = LAMBDA_DRAWS) -> float:
    """lambda = :data:`LAMBDA_SHARE` times the cost spread of the best 1 % of a first batch
    from ``x0`` (its 1 % quantile minus its minimum, over the finite costs), the median over
    ``draws`` seeded batches (zero plan; seeds 0, 1, ...): the weights then fall by e^-100
    across that best percent, so the update follows a handful of the best samples, as the
    hand-tuned built-in systems do. One batch's best percent varies threefold between draws
    on the two-link arm of the examples; the median does not."""
    spreads = []
    for batch in first_batches(problem, goal, x0, config, range(integer("draws", draws, 1))):
        S = np.sort(np.asarray(batch.S, float))
        S = S[np.isfinite(S)]
        if S.size >= 2:
            spreads.append(float(np.quantile(S, 0.01) - S[0]))
    spread = float(np.median(spreads)) if spreads else float("nan")
    if not spread > 0:
        raise fail("lam", None, "the first batches from the start have no spread of finite "
                   "costs among their best samples; pass lam")
    return LAMBDA_SHARE * spread


def system_from_model(model: Model, start, goal, *, name: str | None = None,
                      label: str | None = None, disturbed: Sequence[str] | None = None,
                      Q=None, S=None, sigma=None, lam: float | None = None,
                      q_beta: float | None = None, horizon: int | None = None,
                      level_scale: float | None = None,
                      feedback_weights: FeedbackWeights | None = None,
                      goal_radius: float | None = None, state_scale=None,
                      backup: Callable | None = None, entry: str | None = None) -> System:
    """The system of ``model`` from ``start`` to ``goal`` (physical states of the model, both
    with every margin of h > 0). Each keyword left None is derived from the model (module
    docstring) and recorded in ``System.origins`` with its rule; a value given is used as is.
    ``entry``: ``"module:function"`` (or ``"path/file.py:function"``) that returns this system,
    for studies run by worker processes and for configs. Register the result with
    :func:`~workbench.scenarios.systems.register_system` to build methods by name."""
    if not isinstance(model, Model):
        raise fail("model", type(model).__name__, "must be a workbench Model "
                   "(Model.from_expressions)")
    if model.n_physical != model.nx:
        raise fail("model", model.name, "must be the plain model, not a barrier-embedded one")
    if model.nh == 0:
        raise fail("model.h", "none", "a system needs constraints h(x) > 0 for the safe "
                   "methods to keep; pass h to Model.from_expressions")
    n, origins = model.nx, []
    x0 = as_array("start", start, (n,))
    xg = as_array("goal", goal, (n,))
    lo, hi = np.asarray(model.u_min, float), np.asarray(model.u_max, float)

    def note(field_name: str, given, rule: str) -> None:
        origins.append((field_name, "given" if given is not None else rule))

    T = (integer("horizon", horizon, 1) if horizon is not None
         else int(np.clip(round(HORIZON_S / model.dt), 20, 100)))
    note("horizon", horizon, f"round({HORIZON_S:g} s / dt) within [20, 100]")
    if sigma is None:
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise fail("sigma", None, f"the model {model.name!r} has an unbounded control: "
                       "pass sigma (one standard deviation per control)")
        sig = 0.25 * (hi - lo)
    else:
        sig = as_array("sigma", sigma, (model.nu,))
    note("sigma", sigma, "a quarter of each control's range")
    if state_scale is not None:
        s = as_array("state_scale", state_scale, (n,))
        if np.any(s <= 0):
            raise fail("state_scale", s, "must be numbers > 0")
    else:
        s = state_scales(model, x0, xg, T, sigma=sig)
    note("state_scale", state_scale, "the goal's change of the state (one norm over the "
         "position coordinates), else its spread under random controls over the horizon")
    goal_states = np.abs(xg - x0) > 0
    if model.position is not None:
        goal_states[list(model.position)] = np.any(goal_states[list(model.position)])
    Qv = (np.where(goal_states, 1.0, 0.1) / s**2) if Q is None else as_array("Q", Q, (n,))
    note("Q", Q, "1 / state_scale^2 on the states the goal changes, 0.1 / state_scale^2 on "
         "the others")
    Sv = 10.0 * Qv if S is None else as_array("S", S, (n,))
    note("S", S, "10 Q")
    qb = 0.01 * float(np.mean(Qv)) if q_beta is None else real("q_beta", q_beta, 0.0)
    note("q_beta", q_beta, "0.01 mean(Q)")
    rows, rates = authority(model, x0)
    if disturbed is None:
        if not rows.size:
            raise fail("disturbed", None, f"the controls of {model.name!r} move no state at "
                       "the start; pass disturbed (state names)")
        dist = tuple(model.state_names[i] for i in rows)
    else:
        if isinstance(disturbed, str) or not all(d in model.state_names for d in disturbed):
            raise fail("disturbed", disturbed, f"must be state names of {model.state_names}")
        dist = tuple(disturbed)
    note("disturbed", disturbed, "the states the controls move directly")
    if level_scale is None:
        a = rates[[model.state_names.index(d) for d in dist]]
        if not np.all(np.isfinite(a)) or not a.mean() > 0:
            raise fail("level_scale", None, f"the controls do not move the disturbed states "
                       f"{dist} at the start; pass level_scale")
        ls = float((a.mean() / DI_AUTHORITY) ** 2)
    else:
        ls = real("level_scale", level_scale, 0.0, strict=True)
    note("level_scale", level_scale, "(control authority on the disturbed states / 5)^2")
    if feedback_weights is None:
        half = 0.5 * (hi - lo)
        fw = FeedbackWeights(Q=tuple(5e4 / s**2),
                             R=tuple((5.0 / half) ** 2 if np.all(np.isfinite(half))
                                     else np.ones(model.nu)))
    else:
        fw = feedback_weights
    note("feedback_weights", feedback_weights, "Q = 5e4 / state_scale^2, "
         "R = (5 / half-range)^2")
    if lam is None:
        from workbench.problem.barrier import BarrierOptions, embed_barrier
        problem = goal_costs(embed_barrier(model, BarrierOptions()), Q=Qv, S=Sv, q_beta=qb)
        lam_v = calibrate_lambda(problem, xg, x0,
                                 MPPIConfig(sigma=tuple(sig), horizon=T))
    else:
        lam_v = real("lam", lam, 0.0, strict=True)
    note("lam", lam, f"{LAMBDA_SHARE:g} x the cost spread of the best 1 % of the first batch "
         f"(median over {LAMBDA_DRAWS} draws)")
    sysm_name = name or model.name
    dist0 = float(np.linalg.norm((xg - x0) / s)) if model.position is None else float(
        np.linalg.norm(xg[list(model.position)] - x0[list(model.position)]))
    gr = 0.1 * dist0 if goal_radius is None else real("goal_radius", goal_radius, 0.0,
                                                      strict=True)
    note("goal_radius", goal_radius, "a tenth of the start's distance to the goal")
    backup_law = _derived_backup if backup is None else backup
    note("backup", backup, "model_braking_backup: the control that makes the state move least "
         "over a two-step lookahead (the gatekeeper checks that it stops the model)")
    scene = ModelScene(x0, xg, model.dt, tuple(model.obstacles))
    return System(name=sysm_name, label=label or sysm_name.replace("_", " "),
                  model=_Own(model), state_at=_AtState(n), Q=tuple(Qv), S=tuple(Sv),
                  sigma=tuple(sig), lam=lam_v, q_beta=qb, disturbed=dist, level_scale=ls,
                  state_names=tuple(model.state_names),
                  backup=backup_law, feedback_weights=fw, horizon=T, goal_radius=gr,
                  scene=scene, state_scale=tuple(s), origins=tuple(origins), entry=entry)


def load_entry(entry: str) -> System:
    """The system an ``entry`` returns: ``"package.module:function"`` (imported) or
    ``"path/to/file.py:function"`` (loaded from the file, relative to the working directory);
    the function takes no arguments and returns a :class:`System`. It is registered under its
    name unless a system of that name is registered already (then that one must come from the
    same entry)."""
    if not isinstance(entry, str) or entry.count(":") != 1:
        raise fail("system", entry, "must be a registered system name or 'module:function' "
                   "/ 'path/file.py:function'")
    where, func = entry.split(":")
    if where.endswith(".py"):
        path = Path(where)
        if not path.is_file():
            raise fail("system", entry, f"the file {path} does not exist (relative to "
                       f"{Path.cwd()})")
        mod_name = f"workbench_user_{path.stem}"
        module = sys.modules.get(mod_name)
        if module is None or getattr(module, "__file__", None) != str(path.resolve()):
            spec = importlib.util.spec_from_file_location(mod_name, path.resolve())
            module = importlib.util.module_from_spec(spec)  # type: ignore[arg-type]
            sys.modules[mod_name] = module
            spec.loader.exec_module(module)  # type: ignore[union-attr]
    else:
        try:
            module = importlib.import_module(where)
        except ImportError as e:
            raise fail("system", entry, f"cannot import {where!r} ({e})") from None
    fn = getattr(module, func, None)
    if not callable(fn):
        raise fail("system", entry, f"{where} has no function {func!r}")
    sysm = fn()
    if not isinstance(sysm, System):
        raise fail("system", entry, f"{func}() must return a System (system_from_model), "
                   f"not {type(sysm).__name__}")
    if sysm.entry is None:
        from dataclasses import replace
        sysm = replace(sysm, entry=entry)
    known = SYSTEMS.get(sysm.name)
    if known is None:
        SYSTEMS.register(sysm)
    elif known.entry != sysm.entry:
        raise fail("system", entry, f"returns a system named {sysm.name!r}, but a system of "
                   "that name is registered already")
    return SYSTEMS[sysm.name]


def resolve_system(name_or_entry: str) -> System:
    """A registered system by name, or the system of a ``module:function`` entry
    (:func:`load_entry`)."""
    if isinstance(name_or_entry, str) and ":" in name_or_entry:
        return load_entry(name_or_entry)
    return SYSTEMS.named(name_or_entry)


__all__ = ["LAMBDA_SHARE", "ModelScene", "authority", "calibrate_lambda", "first_batches",
           "load_entry", "resolve_system", "state_scales", "system_from_model"]

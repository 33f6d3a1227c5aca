"""Closed-loop simulation on the true plant with the disturbance models of SPEC 2.3."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Literal, Protocol

import casadi as ca
import numpy as np

from workbench.codegen.fastcall import FastFunction
from workbench.problem.models import Model
from workbench.validation import fail, integer, one_of, real

DisturbanceModel = Literal["velocity_variance", "velocity_std", "white_noise", "kick"]
DISTURBANCE_MODELS: tuple[str, ...] = ("velocity_variance", "velocity_std", "white_noise", "kick")


@dataclass(frozen=True)
class Disturbance:
    """Plant disturbance w on some states (SPEC 2.3): the velocities of the double integrator.

    velocity_variance (default): w = dt [0, 0, xi], xi ~ N(0, level I) (level = variance);
    velocity_std: level is the std, xi ~ N(0, level^2 I);
    white_noise: w = sqrt(dt) sqrt(level) xi01 on the disturbed states;
    kick: w = [0, 0, xi] without the dt factor, xi ~ N(0, level I).

    velocity_index: the disturbed state indices; None (default) takes them from the plant in
    :func:`closed_loop` (:func:`disturbed_states`: the velocities of the double integrator, the
    positions of the single integrator).
    """

    level: float = 0.0
    model: DisturbanceModel = "velocity_variance"
    velocity_index: tuple[int, ...] | None = None

    def __post_init__(self) -> None:
        real("Disturbance.level", self.level, 0.0)
        one_of("Disturbance.model", self.model, DISTURBANCE_MODELS)
        if self.velocity_index is not None:
            idx = self.velocity_index
            allowed = ("must be a non-empty tuple of distinct state indices >= 0, or None "
                       "(take them from the plant)")
            if not isinstance(idx, tuple | list) or not idx:
                raise fail("Disturbance.velocity_index", idx, allowed)
            ints = tuple(integer("Disturbance.velocity_index", i, 0) for i in idx)
            if len(set(ints)) != len(ints):
                raise fail("Disturbance.velocity_index", idx, allowed)
            object.__setattr__(self, "velocity_index", ints)

    def indices(self, plant: Model) -> tuple[int, ...]:
        """The disturbed states for ``plant``: the given ones (checked) or the plant's own."""
        if self.velocity_index is None:
            return disturbed_states(plant)
        bad = [i for i in self.velocity_index if i >= plant.nx]
        if bad:
            raise fail("Disturbance.velocity_index", self.velocity_index,
                       f"index {bad[0]} is out of range for {plant.name} with {plant.nx} states")
        return self.velocity_index

    def sample(self, nx: int, dt: float, rng: np.random.Generator,
               index: tuple[int, ...] | None = None) -> np.ndarray:
        idx = list(index if index is not None else self.velocity_index or ())
        if not idx:
            raise fail("Disturbance.velocity_index", self.velocity_index,
                       "give the disturbed state indices (closed_loop takes them from the plant)")
        w = np.zeros(nx)
        xi = rng.standard_normal(len(idx))
        if self.model == "velocity_variance":
            w[idx] = dt * np.sqrt(self.level) * xi
        elif self.model == "velocity_std":
            w[idx] = dt * self.level * xi
        elif self.model == "white_noise":
            w[idx] = np.sqrt(dt) * np.sqrt(self.level) * xi
        else:
            w[idx] = np.sqrt(self.level) * xi
        return w


def disturbed_states(plant: Model) -> tuple[int, ...]:
    """The physical states a plant disturbance acts on: those the control drives directly.

    A matched disturbance enters where the control enters. Per physical state i, the largest
    |dF_i/du| over seeded random states and controls; the states within a factor 2 of the
    largest are disturbed. Double integrator: the velocities (the position rows are 0 with
    Euler and dt^2/2 against dt with zero-order hold); single integrator: the positions.
    """
    n = plant.n_physical
    jac = ca.Function("dFdu", [plant.x, plant.u], [ca.jacobian(plant.x_next[:n], plant.u)])
    rng = np.random.default_rng(20261123)
    lo = np.where(np.isfinite(plant.u_min), plant.u_min, -1.0)
    hi = np.where(np.isfinite(plant.u_max), plant.u_max, 1.0)
    gain = np.zeros(n)
    for _ in range(8):
        J = np.abs(np.asarray(jac(rng.normal(0.0, 1.0, plant.nx), rng.uniform(lo, hi))))
        gain = np.maximum(gain, np.where(np.isfinite(J), J, 0.0).max(axis=1))
    if not gain.max() > 0:
        raise fail("plant", plant.name, "no state depends on u; give "
                   "Disturbance(velocity_index=...) to choose the disturbed states")
    return tuple(int(i) for i in np.flatnonzero(gain >= 0.5 * gain.max()))


class Controller(Protocol):
    def initial_state(self, x0: np.ndarray): ...

    def step(self, state, x: np.ndarray, rng: np.random.Generator): ...


@dataclass(frozen=True)
class Episode:
    """Per-step records of one closed-loop run. X (n+1, nx), U (n, nu)."""

    X: np.ndarray
    U: np.ndarray
    crashed: bool
    crash_step: int | None
    min_margin: float
    step_time_s: np.ndarray
    infos: tuple = field(default=(), repr=False)


def closed_loop(controller, plant: Model, x0, steps: int, rng_controller: np.random.Generator,
                rng_plant: np.random.Generator, disturbance: Disturbance = Disturbance(),
                keep_infos: bool = True) -> Episode:
    """Run ``controller`` on the plant x+ = F(x, u) + w for ``steps`` steps; stop at a crash
    (min_i h_i <= 0 on the true plant). w acts on ``disturbance.indices(plant)``."""
    integer("steps", steps, 1)
    x = np.asarray(x0, dtype=float)
    if x.shape != (plant.nx,) or not np.all(np.isfinite(x)):
        raise fail("x0", x0, f"must be {plant.nx} finite numbers")
    f = FastFunction(ca.Function("plant", [plant.x, plant.u], [plant.x_next]))
    disturbed = disturbance.indices(plant)
    margins = plant.margins if plant.nh else None
    state = controller.initial_state(x)
    X, U, times, infos = [x.copy()], [], [], []
    crashed, crash_step = False, None
    min_h = float(np.min(margins(x))) if margins else np.inf
    for k in range(steps):
        t0 = time.perf_counter()
        state, u, info = controller.step(state, x, rng_controller)
        times.append(time.perf_counter() - t0)
        u = np.clip(u, plant.u_min, plant.u_max)
        x = f(x, u)[0] + disturbance.sample(plant.nx, plant.dt, rng_plant, disturbed)
        X.append(x.copy())
        U.append(u)
        if keep_infos:
            infos.append(info)
        if margins is not None:
            h = float(np.min(margins(x)))
            min_h = min(min_h, h)
            if h <= 0:
                crashed, crash_step = True, k + 1
                break
    return Episode(X=np.array(X), U=np.array(U), crashed=crashed, crash_step=crash_step,
                   min_margin=min_h, step_time_s=np.array(times), infos=tuple(infos))

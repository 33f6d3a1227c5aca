"""Closed-loop simulation on the true plant with the disturbance models of SPEC 2.3."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Literal, Protocol

import casadi as ca
import numpy as np

from workbench.fastcall import FastFunction
from workbench.models import Model
from workbench.validation import fail, one_of, positive

DisturbanceModel = Literal["velocity_variance", "velocity_std", "white_noise", "kick"]
DISTURBANCE_MODELS: tuple[str, ...] = ("velocity_variance", "velocity_std", "white_noise", "kick")


@dataclass(frozen=True)
class Disturbance:
    """Plant disturbance on the velocity states (double integrator), SPEC 2.3.

    velocity_variance (default): w = dt [0, 0, xi], xi ~ N(0, level I) (level = variance);
    velocity_std: level is the std, xi ~ N(0, level^2 I);
    white_noise: w = sqrt(dt) sqrt(level) xi01 on the velocities;
    kick: w = [0, 0, xi] without the dt factor, xi ~ N(0, level I).
    """

    level: float = 0.0
    model: DisturbanceModel = "velocity_variance"
    velocity_index: tuple[int, int] = (2, 3)

    def __post_init__(self) -> None:
        positive("Disturbance.level", self.level, allow_zero=True)
        one_of("Disturbance.model", self.model, DISTURBANCE_MODELS)

    def sample(self, nx: int, dt: float, rng: np.random.Generator) -> np.ndarray:
        w = np.zeros(nx)
        xi = rng.standard_normal(2)
        if self.model == "velocity_variance":
            w[list(self.velocity_index)] = dt * np.sqrt(self.level) * xi
        elif self.model == "velocity_std":
            w[list(self.velocity_index)] = dt * self.level * xi
        elif self.model == "white_noise":
            w[list(self.velocity_index)] = np.sqrt(dt) * np.sqrt(self.level) * xi
        else:
            w[list(self.velocity_index)] = np.sqrt(self.level) * xi
        return w


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
    (min_i h_i <= 0 on the true plant)."""
    if not isinstance(steps, int) or steps < 1:
        raise fail("steps", steps, "must be an integer >= 1")
    x = np.asarray(x0, dtype=float)
    if x.shape != (plant.nx,) or not np.all(np.isfinite(x)):
        raise fail("x0", x0, f"must be {plant.nx} finite numbers")
    f = FastFunction(ca.Function("plant", [plant.x, plant.u], [plant.x_next]))
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
        x = f(x, u)[0] + disturbance.sample(plant.nx, plant.dt, rng_plant)
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
    return Episode(np.array(X), np.array(U), crashed, crash_step, min_h, np.array(times),
                   tuple(infos))

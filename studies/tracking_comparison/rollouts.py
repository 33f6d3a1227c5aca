"""Monte Carlo closed loops, vectorised over rollouts (assumptions §5.6, §6.3, §6.4), and their
metrics.

Shapes: noise (N, T, nu), states (N, T+1, nx). The plant is the model's own discrete map; for a
linear model (the double integrator) it runs in NumPy as x' = A x + B u + c, with A, B, c read
from the CasADi expression and linearity checked. Margins and barrier states are the model's
CasADi expressions, mapped over the N rollouts in one call per step.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import casadi as ca
import numpy as np

from studies.tracking_comparison.config import METHODS
from workbench.filters.ecbf import ECBFFilter
from workbench.problem.models import Model
from workbench.study import seed_sequence
from workbench.validation import fail


def stream_key(method: str, seed_index: int) -> tuple[int, int]:
    """The (method, seed) words of a task's noise stream: SeedSequence(root, spawn_key=...) is
    SeedSequence(root).spawn per method, then per seed. It depends only on (root seed, method,
    seed index), not on the task list, the order or the worker count; different sample counts,
    noise levels and variants share the same draws (prefixes)."""
    return METHODS.index(method), seed_index


def noise_generator(root_seed: int, method: str, seed_index: int) -> np.random.Generator:
    return np.random.default_rng(seed_sequence(root_seed, stream_key(method, seed_index)))


def control_noise(rng: np.random.Generator, n: int, T: int, nu: int, std: float) -> np.ndarray:
    """i.i.d. N(0, std^2 I) control-channel noise (n, T, nu)."""
    return std * rng.standard_normal((n, T, nu))


@dataclass(frozen=True, eq=False)
class LinearDynamics:
    """x_{k+1} = A x_k + B u_k + c, read exactly from a model whose map is affine in (x, u)."""

    A: np.ndarray
    B: np.ndarray
    c: np.ndarray

    @classmethod
    def from_model(cls, model: Model) -> LinearDynamics:
        z = ca.vertcat(model.x, model.u)
        jac = ca.jacobian(model.x_next, z)
        if ca.depends_on(jac, z):
            raise fail("model.x_next", model.name, "the NumPy rollout needs a map affine in x, u")
        J = np.asarray(ca.Function("J", [z], [ca.densify(jac)])(np.zeros(z.numel())))
        c = np.asarray(ca.Function("c", [model.x, model.u], [model.x_next])(
            np.zeros(model.nx), np.zeros(model.nu))).ravel()
        return cls(A=J[:, : model.nx], B=J[:, model.nx:], c=c)

    def step(self, X: np.ndarray, U: np.ndarray) -> np.ndarray:
        return X @ self.A.T + U @ self.B.T + self.c


def batched(fn: ca.Function, n: int) -> Callable[[np.ndarray], np.ndarray]:
    """(n, n_in) -> (n, n_out) for a single-input, single-output column Function."""
    mapped = fn.map(n)
    n_out = fn.size1_out(0)

    def call(X: np.ndarray) -> np.ndarray:
        return np.asarray(mapped(X.T)).T.reshape(n, n_out)

    return call


def margins_function(model: Model) -> ca.Function:
    """x -> h(x) in the model's own scene."""
    h = ca.substitute(model.h, model.scene, model.scene_value)
    return ca.Function("h", [model.x], [ca.densify(h)])


def lift_function(embedded: Model) -> ca.Function:
    """Physical state -> [x; beta] with beta = B(h(x)) (crash rule and cap included), in the
    model's own scene."""
    xp = embedded.x[: embedded.n_physical]
    lift = ca.substitute(embedded.lift_expr, embedded.scene, embedded.scene_value)
    return ca.Function("lift", [xp], [ca.densify(lift)])


class StepClock:
    """Wall and process CPU seconds of each timed section (``start`` .. ``stop``)."""

    def __init__(self) -> None:
        self.wall: list[float] = []
        self.cpu: list[float] = []
        self._t = (0.0, 0.0)

    def start(self) -> None:
        self._t = (time.perf_counter(), time.process_time())

    def stop(self) -> None:
        self.wall.append(time.perf_counter() - self._t[0])
        self.cpu.append(time.process_time() - self._t[1])


def feedback_rollouts(dyn: LinearDynamics, x0, Xbar, Ubar, K, noise, u_min, u_max,
                      lift: ca.Function | None = None,
                      clock: StepClock | None = None) -> np.ndarray:
    """u_k = clip(ubar_k + K_k (xact_k - xbar_k) + eps_k); xact includes the actual barrier
    state when ``lift`` is given (BaS, assumptions §5.6). Returns physical states (N, T+1, n).
    ``clock`` times the control computation of each step (not the plant's step)."""
    N, T, _ = noise.shape
    n = dyn.A.shape[0]
    X = np.empty((N, T + 1, n))
    X[:, 0] = x0
    lift_n = batched(lift, N) if lift is not None else None
    clock = clock or StepClock()
    for k in range(T):
        xa = X[:, k]
        clock.start()
        full = lift_n(xa) if lift_n is not None else xa
        u = np.clip(Ubar[k] + (full - Xbar[k]) @ K[k].T + noise[:, k], u_min, u_max)
        clock.stop()
        X[:, k + 1] = dyn.step(xa, u)
    return X


@dataclass(frozen=True)
class ECBFRollouts:
    """States (N, T+1, nx) and per-rollout counts of infeasible / fallback / OSQP steps."""

    X: np.ndarray
    infeasible_steps: np.ndarray
    fallback_steps: np.ndarray
    qp_steps: np.ndarray


def ecbf_rollouts(dyn: LinearDynamics, x0, Xbar, Ubar, K, noise, filt: ECBFFilter,
                  noise_after: bool = False, clock: StepClock | None = None) -> ECBFRollouts:
    """u_ref = ubar + K (x - xbar) + eps (noise before the filter, assumptions §6.3), u = ECBF-QP;
    with ``noise_after`` the plant gets clip(ECBF-QP(ubar + K (x - xbar)) + eps) instead.
    ``clock`` times the control computation of each step (feedback and filter)."""
    N, T, _ = noise.shape
    X = np.empty((N, T + 1, dyn.A.shape[0]))
    X[:, 0] = x0
    infeasible, fallback, qp = (np.zeros(N, dtype=np.int64) for _ in range(3))
    clock = clock or StepClock()
    for k in range(T):
        clock.start()
        u_ref = Ubar[k] + (X[:, k] - Xbar[k]) @ K[k].T
        res = filt.filter_batch(X[:, k], u_ref if noise_after else u_ref + noise[:, k])
        clock.stop()
        infeasible += res.infeasible
        fallback += res.fallback_used
        qp += res.qp_solved
        u = np.clip(res.u + noise[:, k], filt.u_min, filt.u_max) if noise_after else res.u
        X[:, k + 1] = dyn.step(X[:, k], u)
    return ECBFRollouts(X, infeasible, fallback, qp)


def rollout_metrics(X: np.ndarray, margins: ca.Function, target_position,
                    position: tuple[int, int] = (0, 1)) -> tuple[np.ndarray, np.ndarray]:
    """min over k = 0..T and i of h_i(x_k), and final distance to the target position, (N,)."""
    N, T1, n = X.shape
    H = batched(margins, N * T1)(X.reshape(N * T1, n)).reshape(N, T1, -1)
    final = np.linalg.norm(X[:, -1, list(position)] - np.asarray(target_position), axis=1)
    return H.min(axis=(1, 2)), final

"""Paper Fig. 4: nominal vs feedback samples of one SAIS batch (limits +-50, velocity variance
5000). SA-RMPPI runs on the plant; the SAIS batch of the first step (>= ``FIRST``) whose
nominal state differs from the real one is kept; its sampled controls are rolled through the
plant model (the real samples from the real state with their applied, feedback-corrected
controls; the nominal samples from the nominal state)."""

from __future__ import annotations

import casadi as ca
import numpy as np

from workbench.scenarios.navigation import NavigationSetup
from workbench.sim import Disturbance
from workbench.study import TaskContext, TaskOutput

FIRST = 5  # earliest step shown: the first steps start from rest, nominal = real
SHOWN = 96  # sample paths drawn per system


def rollout(setup: NavigationSetup, x0: np.ndarray, V: np.ndarray) -> np.ndarray:
    """Positions (N, T+1, 2) of the plant model from x0 (physical) under V (T, nu, N)."""
    T, _, N = V.shape
    plant = setup.plant
    f = ca.Function("f", [plant.x, plant.u], [plant.x_next]).map(N)
    X = np.tile(np.asarray(x0, float)[: plant.nx, None], (1, N))
    out = [X[:2].T.copy()]
    for k in range(T):
        X = np.asarray(f(X, V[k]))
        out.append(X[:2].T.copy())
    return np.stack(out, axis=1)


def illustrate(setup: NavigationSetup, ctrl, task, ctx: TaskContext) -> TaskOutput:
    if ctrl.sampler.lib is not None:
        ctrl.sampler.lib.set_threads(ctx.threads)
    rng_c, rng_w = ctx.rng(0), ctx.rng(1)
    dist = Disturbance(task.variance)
    plant = setup.plant
    f = ca.Function("plant", [plant.x, plant.u], [plant.x_next])
    sais, last = ctrl.sampler.sais, {}

    def recording(x0, xs0, *args, **kw):
        batch = sais(x0, xs0, *args, **kw)
        last.update(x0=np.array(x0), xs0=np.array(xs0), batch=batch)
        return batch

    ctrl.sampler.sais = recording
    try:
        x, state = setup.x0.copy(), ctrl.initial_state(setup.x0)
        path, nominal, shown, crashed = [x[:2].copy()], [], None, False
        for k in range(task.steps):
            state, u, info = ctrl.step(state, x, rng_c)
            nominal.append(info.x_nom[:2].copy())
            if shown is None and k >= FIRST and info.nominal_differs:
                shown = {"step": k, **last}
            x = np.asarray(f(x, np.clip(u, plant.u_min, plant.u_max))).ravel() + dist.sample(
                plant.nx, plant.dt, rng_w, dist.indices(plant))
            path.append(x[:2].copy())
            if np.min(plant.margins(x)) <= 0:
                crashed = True
                break
        if shown is None:  # never differed: show the last batch
            shown = {"step": k, **last}
    finally:
        del ctrl.sampler.sais  # back to the class method
    b = shown["batch"]
    n = min(SHOWN, b.v_nom.shape[2])
    nom = rollout(setup, shown["xs0"], b.v_nom[:, :, :n])
    real = rollout(setup, shown["x0"], b.v_real[:, :, :n])
    arrays = {"path": np.array(path), "nominal_path": np.array(nominal),
              "nominal_samples": nom, "feedback_samples": real,
              "x_real": shown["x0"][:2], "x_nom": shown["xs0"][:2]}
    meta = {"step": int(shown["step"]), "crashed": crashed, "shown": int(n),
            "real_samples_crashed": float(np.mean(b.crashed_real)),
            "nominal_samples_crashed": float(np.mean(b.crashed_nom)),
            "u_limit": float(plant.u_max[0]), "variance": task.variance}
    return TaskOutput(arrays=arrays, meta=meta)

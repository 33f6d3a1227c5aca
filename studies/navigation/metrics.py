"""Per-episode measurements (assumptions §12.2), each defined once, as rows of the tidy tables.

episodes (one row per realisation): crashed, crash step / point / obstacle, final position and
error (a crashed run's final position is its crash point), time to goal (first time within
``goal_radius`` of the goal, NaN if never), time-averaged squared distance to the goal, min h,
speeds, and the controller's internals (counts over the episode's control steps).
velocity (every ``stride``-th state): time, vx, vy.  timing (one row, NOT reproducible): compute
time per control step.
"""

from __future__ import annotations

import numpy as np

from workbench.sampling.feedback import FALLBACK_REASONS
from workbench.sim import Episode


def episode_row(ep: Episode, goal: np.ndarray, dt: float, goal_radius: float,
                circles: np.ndarray) -> dict[str, np.ndarray]:
    P = ep.X[:, :2]
    dist = np.linalg.norm(P - goal[:2], axis=1)
    inside = np.flatnonzero(dist <= goal_radius)
    speed = np.linalg.norm(ep.X[:, 2:4], axis=1)
    obstacle = -1
    if ep.crashed:
        h = np.sum((P[-1] - circles[:, :2]) ** 2, axis=1) - circles[:, 2] ** 2
        obstacle = int(np.argmin(h))
    row = {
        "crashed": ep.crashed, "steps": len(ep.U),
        "crash_step": ep.crash_step if ep.crashed else -1,
        "crash_obstacle": obstacle,
        "final_x": P[-1, 0], "final_y": P[-1, 1], "final_error": dist[-1],
        "progress": 1.0 - dist[-1] / dist[0],
        "time_to_goal_s": inside[0] * dt if inside.size else np.nan,
        "mean_sq_distance": float(np.mean(dist ** 2)),
        "min_h": ep.min_margin, "mean_speed": float(speed.mean()),
        "max_speed": float(speed.max()),
    }
    row.update(internals(ep.infos))
    return {k: np.array([v]) for k, v in row.items()}


def internals(infos) -> dict[str, float | int]:
    """Counts over control steps (robust controllers; zeros / NaN where not applicable) and
    mean effective sample sizes (MPPI: its one ESS; robust: nominal and real)."""
    robust = bool(infos) and hasattr(infos[0], "nominal_differs")
    out: dict[str, float | int] = {"robust": robust}
    if robust:
        reasons = [i.ksafe_fallback for i in infos]
        out.update(
            nominal_differs_steps=sum(bool(i.nominal_differs) for i in infos),
            alpha_fallback_steps=sum(bool(i.fallback_used) for i in infos),
            ksafe_fallback_steps=sum(r is not None for r in reasons),
            **{f"ksafe_{r}": sum(x == r for x in reasons) for r in FALLBACK_REASONS},
            nominal_unsafe_steps=sum(bool(i.nominal_unsafe) for i in infos),
            real_candidate_steps=sum(not i.nominal_differs for i in infos),
            ess_nom_mean=float(np.mean([i.ess_nom for i in infos])),
            ess_real_mean=float(np.mean([i.ess_real for i in infos])),
        )
    else:
        ess = float(np.mean([i.ess for i in infos])) if infos else np.nan
        out.update(nominal_differs_steps=0, alpha_fallback_steps=0, ksafe_fallback_steps=0,
                   **{f"ksafe_{r}": 0 for r in FALLBACK_REASONS}, nominal_unsafe_steps=0,
                   real_candidate_steps=len(infos), ess_nom_mean=ess, ess_real_mean=np.nan)
    return out


def velocity_rows(ep: Episode, dt: float, stride: int) -> dict[str, np.ndarray]:
    k = np.arange(0, len(ep.X), stride)
    return {"step": k, "time_s": k * dt, "vx": ep.X[k, 2], "vy": ep.X[k, 3]}


def timing_row(ep: Episode) -> dict[str, np.ndarray]:
    """Wall-clock mean, median and 95th percentile and mean process CPU time per step [ms]."""
    t = 1e3 * np.asarray(ep.step_time_s)
    return {"mean_step_ms": np.array([t.mean()]), "median_step_ms": np.array([np.median(t)]),
            "p95_step_ms": np.array([np.quantile(t, 0.95)]),
            "mean_cpu_ms": np.array([1e3 * np.mean(ep.step_cpu_s)])}

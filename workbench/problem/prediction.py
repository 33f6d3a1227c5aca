"""Scenes predicted over a horizon: where a scene's moving circles are at each step's time.

A scene whose layout has moving slots (:class:`~workbench.problem.scene_kinds.MovingCircle`,
x, y, r, vx, vy) describes the circles now; at time t from now they are at c + v t
(:meth:`~workbench.problem.scene_layout.SceneLayout.predicted`). A step from x_k to x_{k+1}
is evaluated in the scene of x_{k+1}'s time, (k + 1) dt: its margins and, for a
barrier-embedded model, its dynamics (whose barrier state is formed from x_{k+1}'s margins).
Every controller that rolls its model out over a horizon uses these scenes; a model without
moving slots gets its scene unchanged (the same array).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from workbench.problem.models import Model


def predicts(model: Model) -> bool:
    """Whether the model's scene has moving circles (its scenes change over a horizon)."""
    return model.scene_layout is not None and model.scene_layout.moves


def scene_at(model: Model, scene: np.ndarray, t: float) -> np.ndarray:
    """The scene vector ``scene`` predicted to time ``t`` from now (itself when the model's
    scene has no moving circles)."""
    if not predicts(model):
        return scene
    assert model.scene_layout is not None
    return model.scene_layout.predicted(scene, t)


def scene_sx_at(model: Model, scene, t):
    """The scene symbol ``scene`` predicted to time ``t`` (an SX scalar or a number) from now
    (itself when the model's scene has no moving circles)."""
    if not predicts(model):
        return scene
    assert model.scene_layout is not None
    return model.scene_layout.predicted_sx(scene, t)


def step_scene(model: Model, scene: np.ndarray) -> np.ndarray:
    """The scene of one step from now (x_1's time, dt): what a single step's dynamics take."""
    return scene_at(model, scene, model.dt)


def scenes(model: Model, scene: np.ndarray, n: int, first: int = 1) -> np.ndarray:
    """(ns, n): column k the scene predicted to (first + k) dt (the scene repeated when the
    model's scene has no moving circles)."""
    s = np.asarray(scene, dtype=float)
    if not predicts(model):
        return np.repeat(s[:, None], n, axis=1)
    return np.stack([scene_at(model, s, (first + k) * model.dt) for k in range(n)], axis=1)


def step_scenes(model: Model, scene: np.ndarray, T: int) -> np.ndarray:
    """(ns, T): column k the scene of step k, predicted to (k + 1) dt."""
    return scenes(model, scene, T)


__all__ = ["predicts", "scene_at", "scene_sx_at", "scenes", "step_scene", "step_scenes"]

"""Scenes of obstacles of any kind: the layout that fits them, and how a plant is built on it
(or refused)."""

from __future__ import annotations

import numpy as np
import pytest

from workbench.problem.obstacles import Circle
from workbench.problem.scene_kinds import Capsule, HalfSpace, Sphere
from workbench.problem.scene_layout import SceneLayout
from workbench.problem.sdf_grid import SignedDistanceGrid
from workbench.scenarios.scenes import ObstacleScene
from workbench.scenarios.systems import SYSTEMS, System

GRID = SignedDistanceGrid(np.full((5, 4), 2.0), (0.0, 0.0), 1.0)


def test_the_fitting_layout_has_one_slot_per_obstacle_and_the_grid_shape():
    objs = [Circle((1, 1), 0.5), (2.0, 2.0, 0.3), HalfSpace((0, 1), -1.0),
            Capsule((3, 3), (4, 4), 0.2), GRID]
    lay = SceneLayout.fitting(objs)
    assert lay == SceneLayout.of(circles=2, halfspaces=1, capsules=1, grid=(5, 4))
    assert SceneLayout.fitting([Sphere((0, 0, 1), 0.5)]) == SceneLayout.of(3, spheres=1)
    assert SceneLayout.fitting([]) == SceneLayout()
    with pytest.raises(ValueError, match=r"scene\[1\] = .* at most one grid"):
        SceneLayout.fitting([GRID, GRID])
    with pytest.raises(ValueError, match="share one position dimension"):
        SceneLayout.fitting([Sphere((0, 0, 1), 0.5), Capsule((3, 3), (4, 4), 0.2)])


def test_obstacle_scenes_check_their_layout_and_fields():
    s = ObstacleScene((GRID, Circle((1, 1), 0.5)), start=(3.0, 0.2), goal=(0.2, 3.0))
    assert s.scene_layout == SceneLayout.of(circles=1, grid=(5, 4))
    assert s.obstacles() == (GRID, Circle((1, 1), 0.5))
    big = SceneLayout.of(circles=4, grid=(5, 4))
    assert ObstacleScene((GRID,), layout=big).scene_layout is big
    with pytest.raises(ValueError, match=r"ObstacleScene.objects\[0\] = .*a grid of shape"):
        ObstacleScene((SignedDistanceGrid(np.ones((3, 3))),), layout=big)
    with pytest.raises(ValueError, match=r"ObstacleScene.objects = .*room for 0"):
        ObstacleScene((HalfSpace((0, 1), -1.0),), layout=big)
    with pytest.raises(ValueError, match=r"ObstacleScene.layout = .*planar \(dim 2\)"):
        ObstacleScene((Sphere((0, 0, 1), 0.5),))
    with pytest.raises(ValueError, match=r"ObstacleScene.dt"):
        ObstacleScene((GRID,), dt=0.0)
    with pytest.raises(ValueError, match=r"ObstacleScene.objects = 'grid'"):
        ObstacleScene("grid")


def test_a_plant_on_an_obstacle_scene_uses_its_layout_or_is_refused():
    scene = ObstacleScene((GRID, HalfSpace((0, 1), -1.0)), start=(1.0, 1.0), goal=(3.0, 2.0))
    for name in ("double_integrator", "unicycle", "bicycle"):
        plant = SYSTEMS[name].plant(scene)
        assert plant.scene_layout == scene.scene_layout and plant.scene_capacity == 0
        x = SYSTEMS[name].state_at(np.array([1.0, 2.5]), 0.0)
        h = plant.margins(x)[:2]
        np.testing.assert_allclose(h, [3.5, 2.0], rtol=1e-12)  # the half-plane's, the grid's
        np.testing.assert_allclose(h, plant.scene_layout.numpy_margins(
            [[1.0, 2.5]], plant.scene_value)[0], rtol=1e-12)
    with pytest.raises(ValueError, match=r"scene_capacity = 8 .* leave scene_capacity unset"):
        SYSTEMS["double_integrator"].plant(scene, scene_capacity=8)
    di = SYSTEMS["double_integrator"]

    def circles_only(*, obstacles, dt, u_limit, scene_capacity, runtime_obstacles):
        return di.model(obstacles=obstacles, dt=dt, u_limit=u_limit,
                        scene_capacity=scene_capacity, runtime_obstacles=runtime_obstacles)

    from dataclasses import replace
    own: System = replace(di, name="circles_only", model=circles_only)
    with pytest.raises(ValueError, match=r"system = 'circles_only' .* takes no scene_layout"):
        own.plant(scene)

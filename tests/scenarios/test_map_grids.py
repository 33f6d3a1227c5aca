"""The occupancy_grid map family: the occupancy family's cells as a signed-distance grid, the
scene and plant built on it, scaling; the circle families keep their maps."""

from __future__ import annotations

import numpy as np
import pytest

from workbench.problem.sdf_grid import grid_numpy
from workbench.scenarios.maps import GRID_FAMILIES, MAP_FAMILIES, MapFamily, generate, scaled
from workbench.scenarios.navigation import navigation_setup
from workbench.scenarios.scenes import CircleScene, ObstacleScene


def brute_force(occ: np.ndarray, h: float) -> np.ndarray:
    """Node values by definition: distance between cell centres to the nearest cell of the
    other kind, minus half a cell, negative on occupied cells (no distance transform)."""
    idx = np.argwhere(np.ones_like(occ))
    occ_idx, free_idx = np.argwhere(occ), np.argwhere(~occ)
    out = np.empty(occ.shape)
    for i, j in idx:
        other = free_idx if occ[i, j] else occ_idx
        d = h * np.hypot(*(other - (i, j)).T).min() - h / 2
        out[i, j] = -d if occ[i, j] else d
    return out


@pytest.mark.parametrize("seed", [1000, 3])
def test_grid_maps_are_the_occupancy_cells_as_signed_distances(seed):
    fam = MapFamily("occupancy_grid", fill=0.3, grid=16)
    m = generate(fam, seed)
    o = generate(MapFamily("occupancy", fill=0.3, grid=16), seed)
    assert m.cells == o.cells and len(m.cells) > 10 and m.difficulty == o.difficulty
    assert m.circles == () and m.moving == () and o.grid is None
    h = 10.0 / 16
    occ = np.zeros((16, 16), dtype=bool)
    occ[tuple(np.array(m.cells).T)] = True
    g = m.grid
    assert g is not None and g.shape == (16, 16) and g.resolution == h
    assert g.origin == (h / 2, h / 2)
    np.testing.assert_allclose(g.values, brute_force(occ, h), rtol=1e-12, atol=1e-12)
    assert np.all((g.values < 0) == occ)
    s = m.scene()
    assert isinstance(s, ObstacleScene) and s.objects == (g,) and s.scene_layout.grid == (16, 16)
    assert (s.start, s.goal) == (fam.start, fam.goal)
    assert isinstance(o.scene(), CircleScene)


def test_scaled_grid_maps_scale_distances_and_the_plant_sees_them():
    m = generate(MapFamily("occupancy_grid"), 1000)
    s = scaled(m, 2.0)
    assert s.grid.resolution == 2 * m.grid.resolution and s.start == (1.0, 1.0)
    P = np.random.default_rng(5).uniform(-1.0, 11.0, (40, 2))  # beyond the grid too
    np.testing.assert_allclose(grid_numpy(2 * P, s.grid.row(), s.grid.shape),
                               2 * grid_numpy(P, m.grid.row(), m.grid.shape), rtol=1e-12,
                               atol=1e-12)
    scene = scaled(m.scene(), 2.0)
    assert isinstance(scene, ObstacleScene) and scene.scene_layout == m.scene().scene_layout
    np.testing.assert_array_equal(scene.objects[0].values, s.grid.values)
    nav = navigation_setup(s.scene())
    assert nav.plant.scene_layout.grid == (20, 20) and nav.plant.scene_capacity == 0
    x = np.array([*P[0] * 2, 0.0, 0.0])
    assert nav.plant.margins(x)[0] == pytest.approx(
        grid_numpy(2 * P[:1], s.grid.row(), s.grid.shape)[0], rel=1e-12)


def test_grid_family_knobs_are_refused_where_they_do_not_apply():
    assert GRID_FAMILIES == ("occupancy_grid",) and "occupancy_grid" not in MAP_FAMILIES
    with pytest.raises(ValueError, match=r"map\.moving = 2 .*no moving obstacles"):
        MapFamily("occupancy_grid", moving=2)
    with pytest.raises(ValueError, match=r"map\.n_obstacles = 3 .*occupancy_grid family"):
        MapFamily("occupancy_grid", n_obstacles=3)
    with pytest.raises(ValueError, match=r"map\.family = 'grid' .*occupancy_grid"):
        MapFamily("grid")

"""The map families of other shapes: occupancy_grid (the occupancy family's cells as a
signed-distance grid) and corridor_capsules (the corridor family's walls as capsules); the
scenes and plants built on them, scaling."""

from __future__ import annotations

import numpy as np
import pytest

from workbench.problem.sdf_grid import grid_numpy
from workbench.scenarios.maps import LAYOUT_FAMILIES, MAP_FAMILIES, MapFamily, generate, scaled
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
    assert not set(LAYOUT_FAMILIES) & set(MAP_FAMILIES)
    for name in LAYOUT_FAMILIES:
        with pytest.raises(ValueError, match=r"map\.moving = 2 .*no moving obstacles"):
            MapFamily(name, moving=2)
    with pytest.raises(ValueError, match=r"map\.n_obstacles = 3 .*occupancy_grid family"):
        MapFamily("occupancy_grid", n_obstacles=3)
    with pytest.raises(ValueError, match=r"map\.family = 'grid' .*occupancy_grid"):
        MapFamily("grid")
    with pytest.raises(ValueError, match=r"map\.fill = 0\. .*without an occupied cell"):
        generate(MapFamily("occupancy_grid", fill=0.0), 1)


def segment_distance(P: np.ndarray, a, b) -> np.ndarray:
    a, b = np.asarray(a), np.asarray(b)
    t = np.clip((P - a) @ (b - a) / ((b - a) @ (b - a)), 0.0, 1.0)
    return np.hypot(*(P - (a + t[:, None] * (b - a))).T)


@pytest.mark.parametrize("seed", [3, 11])
def test_capsule_corridors_hold_the_wall_circles_and_keep_the_gates(seed):
    kw = {"n_gates": 3, "corridor_width": 0.7, "radius_range": (0.3, 0.6)}
    m = generate(MapFamily("corridor_capsules", **kw), seed)
    c = generate(MapFamily("corridor", **kw), seed)
    on_walls = sorted(i for w in c.walls for i in w)
    rest = [x for i, x in enumerate(c.circles) if i not in on_walls]
    assert m.walls == () and m.difficulty == c.difficulty
    assert len(m.capsules) + (len(m.circles) - len(rest)) == 6  # two sides per wall
    assert set(rest) <= set(m.circles)  # the random circles, unchanged
    caps = list(m.capsules)
    for i in on_walls:  # every wall circle lies inside a capsule (its centre on the segment)
        w = c.circles[i]
        d = [segment_distance(np.array([w.center]), k.a, k.b)[0] + w.radius - k.radius
             for k in caps]
        assert min(d) <= 1e-9 or w in m.circles
    for w in c.walls:  # the gate: the two sides' facing ends, corridor_width apart
        C = np.array([x.center for x in (c.circles[i] for i in w)])
        k = int(np.argmax(np.hypot(*np.diff(C, axis=0).T)))
        ends = {tuple(C[k]), tuple(C[k + 1])}
        facing = [p for cap in caps for p in (cap.a, cap.b) if p in ends]
        facing += [x.center for x in m.circles if x.center in ends]
        assert len(facing) == 2
        gap = np.hypot(*np.subtract(*facing)) - 2 * kw["radius_range"][1]
        assert gap == pytest.approx(0.7, rel=1e-12)
    lay = m.layout()
    assert lay == generate(MapFamily("corridor_capsules", **kw), seed + 1).layout()
    assert m.scene_layout() == lay and c.layout() is None
    assert lay.count("capsules") == 6 and lay.count("circles") == 5 + 6


def test_a_capsule_corridor_plant_sees_capsules_and_circles():
    m = generate(MapFamily("corridor_capsules"), 3)
    nav = navigation_setup(scaled(m, 0.5).scene())
    assert nav.plant.scene_layout == m.layout()
    P = np.random.default_rng(9).uniform(0.0, 5.0, (30, 2))
    h = np.array([nav.plant.margins(np.array([*p, 0.0, 0.0]))[:nav.plant.scene_layout.n_margins]
                  for p in P])
    np.testing.assert_allclose(h, nav.plant.scene_layout.numpy_margins(P, nav.plant.scene_value),
                               rtol=1e-10, atol=1e-12)
    # the closed form: squared distances to the scaled circles and capsules, unused slots far
    slots = nav.plant.scene_layout.count("circles")
    circles = [np.hypot(*(P - np.multiply(x.center, 0.5)).T) ** 2 - (0.5 * x.radius) ** 2
               for x in m.circles]
    capsules = [segment_distance(P, np.multiply(k.a, 0.5), np.multiply(k.b, 0.5)) ** 2
                - (0.5 * k.radius) ** 2 for k in m.capsules]
    assert len(m.capsules) == 4 and slots == 5 + 4
    np.testing.assert_allclose(h[:, :len(m.circles)], np.column_stack(circles), rtol=1e-9)
    np.testing.assert_allclose(h[:, slots:], np.column_stack(capsules), rtol=1e-9)
    assert np.all(h[:, len(m.circles):slots] > 1e6)  # unused circle slots

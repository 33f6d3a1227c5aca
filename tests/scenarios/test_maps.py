"""Map families, moving obstacles and the difficulty measure (workbench.scenarios.maps)."""

from __future__ import annotations

import time
from dataclasses import replace
from itertools import combinations

import numpy as np
import pytest

from workbench.problem.obstacles import Circle
from workbench.scenarios import maps
from workbench.scenarios.maps import (
    MAP_FAMILIES,
    GeneratedMap,
    MapFamily,
    automaton_step,
    cover_cells,
    difficulty,
    generate,
    occupancy_grid,
    scaled,
)
from workbench.scenarios.scenes import CircleScene, NavigationScene

RES = 0.05


def arr(circles) -> np.ndarray:
    return np.array([(*c.center, c.radius) for c in circles]).reshape(-1, 3)


def gaps(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Edge-to-edge gaps between every circle of A and every circle of B."""
    return (np.hypot(A[:, None, 0] - B[None, :, 0], A[:, None, 1] - B[None, :, 1])
            - A[:, None, 2] - B[None, :, 2])


def pair_gaps(C: np.ndarray) -> np.ndarray:
    return np.array([gaps(C[[i]], C[[j]])[0, 0] for i, j in combinations(range(len(C)), 2)])


def end_gaps(m: GeneratedMap, C: np.ndarray | None = None) -> np.ndarray:
    C = arr(m.circles) if C is None else C
    return np.array([np.hypot(*(C[:, :2] - np.array(p)).T) - C[:, 2] for p in (m.start, m.goal)])


# ------------------------------------------------------------------------------ determinism


@pytest.mark.parametrize("family", MAP_FAMILIES)
def test_same_seed_same_map_and_seeds_differ(family):
    fam = MapFamily(family, moving=2)
    a = generate(fam, 8)
    maps._generate.cache_clear()  # draw again instead of returning the cached map
    b = generate(fam, 8)
    assert a is not b and a == b
    c = generate(fam, 1)
    assert c.circles != a.circles
    assert c.moving != a.moving


def test_spec_family_is_the_navigation_scene():
    for seed in (7, 1):
        m = generate(MapFamily("spec"), seed)
        assert m.circles == NavigationScene(seed=seed).obstacles()
        assert m.walls == () and m.cells == () and m.moving == ()


# ----------------------------------------------------------------------------------- knobs


def test_spec_knobs_are_respected():
    fam = MapFamily("spec", n_obstacles=12, radius_range=(0.2, 0.5), min_gap=0.6,
                    endpoint_clearance=1.0, corridor_width=1.2)
    m = generate(fam, 3)
    C = arr(m.circles)
    assert len(C) == 12
    assert pair_gaps(C).min() >= 0.6 - 1e-9
    assert np.all((C[2:, 2] >= 0.2) & (C[2:, 2] <= 0.5))
    assert gaps(C[[0]], C[[1]])[0, 0] == pytest.approx(1.2)  # the gate
    assert end_gaps(m).min() >= 1.0 - 1e-9


def test_corridor_knobs_are_respected():
    fam = MapFamily("corridor", n_obstacles=4, radius_range=(0.25, 0.6), min_gap=0.5,
                    corridor_width=0.9, endpoint_clearance=1.0, moving=3)
    m = generate(fam, 5)
    C = arr(m.circles)
    wall = sorted(i for w in m.walls for i in w)
    free = [i for i in range(len(C)) if i not in wall]
    assert len(free) == 4 and {i for i, _ in m.moving} <= set(free)  # movers: random ones
    assert np.all(C[wall, 2] == 0.6)  # walls use the top of the radius range
    assert np.all((C[free, 2] >= 0.25) & (C[free, 2] <= 0.6))
    assert pair_gaps(C[free]).min() >= 0.5 - 1e-9
    assert gaps(C[free], C[wall]).min() >= 0.9 - 1e-9  # corridor_width to walls
    assert end_gaps(m).min() >= 1.0 - 1e-9
    # more movers than random circles: the rest are extra circles, min_gap to all
    more = generate(replace(fam, moving=6), 5)
    assert more.circles[:len(C)] == m.circles and len(more.circles) == len(C) + 2
    E = arr(more.circles)
    assert gaps(E[-2:], E[:-2]).min() >= 0.5 - 1e-9 and pair_gaps(E[-2:]).min() >= 0.5 - 1e-9
    assert np.all((E[-2:, 2] >= 0.25) & (E[-2:, 2] <= 0.6))
    assert {i for i, _ in more.moving} == set(free) | {len(C), len(C) + 1}
    assert end_gaps(more).min() >= 1.0 - 1e-9


@pytest.mark.parametrize("family", MAP_FAMILIES)
def test_default_endpoints_are_clear(family):
    for seed in (7, 8):  # (quick spec seeds: NavigationScene samples in Python)
        m = generate(MapFamily(family, moving=2), seed)
        assert end_gaps(m).min() >= MapFamily().endpoint_clearance - 1e-9
        assert m.difficulty.bottleneck > 0 and np.isfinite(m.difficulty.path_length)


def test_corridor_walls_cross_the_box_with_one_gate_each():
    for seed in range(4):
        fam = MapFamily("corridor", n_gates=3, corridor_width=0.7, radius_range=(0.3, 0.6))
        m = generate(fam, seed)
        C = arr(m.circles)
        assert len(m.walls) == 3
        for wall in m.walls:
            W = C[list(wall)]
            # the end circles sit on the box edge
            for end in (W[0], W[-1]):
                assert min(end[0], 10 - end[0], end[1], 10 - end[1]) == pytest.approx(0, abs=1e-9)
            g = np.array([gaps(W[[i]], W[[i + 1]])[0, 0] for i in range(len(W) - 1)])
            gate = int(np.argmax(g))
            assert g[gate] >= 0.7 - 1e-9  # the gate: at least corridor_width wide
            assert np.all(np.delete(g, gate) < 0)  # every other neighbour pair overlaps
            # geometrically: the wall alone leaves a passage of half the gate ...
            d = difficulty(W, m.start, m.goal)
            assert abs(d.bottleneck - 0.35) <= RES  # on the grid: within its resolution
            # ... and none once a circle plugs the gate
            plug = (W[gate, :2] + W[gate + 1, :2]) / 2
            closed = difficulty(np.vstack([W, (*plug, 0.5)]), m.start, m.goal)
            assert closed.bottleneck == 0.0 and closed.path_length == np.inf
        assert m.difficulty.bottleneck <= 0.35 + RES


def test_occupancy_circles_cover_every_occupied_cell_conservatively():
    rng = np.random.default_rng(0)
    for seed in range(10):
        m = generate(MapFamily("occupancy"), seed)
        assert len(m.circles) <= 150 and m.cells
        h = m.cell_size
        C = arr(m.circles)
        cells = np.array(m.cells)
        # random points in every occupied cell lie in some circle
        pts = (cells[:, None, :] + rng.uniform(0, 1, (len(cells), 20, 2))) * h
        pts = np.concatenate([pts.reshape(-1, 2), (cells + 0.999) * h, (cells + 0.001) * h])
        inside = np.hypot(pts[:, None, 0] - C[None, :, 0], pts[:, None, 1] - C[None, :, 1]) \
            <= C[None, :, 2]
        assert inside.any(axis=1).all()
        # conservative by at most (sqrt 2 - 1) / 2 h: circle rims stay within the
        # circumscribed circles of the occupied cells
        a = np.linspace(0, 2 * np.pi, 64, endpoint=False)
        rim = (C[:, None, :2] + C[:, None, 2:] * np.stack([np.cos(a), np.sin(a)], -1)) \
            .reshape(-1, 2)
        centres = (cells + 0.5) * h
        near = np.hypot(rim[:, None, 0] - centres[None, :, 0],
                        rim[:, None, 1] - centres[None, :, 1]).min(axis=1)
        assert near.max() <= h / np.sqrt(2) + 1e-9
        # start and goal are linked with a passage at least min_gap wide
        assert m.difficulty.bottleneck >= MapFamily().min_gap / 2
        assert np.isfinite(m.difficulty.path_length)


def test_occupancy_is_a_cellular_automaton_with_the_barn_rule():
    def slow(occ):  # the rule cell by cell: >= 5 occupied neighbours fill, <= 1 clear
        n, m = occ.shape
        out = occ.copy()
        for i in range(n):
            for j in range(m):
                k = sum(occ[a, b] for a in range(i - 1, i + 2) for b in range(j - 1, j + 2)
                        if (a, b) != (i, j) and 0 <= a < n and 0 <= b < m)
                out[i, j] = True if k >= 5 else False if k <= 1 else occ[i, j]
        return out

    rng = np.random.default_rng(1)
    for fill in (0.2, 0.45, 0.6):
        occ = rng.random((12, 9)) < fill
        assert np.array_equal(automaton_step(occ), slow(occ))
    # the grid a map came from: fill, smoothing, cleared ends
    fam = MapFamily("occupancy", fill=0.3, smoothing=2)
    occ = occupancy_grid(fam, np.random.default_rng(3))
    ref = np.random.default_rng(3).random((20, 20)) < 0.3
    ref = automaton_step(automaton_step(ref))
    assert not np.any(occ & ~ref)
    centres = (np.argwhere(occ != ref) + 0.5) * 0.5
    near = np.minimum(*(np.hypot(*(centres - np.array(e)).T) for e in (fam.start, fam.goal)))
    assert np.all(near - 0.5 / np.sqrt(2) < fam.endpoint_clearance)  # only there
    assert occ[0, 0] == occ[19, 19] == False  # noqa: E712  (cleared around start and goal)
    # cover_cells covers a full block with fewer circles than cells
    block = np.zeros((10, 10), dtype=bool)
    block[2:8, 2:8] = True
    assert len(cover_cells(block, 1.0)) < 36


def test_moving_obstacles_do_not_change_the_map_at_time_0():
    for family in MAP_FAMILIES:
        still = generate(MapFamily(family), 8)
        moving = generate(MapFamily(family, moving=3), 8)
        assert len(moving.moving) == 3 and moving.n_static == len(moving.circles) - 3
        if family == "occupancy":  # no free-standing circles: three are added
            assert moving.circles[:-3] == still.circles
            assert [i for i, _ in moving.moving] == [len(still.circles) + j for j in range(3)]
        else:  # three of the random circles move
            assert moving.circles == still.circles
            assert moving.difficulty == still.difficulty
            assert all(i >= 2 for i, _ in moving.moving)  # never a spec gate circle


# ---------------------------------------------------------------------------- difficulty


def gate(gap: float, D: float = 100.0) -> np.ndarray:
    """Two huge circles on the anti-diagonal leaving a gap around (5, 5): a wall across the
    box with one gate (the widest path crosses it on the line of centres)."""
    u = np.array([1.0, -1.0]) / np.sqrt(2)
    r = D - gap / 2
    return np.array([(*(5 + D * u), r), (*(5 - D * u), r)])


def closed_forms_hold(diff) -> bool:
    """The closed forms a difficulty measure must meet."""
    s, g = (0.5, 0.5), (9.5, 9.5)
    empty = diff((), s, g)
    ok = abs(empty.bottleneck - 0.5) < 1e-9 and abs(empty.path_length - 9 * np.sqrt(2)) < 1e-9
    ok &= abs(empty.straight_clearance - 0.5) < 1e-9 and empty.coverage == 0.0
    off = diff((), (0.5, 2.0), (9.5, 5.0))  # not a lattice direction: at most 2.7 % long
    ratio = off.path_length / np.hypot(9, 3)
    ok &= 1 - 1e-9 <= ratio < 1.027 and abs(off.bottleneck - 0.5) < 1e-9
    for gp in (0.3, 0.6):
        d = diff(gate(gp), s, g)
        ok &= abs(d.bottleneck - gp / 2) <= RES
        ok &= abs(d.straight_clearance - gp / 2) < 1e-6  # the segment crosses the gate
        ok &= abs(d.path_length - 9 * np.sqrt(2)) < 1e-6  # straight through the gate
    one = diff([Circle((5, 5), 2.0)], s, g)  # coverage: the circle's area share
    ok &= abs(one.coverage - np.pi * 4 / 100) < 2e-3 and abs(one.straight_clearance + 2) < 1e-9
    wall = diff(gate(-0.2), s, g)
    ok &= wall.bottleneck == 0.0 and wall.path_length == np.inf
    ok &= wall.straight_clearance == pytest.approx(-0.1)
    return bool(ok)


def test_difficulty_meets_closed_forms():
    assert closed_forms_hold(difficulty)
    assert difficulty(gate(0.6), (0.5, 0.5), (9.5, 9.5)).n_circles == 2
    # inside a circle: no path
    inside = difficulty([Circle((0.5, 0.5), 0.2)], (0.5, 0.5), (9.5, 9.5))
    assert inside.bottleneck == 0.0 and inside.path_length == np.inf


def test_broken_difficulties_fail_the_closed_forms(monkeypatch):
    def mean_distance(X, Y, C):  # min over circles replaced by the mean
        if not len(C):
            return np.full(np.broadcast_shapes(np.shape(X), np.shape(Y)), np.inf)
        return np.mean([np.hypot(X - cx, Y - cy) - r for cx, cy, r in C], axis=0)

    with monkeypatch.context() as m:
        m.setattr(maps, "_circle_distance", mean_distance)
        assert not closed_forms_hold(maps.difficulty)

    real_label = maps.ndimage.label

    def one_component(mask, structure=None):  # connectivity ignored
        lab, n = real_label(mask, structure=structure)
        return (lab > 0).astype(int), min(n, 1)

    with monkeypatch.context() as m:
        m.setattr(maps.ndimage, "label", one_component)
        assert not closed_forms_hold(maps.difficulty)
    assert closed_forms_hold(difficulty)


def test_difficulty_is_fast():
    m = generate(MapFamily("occupancy", fill=0.35), 9)
    assert len(m.circles) > 80
    t = time.perf_counter()
    difficulty(m.circles, m.start, m.goal)
    assert time.perf_counter() - t < 1.0


# ------------------------------------------------------------------------ moving obstacles


def test_moving_obstacles_translate_and_bounce():
    fam = MapFamily("corridor", moving=4, speed=1.5)
    m = generate(fam, 4)
    dt = 0.05
    assert m.scene_at(0, dt) == m.circles
    assert end_gaps(m, arr(m.circles)[[i for i, _ in m.moving]]).min() \
        >= fam.endpoint_clearance - 1e-9
    for _, v in m.moving:
        assert np.hypot(*v) == pytest.approx(1.5)
    # step-by-step reflection in the box, against the closed form
    pos = {i: np.array(m.circles[i].center) for i, _ in m.moving}
    vel = {i: np.array(v) for i, v in m.moving}
    scene = m.moving_scene(dt)
    bounced = set()
    for k in range(1, 400):
        circles = scene(k)
        assert circles == m.scene_at(k, dt)
        still = {i for i, _ in m.moving}
        assert all(circles[i] == c for i, c in enumerate(m.circles) if i not in still)
        for i, _ in m.moving:
            r = m.circles[i].radius
            p = pos[i] + vel[i] * dt
            for a in range(2):
                if p[a] > 10 - r:
                    p[a], vel[i][a] = 2 * (10 - r) - p[a], -vel[i][a]
                    bounced.add(i)
                elif p[a] < r:
                    p[a], vel[i][a] = 2 * r - p[a], -vel[i][a]
                    bounced.add(i)
            pos[i] = p
            assert np.allclose(circles[i].center, p, atol=1e-9)
            assert circles[i].radius == r
            if k * dt * 1.5 < 0.09:  # before any bounce: plain velocity * k * dt
                c0 = np.array(m.circles[i].center)
                assert np.allclose(circles[i].center, c0 + np.array(vel[i]) * k * dt)
    assert bounced  # 20 m of travel: every mover hit the box
    again = generate(fam, 4).scene_at(123, dt)
    assert again == m.scene_at(123, dt)


def test_moving_scene_runs_in_closed_loop():
    from workbench.problem.models import double_integrator
    from workbench.sim import Disturbance, closed_loop

    m = generate(MapFamily("spec", n_obstacles=4, moving=2, speed=2.0), 0)
    plant = double_integrator(obstacles=m.circles, u_limit=5.0)

    class Hold:
        def initial_state(self, x0):
            return None

        def step(self, state, x, rng):
            return state, np.zeros(2), None

    rng = np.random.default_rng(0)
    ep = closed_loop(Hold(), plant, np.array([*m.start, 0.0, 0.0]), 5, rng, rng,
                     Disturbance(level=0.0), keep_infos=False,
                     scene=m.moving_scene(plant.dt))
    for k in range(6):
        assert np.array_equal(ep.scenes[k], plant.scene_vector(m.scene_at(k, plant.dt)))


# ------------------------------------------------------------------------ scenes and scaling


def test_scene_and_scaled():
    m = generate(MapFamily("corridor", moving=1), 1)
    sc = m.scene()
    assert isinstance(sc, CircleScene) and sc.circles == m.circles and sc.goal == m.goal
    big = scaled(m, 2.0)
    assert isinstance(big, GeneratedMap) and big.start == (1.0, 1.0) and big.goal == (19.0, 19.0)
    assert np.allclose(arr(big.circles), 2 * arr(m.circles))
    assert big.box == ((0.0, 20.0), (0.0, 20.0))
    assert np.allclose(big.moving[0][1], 2 * np.array(m.moving[0][1]))
    assert np.allclose(big.scene_at(50, 0.1)[-1].center, 2 * np.array(m.scene_at(50, 0.1)[-1]
                                                                        .center))
    # the scaled difficulty equals the difficulty of the scaled map (grid scaled along)
    d = difficulty(big.circles, big.start, big.goal, resolution=2 * RES,
                   box=big.box)
    for k in ("bottleneck", "straight_clearance", "coverage"):
        assert getattr(d, k) == pytest.approx(getattr(big.difficulty, k), rel=1e-9, abs=1e-9)
    # (rounding can tip which of many equal-clearance nodes pass the bottleneck)
    assert d.path_length == pytest.approx(big.difficulty.path_length, rel=0.01)
    nav = scaled(NavigationScene(), 0.5)
    assert isinstance(nav, CircleScene) and nav.start == (0.25, 0.25)
    assert nav.circles[0] == Circle((1.8, 2.5), 0.5)
    assert scaled(sc, 3.0).circles[0].radius == pytest.approx(3 * m.circles[0].radius)
    assert scaled([Circle((1, 2), 0.5)], 2.0) == (Circle((2, 4), 1.0),)


# ------------------------------------------------------------------------------- bad input


@pytest.mark.parametrize("kw, field", [
    (dict(family="maze"), "map.family"),
    (dict(n_obstacles=1), "map.n_obstacles"),
    (dict(family="corridor", n_obstacles=-1), "map.n_obstacles"),
    (dict(family="occupancy", n_obstacles=30), "map.n_obstacles"),
    (dict(radius_range=(0.5, 0.2)), "map.radius_range"),
    (dict(radius_range=(0.0, 0.2)), "map.radius_range"),
    (dict(min_gap=-0.1), "map.min_gap"),
    (dict(corridor_width=0.0), "map.corridor_width"),
    (dict(n_gates=-1), "map.n_gates"),
    (dict(n_gates=2.0), "map.n_gates"),
    (dict(fill=1.5), "map.fill"),
    (dict(grid=2), "map.grid"),
    (dict(smoothing=-1), "map.smoothing"),
    (dict(start=(0.5,)), "map.start"),
    (dict(start=(10.0, 5.0)), "map.start"),
    (dict(goal=(0.5, 0.5)), "map.goal"),
    (dict(endpoint_clearance=float("nan")), "map.endpoint_clearance"),
    (dict(moving=-1), "map.moving"),
    (dict(speed=-1.0), "map.speed"),
])
def test_bad_knobs_name_the_field(kw, field):
    with pytest.raises(ValueError, match=field.replace(".", r"\.")) as exc:
        MapFamily(**kw)
    if field == "map.family":
        assert "unknown map family" in str(exc.value) and "'occupancy'" in str(exc.value)


def test_start_or_goal_inside_an_obstacle_is_an_error():
    with pytest.raises(ValueError, match=r"map\.start .*inside"):
        generate(MapFamily("spec", start=(3.6, 5.0)), 7)  # in a gate circle
    with pytest.raises(ValueError, match=r"map\.goal .*inside"):
        generate(MapFamily("spec", goal=(6.4, 5.2)), 7)
    with pytest.raises(ValueError, match=r"map\.(start|goal) .*wall circle"):
        generate(MapFamily("corridor", n_gates=1, endpoint_clearance=6.5), 0)
    with pytest.raises(ValueError, match=r"map\.n_gates .*apart"):
        generate(MapFamily("corridor", n_gates=12), 0)
    with pytest.raises(ValueError, match=r"map\.n_obstacles .*placed only"):
        generate(MapFamily("corridor", n_obstacles=60), 0)
    with pytest.raises(ValueError, match=r"map\.moving .*placed only"):
        generate(MapFamily("spec", moving=40), 7)
    with pytest.raises(ValueError, match=r"map\.fill"):
        generate(MapFamily("occupancy", fill=0.7, smoothing=1), 0)
    with pytest.raises(ValueError, match=r"map\.seed"):
        generate(MapFamily(), -1)
    with pytest.raises(ValueError, match=r"scene_at\.dt"):
        generate(MapFamily("corridor", moving=1), 0).scene_at(1, 0.0)
    with pytest.raises(ValueError, match=r"scaled\.factor"):
        scaled(CircleScene(()), 0.0)


def test_obstacle_count_defaults_per_family():
    assert MapFamily().obstacle_count == 30 and MapFamily("corridor").obstacle_count == 5
    occ = replace(MapFamily("spec", fill=0.3), family="occupancy")  # unset count carries over
    assert occ.obstacle_count == 0 and occ.n_obstacles is None
    assert MapFamily("corridor", n_obstacles=0).obstacle_count == 0

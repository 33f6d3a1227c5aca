"""Occupancy maps: map_server PGM + YAML files (written here) and arrays become signed-distance
grids whose node values match the closed-form distance to an occupied rectangle."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from workbench.problem.sdf_grid import grid_numpy
from workbench.scenarios.occupancy import CORNER_EXCESS, OccupancyMap, load_map, read_pgm

FREE, OCC, UNKNOWN = 254, 0, 205  # what map_server's map_saver writes


def write_pgm(path: Path, image: np.ndarray, maxval: int = 255, ascii: bool = False,
              comment: bool = False) -> None:
    """image (height, width), row 0 at the top."""
    h, w = image.shape
    head = ("P2" if ascii else "P5") + ("\n# made by a test\n" if comment else "\n") \
        + f"{w} {h}\n{maxval}\n"
    if ascii:
        body = "\n".join(" ".join(str(int(v)) for v in row) for row in image).encode()
    else:
        body = image.astype(">u2" if maxval > 255 else "u1").tobytes()
    path.write_bytes(head.encode() + body)


def write_map(tmp: Path, pixels: np.ndarray, name: str = "map", **fields) -> Path:
    meta = {"image": f"{name}.pgm", "resolution": 0.25, "origin": [-1.0, 2.0, 0.0],
            "negate": 0, "occupied_thresh": 0.65, "free_thresh": 0.196}
    meta.update(fields)
    pgm = {k: meta.pop(k) for k in ("maxval", "ascii", "comment") if k in meta}
    write_pgm(tmp / f"{name}.pgm", pixels, **pgm)
    lines = [f"{k}: {v}" for k, v in meta.items() if v is not None]
    (tmp / f"{name}.yaml").write_text("\n".join(lines) + "\n")
    return tmp / f"{name}.yaml"


def cells_image(occ: np.ndarray, free: int = FREE, occupied: int = OCC) -> np.ndarray:
    """The image (row 0 at the top) of cells occ[i, j] (i along x, j along y)."""
    return np.where(np.flipud(occ.T), occupied, free)


def rect_cells(shape=(12, 9), xs=(3, 7), ys=(2, 5)) -> np.ndarray:
    occ = np.zeros(shape, dtype=bool)
    occ[xs[0]:xs[1], ys[0]:ys[1]] = True
    return occ


# ----------------------------------------------------------------- values against a closed form


@pytest.mark.parametrize("inflation", [0.0, 0.3])
def test_rectangle_distances_match_the_closed_form(inflation):
    h, origin, xs, ys = 0.25, (-1.0, 2.0), (3, 7), (2, 5)
    m = OccupancyMap(rect_cells(xs=xs, ys=ys), h, origin)
    g = m.signed_distance(inflation)
    nx, ny = m.shape
    assert g.shape == (nx, ny) and g.resolution == h
    assert g.origin == pytest.approx((origin[0] + h / 2, origin[1] + h / 2), rel=1e-15)
    i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    P = m.cell_centre(i, j)
    x0, x1 = origin[0] + xs[0] * h, origin[0] + xs[1] * h
    y0, y1 = origin[1] + ys[0] * h, origin[1] + ys[1] * h
    dx = np.maximum(np.maximum(x0 - P[..., 0], P[..., 0] - x1), 0)
    dy = np.maximum(np.maximum(y0 - P[..., 1], P[..., 1] - y1), 0)
    inside = (dx == 0) & (dy == 0)
    exact = np.where(inside, -np.minimum.reduce([P[..., 0] - x0, x1 - P[..., 0],
                                                 P[..., 1] - y0, y1 - P[..., 1]]),
                     np.hypot(dx, dy)) - inflation
    side = inside | (dx == 0) | (dy == 0)  # nearest point on an edge, not a corner
    assert side.sum() > 40 and (~side).sum() > 20
    np.testing.assert_allclose(g.values[side], exact[side], rtol=1e-12, atol=1e-12)
    over = g.values[~side] - exact[~side]  # towards a corner: optimistic, bounded
    assert np.all(over >= 0) and np.all(over <= CORNER_EXCESS * h * (1 + 1e-12))
    assert over.max() > 0.5 * CORNER_EXCESS * h  # the bound is nearly reached
    # between a free and an occupied neighbour the interpolated grid crosses 0 on their edge
    edge = np.array([[x0, (y0 + y1) / 2], [(x0 + x1) / 2, y1], [x1, y0 + h / 2]])
    np.testing.assert_allclose(grid_numpy(edge, g.row(), g.shape), -inflation, atol=1e-12)


def test_a_map_needs_occupied_and_free_cells():
    for occ in (np.zeros((4, 4), bool), np.ones((4, 4), bool)):
        with pytest.raises(ValueError, match="at least one occupied and one free"):
            OccupancyMap(occ, 0.1).signed_distance()
    with pytest.raises(ValueError, match="inflation"):
        OccupancyMap(rect_cells(), 0.1).signed_distance(-0.1)


def test_arrays_of_probabilities_use_the_threshold():
    p = np.array([[0.0, 0.5, 0.51], [1.0, 0.2, 0.7]])
    assert OccupancyMap.from_array(p, 0.1).occupied.tolist() == [[False, False, True],
                                                                  [True, False, True]]
    assert OccupancyMap.from_array(p, 0.1, threshold=0.6).occupied.tolist() == [
        [False, False, False], [True, False, True]]
    with pytest.raises(ValueError, match=r"occupancy = .*probabilities in \[0, 1\]"):
        OccupancyMap.from_array(p + 0.5, 0.1)
    with pytest.raises(ValueError, match="threshold"):
        OccupancyMap.from_array(p, 0.1, threshold=1.5)
    with pytest.raises(ValueError, match=r"OccupancyMap.resolution"):
        OccupancyMap.from_array(p > 0.5, 0.0)
    with pytest.raises(ValueError, match=r"OccupancyMap.occupied"):
        OccupancyMap(np.zeros((1, 5), bool), 0.1)


# ----------------------------------------------------------------- files


@pytest.mark.parametrize("pgm", [{}, {"ascii": True}, {"maxval": 65535}, {"comment": True}])
def test_files_load_with_the_image_upside_down_and_the_origin_at_the_lower_left(tmp_path, pgm):
    occ = rect_cells()
    occ[0, 8] = True  # top-left cell: catches a flipped or transposed image
    img = cells_image(occ)
    if pgm.get("maxval"):
        img = np.where(img == FREE, 65535 - 257, 0)
    m = load_map(write_map(tmp_path, img, **pgm))
    assert m.occupied.shape == (12, 9) and np.array_equal(m.occupied, occ)
    assert m.resolution == 0.25 and m.origin == (-1.0, 2.0)
    ref = OccupancyMap(occ, 0.25, (-1.0, 2.0)).signed_distance(0.2)
    np.testing.assert_array_equal(m.signed_distance(0.2).values, ref.values)


def test_thresholds_negate_and_unknown_cells(tmp_path):
    # p = (255 - v) / 255: 89 -> 0.651 occupied, 90 -> 0.647 unknown, 205 -> 0.1961 unknown,
    # 206 -> 0.192 free (occupied_thresh 0.65, free_thresh 0.196)
    row = np.array([[89, 90, 205, 206, 0, 255]])
    img = np.vstack([row, row])
    want_occ = [True, True, True, False, True, False]
    want_free = [True, False, False, False, True, False]
    m = load_map(write_map(tmp_path, img))
    assert m.occupied[:, 0].tolist() == want_occ
    assert load_map(write_map(tmp_path, img), unknown="free").occupied[:, 0].tolist() == \
        want_free
    neg = load_map(write_map(tmp_path, 255 - img, negate=1), unknown="free")
    assert neg.occupied[:, 0].tolist() == want_free
    scale = load_map(write_map(tmp_path, img, mode="scale"))
    assert scale.occupied[:, 0].tolist() == want_occ
    with pytest.raises(ValueError, match="unknown = 'maybe'"):
        load_map(write_map(tmp_path, img), unknown="maybe")


def test_raw_mode_reads_percentages(tmp_path):
    img = np.array([[0, 19, 20, 64, 66, 100, 101, 255]] * 2)
    m = load_map(write_map(tmp_path, img, mode="raw", free_thresh=0.2), unknown="free")
    assert m.occupied[:, 0].tolist() == [False, False, False, False, True, True, False, False]
    m = load_map(write_map(tmp_path, img, mode="raw", free_thresh=0.2))
    assert m.occupied[:, 0].tolist() == [False, False, True, True, True, True, True, True]


IMG = cells_image(rect_cells())


@pytest.mark.parametrize(("fields", "match"), [
    ({"origin": "[0.0, 0.0, 0.5]"}, r"map.yaml: origin = .*yaw other than 0"),
    ({"origin": "[0.0, 0.0]"}, r"origin = .*\[x, y, yaw\]"),
    ({"resolution": None}, r"map.yaml: resolution = None is invalid: missing"),
    ({"resolution": 0}, r"resolution = 0 is invalid: must be > 0"),
    ({"resolution": "fine"}, r"resolution = 'fine' is invalid: must be a number"),
    ({"negate": 2}, r"negate = 2 is invalid: must be 0 or 1"),
    ({"free_thresh": 0.7}, r"free_thresh = 0.7 is invalid: must be <= occupied_thresh"),
    ({"occupied_thresh": 1.5}, r"occupied_thresh = 1.5 is invalid"),
    ({"mode": "fuzzy"}, r"mode = 'fuzzy' is invalid"),
    ({"colour": "red"}, r"map.yaml: colour = 'red' is invalid: unknown field"),
    ({"image": "nowhere.pgm"},
     r"map.yaml: image = 'nowhere.pgm' is invalid: .*nowhere.pgm.* cannot be read"),
])
def test_bad_yaml_fields_are_refused_by_file_and_field(tmp_path, fields, match):
    with pytest.raises(ValueError, match=match):
        load_map(write_map(tmp_path, IMG, **fields))


def test_bad_files_are_refused(tmp_path):
    with pytest.raises(ValueError, match=r"map file = .*missing.yaml.* cannot be read"):
        load_map(tmp_path / "missing.yaml")
    (tmp_path / "list.yaml").write_text("- 1\n- 2\n")
    with pytest.raises(ValueError, match="must hold a YAML mapping"):
        load_map(tmp_path / "list.yaml")
    (tmp_path / "bad.yaml").write_text("image: [unclosed\n")
    with pytest.raises(ValueError, match="is not valid YAML"):
        load_map(tmp_path / "bad.yaml")
    p = tmp_path / "x.pgm"
    p.write_bytes(b"P6\n2 2\n255\n" + bytes(12))
    with pytest.raises(ValueError, match="not a PGM image"):
        read_pgm(p)
    p.write_bytes(b"P5\n4 4\n255\n" + bytes(10))
    with pytest.raises(ValueError, match="holds 10 bytes of pixels, 16 expected"):
        read_pgm(p)
    p.write_bytes(b"P5\n4 4")
    with pytest.raises(ValueError, match="truncated or malformed PGM header"):
        read_pgm(p)
    p.write_bytes(b"P2\n2 2\n100\n1 2 3 101\n")
    with pytest.raises(ValueError, match="pixel value 101 above maxval 100"):
        read_pgm(p)
    p.write_bytes(b"P2\n2 2\n100\n1 2 x 4\n")
    with pytest.raises(ValueError, match="4 whole numbers expected"):
        read_pgm(p)
    write_pgm(tmp_path / "one.pgm", np.zeros((1, 5), int))
    (tmp_path / "one.yaml").write_text("image: one.pgm\nresolution: 0.1\norigin: [0, 0, 0]\n"
                                       "negate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.2\n")
    with pytest.raises(ValueError, match=r"one.yaml.*at least 2 x 2"):
        load_map(tmp_path / "one.yaml")


# ----------------------------------------------------------------- closed loop on a map file


def test_bas_mppi_and_sa_rmppi_cross_a_map_file_without_crashing(tmp_path):
    """A 6 m x 6 m map (0.5 m cells) with a 2 m block across the start-goal diagonal, robot
    radius 0.1 m: both controllers go around it and stop within 0.3 m of the goal (measured:
    BaS-MPPI after 61 steps, closest 0.15 m; SA-RMPPI after 33 steps, closest 0.09 m; 32
    samples, horizon 15, dt 0.1; a limit of 80 steps)."""
    import workbench as wb
    from workbench.sampling.mppi import MPPIConfig
    from workbench.sampling.threshold import AlphaRule
    from workbench.scenarios.navigation import navigation_setup
    from workbench.scenarios.scenes import ObstacleScene

    occ = np.zeros((12, 12), dtype=bool)
    occ[4:8, 4:8] = True
    path = write_map(tmp_path, cells_image(occ), resolution=0.5, origin=[0.0, 0.0, 0.0])
    grid = load_map(path).signed_distance(inflation=0.1)
    assert grid.shape == (12, 12) and grid.values.min() == pytest.approx(-0.1 - 0.75)
    scene = ObstacleScene((grid,), start=(0.75, 0.75), goal=(5.25, 5.25), dt=0.1)
    nav = navigation_setup(scene, mppi=MPPIConfig(n_samples=32, horizon=15, sigma=(5.0, 5.0),
                                                  lam=10.0))
    assert nav.plant.scene_layout is not None and nav.plant.scene_layout.grid == (12, 12)
    diagonal = np.linspace(nav.x0, nav.goal, 50)  # the straight line crosses the block
    assert min(float(nav.plant.margins(x)[0]) for x in diagonal) < -0.5
    for name in ("bas_mppi", "sa_rmppi"):
        ctrl = nav.controller(name, rule=AlphaRule(calibration_steps=20))
        ep = wb.closed_loop(ctrl, nav.plant, nav.x0, 80, np.random.default_rng(1),
                            np.random.default_rng(2), stop_at_goal=0.3, goal=nav.goal)
        assert not ep.crashed and ep.min_margin > 0, name
        assert ep.reached_goal and len(ep.U) < 80, name
        assert np.linalg.norm(ep.X[-1, :2] - nav.goal[:2]) <= 0.3, name

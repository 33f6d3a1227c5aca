"""Counts and scales of the scenario settings: bools refused, absurd sizes refused at once with
the field, the value and the allowed range; the occupancy cover keeps its maps with bounded
memory."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest

from workbench.sampling.threshold import AlphaRule, progress_curve
from workbench.scenarios import maps
from workbench.scenarios.maps import (
    MAX_CIRCLES,
    MAX_GRID,
    MAX_NODES,
    MapFamily,
    cover_cells,
    difficulty,
    generate,
)
from workbench.scenarios.systems import SYSTEMS
from workbench.validation import MAX_STEPS


@pytest.mark.parametrize(("kw", "message"), [
    (dict(n_obstacles=10**9), rf"^map\.n_obstacles = {10**9} is invalid: must be an integer in "
     rf"\[2, {MAX_CIRCLES}\] \(it counts the two gate circles\)$"),
    (dict(family="corridor", n_obstacles=10**6), rf"^map\.n_obstacles = {10**6} is invalid: "
     rf"must be an integer in \[0, {MAX_CIRCLES}\]$"),
    (dict(family="corridor", n_obstacles=np.True_), r"^map\.n_obstacles = True is invalid"),
    (dict(family="occupancy", grid=150), rf"^map\.grid = 150 is invalid: must be an integer in "
     rf"\[4, {MAX_GRID}\]$"),
    (dict(moving=True), r"^map\.moving = True is invalid"),
])
def test_map_counts_are_bounded(kw, message):
    """Before: n_obstacles = 10**9 was accepted and generate() spent seconds drawing before
    failing; grid = 150 was accepted (its cover needed gigabytes)."""
    t0 = time.perf_counter()
    with pytest.raises(ValueError, match=message):
        MapFamily(**kw)
    assert time.perf_counter() - t0 < 5


def test_the_difficulty_grid_is_bounded():
    """Before: resolution 1e-7 tried to allocate a 10^8 x 10^8 grid (MemoryError after ~10 s,
    or swapping)."""
    with pytest.raises(ValueError, match=r"^difficulty\.resolution = 1\.e-07 is invalid: gives "
                       rf"a grid of 1e\+16 nodes over the box .*, above the limit {MAX_NODES}; "
                       "use a coarser resolution$"):
        difficulty([(5.0, 5.0, 1.0)], (0.5, 0.5), (9.5, 9.5), resolution=1e-7)
    with pytest.raises(ValueError, match=r"gives a grid of inf nodes"):
        difficulty([], (0.5, 0.5), (9.5, 9.5), resolution=5e-324)
    d = difficulty([(5.0, 5.0, 1.0)], (0.5, 0.5), (9.5, 9.5), resolution=0.01)  # 10^6 nodes
    assert d.bottleneck > 0


def _cover_reference(occ, h):
    """The cover as first written (all pairwise distances at once, recount every pick)."""
    idx = np.argwhere(occ)
    if not idx.size:
        return np.zeros((0, 3))
    P = (idx + 0.5) * h
    pad = np.pad(occ, 1, constant_values=False)
    F = (np.argwhere(~pad) - 1 + 0.5) * h
    dx = np.maximum(np.abs(P[:, None, 0] - F[None, :, 0]) - h / 2, 0.0)
    dy = np.maximum(np.abs(P[:, None, 1] - F[None, :, 1]) - h / 2, 0.0)
    R = np.maximum(np.hypot(dx, dy).min(axis=1), h / np.sqrt(2))
    corners = P[:, None, :] + h / 2 * np.array([[-1, -1], [-1, 1], [1, -1], [1, 1]])
    far = np.hypot(P[:, None, None, 0] - corners[None, :, :, 0],
                   P[:, None, None, 1] - corners[None, :, :, 1]).max(axis=2)
    M = far <= R[:, None] + 1e-9 * h
    todo = np.ones(idx.shape[0], dtype=bool)
    chosen = []
    while todo.any():
        c = int(np.argmax(M[:, todo].sum(axis=1)))
        chosen.append(c)
        todo &= ~M[c]
    return np.column_stack([P[chosen], R[chosen]])


def test_the_blocked_cover_gives_the_same_circles(monkeypatch):
    """Guard (passes before the change too): blocks of distances and the running count of
    newly covered cells pick exactly the circles of the all-at-once version, so every
    occupancy map is unchanged."""
    rng = np.random.default_rng(5)
    grids = [rng.random((g, g)) < f for g, f in ((7, 0.5), (23, 0.3), (31, 0.6), (12, 0.9))]
    for occ in grids:
        np.testing.assert_array_equal(cover_cells(occ, 0.5), _cover_reference(occ, 0.5))
    monkeypatch.setattr(maps, "_CHUNK", 97)  # many small blocks
    for occ in grids:
        np.testing.assert_array_equal(cover_cells(occ, 0.5), _cover_reference(occ, 0.5))
    m = generate(MapFamily("occupancy"), 3)
    assert m.difficulty.bottleneck > 0 and len(m.circles) > 0


@pytest.mark.parametrize(("field", "value", "message"), [
    ("sigma", (1e-200, 1.0), r"^System\.sigma\[0\] = 1\.e-200 is invalid: must be a finite "
     r"number in \[1\.492e-154, 6\.704e\+153\]"),
    ("sigma", (True, 1.0), r"^System\.sigma = \(True, 1\.0\) is invalid: must be numbers, not "
     "true/false$"),
    ("lam", 1e-320, r"^System\.lam = 1\.e-320 is invalid: must be a finite number in "
     r"\[2\.225e-308, 4\.494e\+307\]"),
    ("lam", True, r"^System\.lam = True is invalid"),
    ("Q", (1.0, True, 1.0, 1.0), r"^System\.Q = \(1\.0, True, 1\.0, 1\.0\) is invalid"),
])
def test_system_sampler_scales_are_checked_like_the_sampler_settings(field, value, message):
    """Before: a sigma of 1e-200 (squared: 0), a lambda of 1e-320 (reciprocal: inf) and
    sigma (True, 1) were accepted."""
    with pytest.raises(ValueError, match=message):
        dataclasses.replace(SYSTEMS["double_integrator"], **{field: value})


def test_calibration_steps_and_curve_bins_are_bounded():
    with pytest.raises(ValueError, match=rf"^AlphaRule\.calibration_steps = {10**12} is invalid:"
                       rf" must be an integer in \[10, {MAX_STEPS}\]$"):
        AlphaRule(calibration_steps=10**12)
    with pytest.raises(ValueError, match=r"^AlphaRule\.calibration_steps = True is invalid"):
        AlphaRule(calibration_steps=True)
    d, F = np.linspace(0.1, 10.0, 50), np.linspace(1.0, 100.0, 50)
    with pytest.raises(ValueError, match=r"^bins = 1000000000000 is invalid: must be an "
                       r"integer in \[1, 10000\]$"):
        progress_curve(d, F, bins=10**12)
    assert progress_curve(d, F, bins=5)[0].size == 5


def test_a_start_on_a_circle_is_named_as_on_its_boundary():
    from workbench.scenarios.scenes import CircleScene

    with pytest.raises(ValueError, match=r"CircleScene\.start.*on the boundary of circle 0"):
        CircleScene(circles=((1.0, 0.0, 0.5),), start=(0.5, 0.0), goal=(3.0, 0.0))


def test_a_navigation_start_within_the_crash_margin_is_named():
    """A start within the barrier's crash margin eps_h of an obstacle (h = 1e-9 > 0) is refused
    when the set-up is built: the first step would count every sample as crashed."""
    from workbench.scenarios.navigation import navigation_setup
    from workbench.scenarios.scenes import CircleScene

    scene = CircleScene(circles=((1.0, 0.0, 0.5),), start=(0.5 - 1e-9, 0.0), goal=(3.0, 0.0))
    with pytest.raises(ValueError, match=r"scene\.start.*within 1e-06 of the boundary"):
        navigation_setup(scene)

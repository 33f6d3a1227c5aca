"""The arena on maps given as a signed-distance grid (family occupancy_grid): the plant is built
on the map's grid, episodes run, and the stored paths are checked against the grid."""

from __future__ import annotations

import numpy as np
import pytest

from studies.arena import STUDY
from studies.arena.config import DisturbanceSpec
from studies.arena.episodes import arena_map, setup
from studies.arena.tasks import hand_settings, where
from workbench.problem.scene_kinds import MovingCircle
from workbench.problem.sdf_grid import grid_numpy
from workbench.scenarios.maps import MapFamily
from workbench.study import RunStore
from workbench.study.runner import profile_config
from workbench.study.runner import run as run_study


def test_grid_maps_run_in_the_arena(tmp_path):
    fam = MapFamily("occupancy_grid")
    cfg = profile_config(STUDY, "tiny", controllers=("bas_mppi",),
                         systems=("double_integrator",), families=(fam,), test_maps=1,
                         realisations=1, disturbances=(DisturbanceSpec(level=10.0),))
    w = where(cfg, "double_integrator", "occupancy_grid", cfg.test_seed)
    assert w.capacity is None
    plant = setup(w, hand_settings(cfg, "double_integrator")).plant
    assert plant.scene_layout is not None and plant.scene_layout.grid == (20, 20)
    assert plant.scene_capacity == 0
    run_study(STUDY, cfg, tmp_path, workers=0, progress=False)
    store = RunStore(tmp_path)
    ep = store.table("episodes")
    assert list(ep["family"]) == ["occupancy_grid"]
    r = ep.iloc[0]
    g = arena_map(fam, int(r["map_seed"])).grid
    X = store.arrays(r["task_id"])["X"]
    h = grid_numpy(X[:, :2], g.row(), g.shape)
    assert len(X) > 10 and np.ptp(X[:, 0]) > 0.1  # it moved
    np.testing.assert_allclose(h.min(), r["min_h"], rtol=1e-9)  # the crash rule is the grid
    assert (h.min() > 0) != bool(r["crashed"])


def test_a_family_that_predicts_tells_the_controllers_the_velocities(tmp_path):
    """map.predict: the plant's scene has a moving slot per moving circle, the controllers'
    scene of each step carries the circles' true positions and velocities, and the episode's
    crash rule is the true motion (the stored path's clearance from the moving circles)."""
    fam = MapFamily("spec", moving=2, speed=0.7, predict=True)
    plain = MapFamily("spec", moving=2, speed=0.7)
    cfg = profile_config(STUDY, "tiny", controllers=("bas_mppi",),
                         systems=("double_integrator",), families=(fam,), test_maps=1,
                         realisations=1, steps=60, disturbances=(DisturbanceSpec(level=10.0),))
    w = where(cfg, "double_integrator", "spec", cfg.test_seed)
    plant = setup(w, hand_settings(cfg, "double_integrator")).plant
    assert plant.scene_layout.count("moving") == 2 and plant.scene_capacity == 0
    m = arena_map(fam, w.seed)
    assert m.circles == arena_map(plain, w.seed).circles  # the same maps
    scene = w.moving(plant.dt)(5)
    moving = [o for o in scene if isinstance(o, MovingCircle)]
    assert len(moving) == 2 and all(np.hypot(*o.velocity) == pytest.approx(0.7)
                                    for o in moving)
    truth = m.scene_at(5, plant.dt)
    assert {o.center for o in moving} <= {c.center for c in truth}
    run_study(STUDY, cfg, tmp_path, workers=0, progress=False)
    store = RunStore(tmp_path)
    r = store.table("episodes").iloc[0]
    X = store.arrays(r["task_id"])["X"]
    h = [min(np.hypot(*(X[k, :2] - np.asarray(c.center))) ** 2 - c.radius ** 2
             for c in m.scene_at(k, plant.dt)) for k in range(len(X))]
    np.testing.assert_allclose(min(h), r["min_h"], rtol=1e-9)


def test_predict_needs_moving_circles():
    with pytest.raises(ValueError, match=r"^map\.predict = True .*map\.moving > 0"):
        MapFamily("spec", predict=True)
    with pytest.raises(ValueError, match=r"^map\.predict"):
        MapFamily("spec", moving=1, predict="yes")

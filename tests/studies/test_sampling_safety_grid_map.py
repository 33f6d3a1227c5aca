"""The sampling-safety study on a generated map family (occupancy_grid: a signed-distance
grid): the plant is built on the map's grid, the stored paths are checked against the grid,
configs without a family keep their identity, and family settings that cannot apply are
refused."""

from __future__ import annotations

import numpy as np
import pytest

from studies.navigation.scene import MapSpec
from studies.sampling_safety import STUDY
from studies.sampling_safety.tasks import fingerprint, setup
from workbench.problem.sdf_grid import grid_numpy
from workbench.scenarios.maps import MapFamily, generate
from workbench.study import RunStore
from workbench.study.runner import profile_config
from workbench.study.runner import run as run_study

GRID = MapFamily("occupancy_grid")


def tiny(**overrides):
    return profile_config(STUDY, "tiny", **overrides)


def test_a_grid_map_runs_and_its_paths_are_checked_against_the_grid(tmp_path):
    cfg = tiny(controllers=("bas_mppi", "sa_rmppi"), family=GRID, map_seed=1,
               variances=(10.0,), realisations=1, steps=40)
    plant = setup(cfg.resolved()).plant
    assert plant.scene_layout is not None and plant.scene_layout.grid == (20, 20)
    assert fingerprint(cfg)["map_seed"] == 1 and fingerprint(cfg)["family"]["family"] == \
        "occupancy_grid"
    outcome = run_study(STUDY, cfg, tmp_path, workers=0, progress=False)
    store = RunStore(tmp_path)
    ep = store.table("episodes")
    assert sorted(ep["controller"]) == ["bas_mppi", "sa_rmppi"]
    g = generate(GRID, 1).grid
    for _, r in ep.iterrows():
        X = store.arrays(r["task_id"])["X"]
        h = grid_numpy(X[:, :2], g.row(), g.shape)
        assert len(X) > 10 and np.ptp(X[:, 0]) > 0.1
        assert h.min() == pytest.approx(float(r["min_h"]), rel=1e-9)
    assert "the generated occupancy_grid map of seed 1" in outcome.report.read_text()


def test_configs_without_a_family_keep_their_identity():
    fp = fingerprint(tiny())
    assert "family" not in fp and "map_seed" not in fp


@pytest.mark.parametrize("overrides, match", [
    ({"family": GRID, "scene": MapSpec()}, r"^family = 'occupancy_grid' .*not both"),
    ({"map_seed": 3}, r"^map_seed = 3 .*set family"),
    ({"family": MapFamily("corridor", moving=2)}, r"^family = 'corridor' .*moving = 0"),
    ({"family": GRID, "map_seed": -1}, r"^map_seed"),
    ({"family": "occupancy_grid"}, r"^family = 'occupancy_grid' .*MapFamily"),
])
def test_family_settings_that_cannot_apply_are_refused(overrides, match):
    with pytest.raises(ValueError, match=match):
        tiny(**overrides)

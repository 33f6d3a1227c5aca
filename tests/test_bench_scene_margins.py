"""The scene-margin benchmark (benchmarks/scene_margins.py) at tiny sizes: every figure is
measured and recorded, the 3-D model's margins are its spheres', bad settings are refused."""

from __future__ import annotations

import json

import numpy as np
import pytest

from benchmarks.scene_margins import (
    SceneBenchConfig,
    circles_grid,
    double_integrator_3d,
    main,
)
from workbench.problem.scene_kinds import Sphere
from workbench.problem.scene_layout import SceneLayout


@pytest.mark.parametrize("field, kw", [
    ("SceneBenchConfig.samples", {"samples": 2}),
    ("SceneBenchConfig.repeats", {"repeats": 0}),
    ("SceneBenchConfig.grid_sizes", {"grid_sizes": (50, 1)}),
    ("SceneBenchConfig.obstacles", {"obstacles": (4, 2)}),
    ("SceneBenchConfig.many_obstacles", {"many_obstacles": 2})])
def test_config_refuses_bad_values(field, kw):
    with pytest.raises(ValueError, match=field):
        SceneBenchConfig(**kw)


def test_the_3d_model_has_one_margin_per_sphere():
    lay = SceneLayout(3, (("spheres", 2),))
    m = double_integrator_3d(lay, [Sphere((1.0, 2.0, 3.0), 0.5)])
    x = np.array([1.0, 2.0, 4.0, 0, 0, 0])
    h = np.asarray(m.margins(x)).ravel()
    assert h[0] == pytest.approx(1.0 - 0.25) and h[1] > 1e10  # a used and an unused slot


def test_circles_grid_is_the_signed_distance_at_the_nodes():
    g = circles_grid(11, [(5.0, 5.0, 1.0)])
    assert g.resolution == pytest.approx(1.0)
    assert g.values[5, 5] == pytest.approx(-1.0) and g.values[0, 5] == pytest.approx(4.0)


def test_the_benchmark_writes_every_record(tmp_path, monkeypatch):
    import benchmarks.scene_margins as sm

    tiny = SceneBenchConfig(samples=8, horizon=2, repeats=1, grid_sizes=(3, 4),
                            grid_vs_circle_size=3, occupancy_size=4, many_obstacles=5,
                            obstacles=(1, 2))
    real = sm.records
    monkeypatch.setattr(sm, "records", lambda repeats: real(repeats, tiny))
    out = tmp_path / "scene.json"
    main(["--out", str(out), "--repeats", "1"])
    data = json.loads(out.read_text())
    names = {r["name"] for r in data["records"]}
    assert names == {"scene_grid_margin_ns_per_sample_step", "scene_grid_occupancy_many_vs_few",
                     "scene_spheres_vs_circles_per_obstacle_n2", "scene_grid_sais_3x3",
                     "scene_grid_sais_3x3_spread", "scene_grid_sais_4x4",
                     "scene_grid_sais_4x4_spread"}
    for r in data["records"]:
        assert r["value"] is not None and r["value"] == r["value"], r["name"]
    occ = next(r for r in data["records"] if r["name"].endswith("many_vs_few"))["params"]
    assert occ["maps"]["many"]["occupied_share"] >= occ["maps"]["few"]["occupied_share"]
    assert data["machine"]["cpu"]

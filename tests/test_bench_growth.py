"""The growth-curve benchmark (benchmarks/growth.py) at tiny sizes: it measures every series on
every axis, fits the lines, writes growth.json and growth.png, and renders the report section."""

from __future__ import annotations

import json

import numpy as np
import pytest

from benchmarks.growth import GrowthConfig, circle_map, growth, linear_fit, markdown


def test_linear_fit_recovers_a_line_and_its_exponent():
    x = np.array([1.0, 3.0, 10.0, 30.0, 100.0])
    f = linear_fit(x, 0.25 * x + 2.0)
    assert f["slope"] == pytest.approx(0.25) and f["intercept"] == pytest.approx(2.0)
    assert f["r2"] == pytest.approx(1.0)
    assert linear_fit(x, 3.0 * x)["loglog_exponent"] == pytest.approx(1.0)
    assert linear_fit(x, x**2)["loglog_exponent"] == pytest.approx(2.0)
    assert linear_fit([5.0], [1.0])["slope"] is None


def test_circle_map_places_n_circles_clear_of_start_and_goal():
    for n in (1, 30, 300):
        scene = circle_map(n)
        circles = scene.obstacles()
        assert len(circles) == n
        for c in circles:
            for end in (scene.start, scene.goal):
                assert np.linalg.norm(np.subtract(end, c.center)) > c.radius
    assert circle_map(30) == circle_map(30)  # seeded


@pytest.mark.parametrize("field, kw", [
    ("GrowthConfig.samples", {"samples": (64, 32)}),
    ("GrowthConfig.circles", {"circles": ()}),
    ("GrowthConfig.repeats", {"repeats": 0}),
    ("GrowthConfig.threads", {"threads": 0})])
def test_growth_config_refuses_bad_values(field, kw):
    with pytest.raises(ValueError, match=field):
        GrowthConfig(**kw)


def test_growth_writes_curves_fits_figure_and_report(tmp_path):
    cfg = GrowthConfig(samples=(16, 32), horizons=(3, 5), circles=(2, 3), base_samples=16,
                       base_horizon=4, repeats=1, step_steps=1, fit_from_circles=1)
    data = growth(cfg, tmp_path)
    on_disk = json.loads((tmp_path / "growth.json").read_text())
    assert on_disk["axes"].keys() == {"samples", "horizon", "circles"}
    assert (tmp_path / "growth.png").stat().st_size > 10_000
    for axis, xs in (("samples", cfg.samples), ("horizon", cfg.horizons),
                     ("circles", cfg.circles)):
        a = on_disk["axes"][axis]
        assert a["x"] == list(xs)
        want = {"sais_batch", "bas_mppi_step", "floor_sais"}
        if axis != "circles":
            want.add("sa_rmppi_step")
        else:  # the loop-over-circles kernels beside the straight-line ones
            want |= {"sais_batch_loop", "bas_mppi_step_loop"}
        assert set(a["series"]) == want
        for name, ys in a["series"].items():
            assert len(ys) == len(xs) and all(y > 0 for y in ys), (axis, name)
            assert a["fits"][name]["slope"] is not None
    assert set(on_disk["compile"]) == {"2", "3"}
    assert all(v["library_bytes"] > 0 for v in on_disk["compile"].values())
    s = on_disk["summary"]["sais_batch"]
    assert s["ms_per_circle"] is not None and s["us_per_sample"] is not None
    md = markdown(data)
    assert "growth.png" in md and "ms per circle" in md and "| 2 |" in md

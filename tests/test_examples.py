"""The examples run as a user runs them (``python examples/NAME.py``) and do what they say:
their printed numbers are parsed and checked."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).parents[1]
NUM = r"(-?[\d.]+)"


def run_example(name: str) -> str:
    r = subprocess.run([sys.executable, str(ROOT / "examples" / name)], capture_output=True,
                       text=True, timeout=300, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    assert "Warning" not in r.stderr, r.stderr  # e.g. no fallback from the compiled kernels
    return r.stdout


def test_own_model_through_bas_ilqg_and_the_sampler():
    out = run_example("own_model.py")
    plan = re.search(rf"BaS-iLQG: converged (\w+), cost {NUM}, min h {NUM}, final error {NUM} m",
                     out)
    drive = re.search(rf"BaS-MPPI: crashed (\w+), min h {NUM}, final error {NUM} m, compiled "
                      rf"kernels (\w+), {NUM} ms per step", out)
    assert plan and drive, out
    assert plan[1] == "True" and float(plan[3]) > 0.05 and float(plan[4]) < 0.05
    assert 0 < float(plan[2]) < 100
    # closed loop from (0, 0) to (4.5, 0.5) past both circles in 7.5 s, never touching them
    assert drive[1] == "False" and float(drive[2]) > 0.0 and float(drive[3]) < 0.3
    assert drive[4] == "True"  # the sampler ran on kernels generated from the user's model


def test_custom_scene_through_sa_rmppi():
    out = run_example("custom_scene.py")
    rows = dict(re.findall(r"^(\w+)\s+crashed (.*)$", out, re.M))
    assert set(rows) == {"sa_rmppi", "bas_mppi"}, out
    pat = rf"(\w+), (\d+) steps, min h {NUM}, final error {NUM} m, robust part active (\d+)%"
    sa = re.match(pat, rows["sa_rmppi"])
    bas = re.match(pat, rows["bas_mppi"])
    assert sa and bas, out
    for r in (sa, bas):  # safe, at the goal of the user's map
        assert r[1] == "False" and r[2] == "350" and float(r[3]) > 0 and float(r[4]) < 0.3
    # SA-RMPPI's robust part acts on some steps under the disturbance; BaS-MPPI has none
    assert 5 <= int(sa[5]) <= 80 and int(bas[5]) == 0


def test_own_model_robust_bicycle_under_a_speed_disturbance():
    import json

    out = run_example("own_model_robust.py")
    res = json.loads(out.strip().splitlines()[-1])
    assert set(res) == {"bas_ilqg", "bas_mppi", "rmppi", "sa_rmppi"}, out
    sa = res["sa_rmppi"]
    assert sa["crashed"] is False and sa["steps"] == 150 and sa["final_distance"] < 0.5
    # the robust part acts on some of SA-RMPPI's steps, not all; K_safe never falls back
    assert 0.1 <= sa["nominal_differs"] <= 0.9 and sa["ksafe_fallback"] < 0.01
    assert 0.0 < res["rmppi"]["nominal_differs"] < 1.0
    assert res["bas_mppi"]["nominal_differs"] is None  # no robust part to act


def test_moving_obstacle_without_recompiling():
    """A circle moves across the path: the scene changes every step with no library built,
    in well under a millisecond; the crash check follows the moving circle (the controller
    that is never told the scene moves hits it, the two that are told do not)."""
    import json

    out = run_example("moving_obstacle.py")
    res = json.loads(out.strip().splitlines()[-1])
    assert res["recompiles"] == 0 and 0 < res["scene_update_ms"] < 1.0, out
    assert res["crashed"] == {"bas_mppi": False, "sa_rmppi": False, "bas_mppi_blind": True}, out
    assert res["steps"]["bas_mppi"] == res["steps"]["sa_rmppi"] == 250
    assert res["steps"]["bas_mppi_blind"] < 250 and res["min_margin"]["bas_mppi_blind"] <= 0
    assert set(res["step_ms"]) == set(res["crashed"]) and 0 < res["nominal_differs"] < 1


def test_set_threads_reaches_every_library_loaded_before_and_after():
    import pytest

    from workbench import sampling
    from workbench.sampling.kernels.library import sampler_library
    from workbench.scenarios.navigation import navigation_setup
    from workbench.scenarios.scenes import CircleScene

    first = sampler_library(navigation_setup().problem)
    if first is None:
        pytest.skip("no C compiler: no sampler libraries to set")
    sampling.set_threads(1)
    assert first.cdll.wb_get_threads() == 1 and sampling.get_threads() == 1
    later = sampler_library(navigation_setup(CircleScene([(2.0, 2.0, 0.5)])).problem)
    assert later.cdll.wb_get_threads() == 1
    sampling.set_threads(2)
    assert first.cdll.wb_get_threads() == later.cdll.wb_get_threads() == 2
    for bad in (0, 1.5, True):
        with pytest.raises(ValueError, match="threads"):
            sampling.set_threads(bad)


def test_circle_scene_checks_its_input():
    import pytest

    from workbench.problem.obstacles import Circle
    from workbench.scenarios.scenes import CircleScene

    s = CircleScene.from_circles([(1, 2, 0.5), Circle((3, 3), 1.0)], start=(0, 0), goal=(5, 5))
    assert s.obstacles() == (Circle((1, 2), 0.5), Circle((3, 3), 1.0))
    with pytest.raises(ValueError, match=r"CircleScene.goal .* inside circle 1"):
        CircleScene([(1, 2, 0.5), (5, 5, 1.0)], goal=(5.2, 5.0))
    with pytest.raises(ValueError, match=r"CircleScene.circles\[0\]"):
        CircleScene([(1, 2)])
    with pytest.raises(ValueError, match=r"Circle\.radius"):
        CircleScene([(1, 2, -1)])

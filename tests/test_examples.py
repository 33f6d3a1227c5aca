"""The examples run as a user runs them (``python examples/NAME.py``) and do what they say:
their printed numbers are parsed and checked, and the figures the README quotes from them are
what they print, at the tolerance marked beside each (``<!-- figure: ... -->``, see
``tests/shown_output.py``). Each example runs once per session."""

from __future__ import annotations

import functools
import re
import subprocess
import sys
from pathlib import Path

import shown_output  # tests/shown_output.py

ROOT = Path(__file__).parents[1]
README = ROOT / "README.md"
NUM = r"(-?[\d.]+)"
EXAMPLES = ("own_model.py", "custom_scene.py", "own_model_robust.py", "moving_obstacle.py")


@functools.cache
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


def readme_problems(path: Path = README) -> list[str]:
    """Where the README at ``path`` quotes a figure other than its example prints."""
    found = shown_output.figures(path, "README.md")
    assert {f.example for f in found} <= set(EXAMPLES), "a figure of an example not run here"
    return [p for f in found for p in f.check(run_example(f.example))]


def test_readme_figures_are_what_the_examples_print():
    """Every example the README describes has its quoted figures marked and checked (the
    examples' runs above are reused)."""
    found = shown_output.figures(README, "README.md")
    assert {f.example for f in found} == set(EXAMPLES) - {"moving_obstacle.py"}, found
    problems = readme_problems()
    assert not problems, "\n".join(problems)


def test_a_readme_figure_edited_beyond_its_tolerance_is_reported(tmp_path):
    text = README.read_text()
    old = "final error ≈ 0.09 m<!-- figure: own_model.py"
    assert text.count(old) == 1
    path = tmp_path / "README.md"
    path.write_text(text.replace(old, old.replace("0.09", "0.25")))
    [problem] = readme_problems(path)
    line = text[:text.index(old)].count("\n") + 1
    assert problem.startswith(f"README.md, line {line}: figure 0.25 is printed by own_model.py "
                              "as ") and "beyond its tolerance (rtol=0, atol=0.1)" in problem
    path.write_text(text.replace(old, old.replace("0.09", "0.15")))  # within 0.1
    assert readme_problems(path) == []


def test_figure_markers_are_read_as_written(tmp_path):
    page = tmp_path / "page.md"
    page.write_text('acts on ≈ 38%<!-- figure: x.py json:a.b scale=100 atol=10 --> of steps;\n'
                    'syntax: `<!-- figure: x.py "y {}" exact -->` (quoted, not a marker)\n')
    [figure] = shown_output.figures(page)
    assert (figure.value, figure.pattern, figure.line) == ("38", "json:a.b", 1)
    assert figure.check('noise\n{"a": {"b": 0.44}}') == []
    [problem] = figure.check('{"a": {"b": 0.52}}')
    assert problem == ("page.md, line 1: figure 38 is printed by x.py as 52, beyond its "
                       "tolerance (rtol=0, atol=10)")


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
    with pytest.raises(ValueError, match=r"CircleScene\.circles\[0\] .*radius .* must be > 0"):
        CircleScene([(1, 2, -1)])

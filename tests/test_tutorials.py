"""The three tutorials of the documentation site run as a reader runs them, and print what their
pages show.

Each page's ```python blocks run in order in one namespace (in a temporary directory), with
their printed output captured per block. The ```text block after a python block is what that
block prints, marked with its tolerance in an HTML comment just above it, e.g.
``<!-- output: rtol=0.01 atol=0.001; "final error {} m": atol=0.1; "{} ms per step":
unchecked -->``: the first clause (``exact``, or ``rtol=R atol=A``: a number passes when
``|printed - shown| <= max(R * |shown|, A)``) holds for every number of the block; each
``"PATTERN": TOLERANCE`` clause overrides it for the numbers at ``{}`` in that quoted text;
``unchecked`` is for numbers that vary by machine, such as timings. Text other than numbers
must match exactly, modulo whitespace. A text block right after a python block without a
marker fails, as does a pattern that matches no number. The syntax in full, and the
``<!-- figure: ... -->`` marker for numbers quoted in prose, is in ``tests/shown_output.py``.
Beyond the shown numbers, the claims the pages make of them are checked here too.

To choose a tolerance, rerun the page as another machine would, e.g. with
``OPENBLAS_CORETYPE=Nehalem`` or ``GLIBC_TUNABLES=glibc.cpu.hwcaps=-AVX2,-FMA``: a closed loop is
chaotic, and a last-bit difference in BLAS or libm can move its final numbers far beyond their
last digit (the own-model page's closed loops do; plans, counts and the other pages' loops do
not), while runs on one machine repeat exactly.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import warnings
from pathlib import Path

import pytest
import shown_output  # tests/shown_output.py

ROOT = Path(__file__).parents[1]
TUTORIALS = ROOT / "docs" / "tutorials"
PAGES = ("own-model.md", "own-map-study.md", "moving-obstacle.md", "compare-on-your-model.md",
         "occupancy-map.md")
NUM = r"(-?[\d.]+)"


def blocks(page: str, path: Path | None = None) -> list[tuple[str, shown_output.Shown | None]]:
    """(python code, its marked shown output or None) of each python block of a page."""
    return shown_output.page_blocks(path or TUTORIALS / page, page)


def run_page(page: str, where: Path) -> list[tuple[str, str, shown_output.Shown | None]]:
    """Run a page's blocks in one namespace in ``where``: (code, printed, shown) per block.
    Fails on any warning raised from the workbench (e.g. a fallback from compiled kernels)."""
    scope: dict = {"__name__": "__tutorial__"}
    results = []
    cwd = os.getcwd()
    os.chdir(where)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            for i, (code, shown) in enumerate(blocks(page)):
                buffer = io.StringIO()
                with contextlib.redirect_stdout(buffer):
                    exec(compile(code, f"{page}:block{i}", "exec", dont_inherit=True), scope)
                results.append((code, buffer.getvalue(), shown))
    finally:
        os.chdir(cwd)
    ours = [str(w.message) for w in caught if f"{os.sep}workbench{os.sep}" in w.filename]
    assert not ours, f"{page}: warnings from the workbench: {ours}"
    return results


def printed(results) -> str:
    """Everything a page's blocks printed."""
    return "".join(p for _, p, _ in results)


def differences(results, page: str, path: Path | None = None) -> list[str]:
    """Where the page at ``path`` (default: the tutorial) shows other than its blocks printed."""
    found = blocks(page, path)
    assert [c for c, _ in found] == [c for c, _, _ in results], f"{page}: blocks changed"
    pairs = zip(found, results, strict=True)
    return [p for (_, shown), (_, got, _) in pairs if shown
            for p in shown_output.compare(shown, got)]


def check_shown_output(results, page: str) -> None:
    assert any(shown for _, _, shown in results), f"{page}: no output block"
    problems = differences(results, page)
    assert not problems, "\n".join(problems)


@pytest.fixture(scope="module")
def own_model(tmp_path_factory):
    return run_page("own-model.md", tmp_path_factory.mktemp("tutorial1"))


def test_every_tutorial_page_has_python_blocks_and_outputs():
    for page in PAGES:
        found = blocks(page)
        assert found and any(shown for _, shown in found), page


def test_tutorial_own_model(own_model):
    check_shown_output(own_model, "own-model.md")
    out = printed(own_model)
    plans = dict(re.findall(r"^(iLQG|BaS-iLQG)\s+(converged .*)$", out, re.M))
    pat = rf"converged (\w+), min h {NUM}, final error {NUM} m"
    ilqg, bas = (re.match(pat, plans[k]) for k in ("iLQG", "BaS-iLQG"))
    assert ilqg and bas, out
    # plain iLQG rides the first circle's boundary (no margin); BaS-iLQG keeps a margin and
    # gets there
    assert ilqg[1] == bas[1] == "True"
    assert 0.0 <= float(ilqg[2]) < 0.01
    assert float(bas[2]) > 0.05 and float(bas[3]) < 0.05
    drive = re.search(rf"BaS-MPPI undisturbed: crashed (\w+), min h {NUM}, final error {NUM} m, "
                      r"compiled kernels (\w+)", out)
    assert drive and drive[1] == "False" and float(drive[2]) > 0 and float(drive[3]) < 0.3, out
    assert drive[4] == "True"  # the sampler ran on kernels generated from the page's model
    rows = {m[0]: m[1:] for m in re.findall(
        rf"^(BaS-MPPI|SA-RMPPI): (\d+) of (\d+) crashed, median final error {NUM} m, robust "
        rf"part active on (\d+)% of the steps, {NUM} ms per step$", out, re.M)}
    assert set(rows) == {"BaS-MPPI", "SA-RMPPI"}, out
    for crashes, n, error, _, ms in rows.values():
        assert int(n) == 10 and int(crashes) <= 5  # mostly safe under the mild disturbance
        assert float(error) < 0.5 and float(ms) > 0  # the safe ones end near the goal
    assert int(rows["BaS-MPPI"][3]) == 0  # no robust part
    assert 2 <= int(rows["SA-RMPPI"][3]) <= 60  # the selection acts on some steps, not all
    calibrations = [c for c, _, _ in own_model if "wb.calibrate(" in c]
    assert len(calibrations) == 1  # one threshold, shared by every realisation


@pytest.fixture(scope="module")
def own_map(tmp_path_factory):
    where = tmp_path_factory.mktemp("tutorial2")
    return run_page("own-map-study.md", where), where


def cli_command(page: str) -> list[str]:
    """The page's ```sh block marked <!-- cli -->, as an argument list."""
    import shlex

    text = (TUTORIALS / page).read_text()
    m = re.search(r"<!-- cli -->\s*```sh\n(.*?)```", text, re.S)
    assert m, f"{page}: no command-line block"
    return shlex.split(m[1].replace("\\\n", " "))


def test_tutorial_own_map_study(own_map):
    results, where = own_map
    check_shown_output(results, "own-map-study.md")
    out = printed(results)
    assert re.search(r"^8 circles from \(0\.5, 0\.5\) to \(6\.0, 6\.0\)$", out, re.M), out
    n_tasks = re.search(r"^(\d+) tasks, tasks hash ([0-9a-f]{12})$", out, re.M)
    assert n_tasks and int(n_tasks[1]) == 20, out  # 2 controllers x 2 variances x 5
    cells = re.findall(rf"^(SA-RMPPI|BaS-MPPI)\s+\S+\s+var\s+{NUM}\s+safety (\d+)% "
                       rf"\[(\d+), (\d+)\]\s+RMSE {NUM}\s+{NUM} ms/step$", out, re.M)
    assert len(cells) == 8, out  # four cells, printed after the run and after the resume
    for name, var, safety, low, high, rmse, _ in cells:
        assert int(low) <= int(safety) <= int(high) <= 100
        if float(var) == 0:  # undisturbed, both controllers are safe on the map and at the goal
            assert int(safety) == 100 and float(rmse) < 0.3, (name, var, safety, rmse)
        else:
            assert int(safety) >= 40 and float(rmse) < 1.0, (name, var, safety, rmse)
    runs = re.findall(r"^computed (\d+), loaded (\d+)", out, re.M)
    assert runs == [("20", "0"), ("0", "20")], out  # the second run resumed: nothing computed
    assert "report my_map_run/report.md" in out
    files = dict(re.findall(r"^(\S+\.\w+)\s+(True|False)$", out, re.M))
    assert len(files) == 7 and set(files.values()) == {"True"}, out
    assert (where / "my_map_run" / "episodes.parquet").is_file()
    rows = re.findall(r"^(?:(bas_mppi|sa_rmppi)\s+)?\s*(0\.0|50\.0)\s+(\d+)\s+([\d.]+)\s+"
                      r"([\d.]+)$", out, re.M)
    assert len(rows) == 4, out
    robust = [float(r[4]) for r in rows]
    crashes = [int(r[2]) for r in rows]
    assert robust[0] == robust[1] == 0.0  # BaS-MPPI has no robust part
    assert 0 <= robust[2] < robust[3] <= 350  # SA-RMPPI's acts more under the disturbance
    assert crashes[0] == crashes[2] == 0 and max(crashes) <= 3
    signed = r"([-+]?[\d.]+)"
    pairs = re.findall(r"^variance (\d+): only SA-RMPPI safe in (\d+), only BaS-MPPI safe in "
                       rf"(\d+) of (\d+); difference {signed} \[{signed}, {signed}\], "
                       rf"p = {NUM}$", out, re.M)
    assert [p[0] for p in pairs] == ["0", "50"], out
    for _, b, c, n, diff, low, high, p in pairs:
        assert int(n) == 5 and int(b) + int(c) <= 5 and 0 <= float(p) <= 1
        assert float(low) <= float(diff) <= float(high)
        assert abs(float(diff) - (int(b) - int(c)) / 5) < 1e-9


def test_tutorial_own_map_study_command_line_is_the_same_study(own_map, tmp_path):
    """The page's command, with --dry-run, describes exactly the study the Python ran."""
    import json
    import subprocess
    import sys

    results, _ = own_map
    scope_hash = re.search(r"tasks hash ([0-9a-f]{12})", printed(results))[1]
    argv = cli_command("own-map-study.md")
    assert argv[:3] == ["workbench", "run", "navigation"]
    workbench = Path(sys.executable).with_name("workbench")
    r = subprocess.run([str(workbench), *argv[1:], "--dry-run"], capture_output=True, text=True,
                       timeout=300, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    manifest = json.loads(r.stdout)
    assert manifest["n_tasks"] == 20 and manifest["tasks_sha256"][:12] == scope_hash
    assert not (tmp_path / "my_map_run").exists()  # a dry run writes nothing


@pytest.fixture(scope="module")
def moving(tmp_path_factory):
    return run_page("moving-obstacle.md", tmp_path_factory.mktemp("tutorial3"))


def test_tutorial_moving_obstacle(moving):
    import json

    check_shown_output(moving, "moving-obstacle.md")
    out = printed(moving)
    assert re.search(r"^4 circle slots; the moving circle starts at 2\.24, 1\.76$", out, re.M)
    rows = {m[0]: m[1:] for m in re.findall(
        rf"^(\w+)\s+crashed (\w+), (\d+) steps, min h {NUM}, final error {NUM} m$", out, re.M)}
    assert set(rows) == {"bas_mppi", "sa_rmppi", "bas_mppi_blind"}, out
    for name in ("bas_mppi", "sa_rmppi"):  # told that the circle moves: they pass it
        crashed, steps, min_h, error = rows[name]
        assert crashed == "False" and steps == "350" and float(min_h) > 0
        assert float(error) < 0.5, (name, error)
    crashed, steps, min_h, _ = rows["bas_mppi_blind"]  # never told: the crash check catches it
    assert crashed == "True" and int(steps) < 350 and float(min_h) <= 0
    built = re.search(rf"libraries built while driving: (\d+); a scene change takes {NUM} ms",
                      out)
    assert built and built[1] == "0" and float(built[2]) > 0, out  # no recompilation
    active = re.search(r"robust part active on (\d+)% of the steps", out)
    assert active and 0 < int(active[1]) < 100, out
    last = json.loads(out.strip().splitlines()[-1])
    assert last == {"bas_mppi": False, "sa_rmppi": False, "bas_mppi_blind": True}


@pytest.fixture(scope="module")
def compare_page(tmp_path_factory):
    where = tmp_path_factory.mktemp("tutorial4")
    return run_page("compare-on-your-model.md", where), where


def test_tutorial_compare_on_your_model(compare_page):
    results, where = compare_page
    check_shown_output(results, "compare-on-your-model.md")
    out = printed(results)
    ran = re.findall(r"^(\w+): crashed (True|False), min h", out, re.M)
    assert [r[0] for r in ran] == ["bas_mppi", "sa_rmppi", "cbf_projection", "gatekeeper"]
    cells = re.findall(r"^(\w+): safe in (\d+) of 6, reached the goal in (\d+)$", out, re.M)
    assert sorted(c[0] for c in cells) == ["bas_mppi", "gatekeeper", "mppi_crash", "sa_rmppi"]
    assert (where / "runs" / "arm" / "report.md").is_file()
    assert (where / "arm.png").stat().st_size > 10_000


def edited(tmp_path: Path, page: str, old: str, new: str) -> Path:
    """A copy of a tutorial page with its one occurrence of ``old`` replaced by ``new``."""
    text = (TUTORIALS / page).read_text()
    assert text.count(old) == 1, (page, old)
    path = tmp_path / page
    path.write_text(text.replace(old, new))
    return path


def test_tutorial_occupancy_map(tmp_path):
    results = run_page("occupancy-map.md", tmp_path)
    check_shown_output(results, "occupancy-map.md")
    out = printed(results)
    loops = re.findall(r"^(bas_mppi|sa_rmppi): crashed (True|False), reached the goal "
                       rf"(True|False) after (\d+) steps, closest approach {NUM} m$", out, re.M)
    assert [r[0] for r in loops] == ["bas_mppi", "sa_rmppi"], out
    for _, crashed, reached, steps, closest in loops:  # around the desk, not through it
        assert crashed == "False" and reached == "True" and int(steps) < 120
        assert float(closest) > 0
    cells = re.findall(r"^(bas_mppi|sa_rmppi): safe in (\d+) of (\d+)", out, re.M)
    assert sorted(c[0] for c in cells) == ["bas_mppi", "sa_rmppi"], out
    assert all(int(n) == 4 and int(k) >= 2 for _, k, n in cells), out  # mostly safe
    report = (tmp_path / "runs" / "office" / "report.md").read_text()
    assert "![the map and the paths](map.png)" in report  # the map from the file, drawn
    assert (tmp_path / "runs" / "office" / "map.png").stat().st_size > 5000


def test_a_shown_number_edited_beyond_its_tolerance_is_reported(own_model, tmp_path):
    """The plan's min h is exact: the page's old, stale 0.163 fails, naming page, block and
    number; a closed-loop error (atol 0.1) fails at 0.3 and passes at 0.15; a timing is not
    checked at all."""
    page = "own-model.md"
    assert differences(own_model, page) == []
    stale = edited(tmp_path, page, "min h 0.127, final error 0.001 m",
                   "min h 0.163, final error 0.001 m")
    [problem] = differences(own_model, page, stale)
    assert problem.startswith(f"{page}, output block 2 (line ")
    assert "number 0.163 on line" in problem and "printed as 0.127" in problem
    assert "(exact)" in problem and "BaS-iLQG converged True" in problem
    far = edited(tmp_path, page, "min h 0.130, final error 0.089 m",
                 "min h 0.130, final error 0.300 m")
    [problem] = differences(own_model, page, far)
    assert "output block 3" in problem and "number 0.300" in problem and "atol=0.1" in problem
    near = edited(tmp_path, page, "min h 0.130, final error 0.089 m",
                  "min h 0.130, final error 0.150 m")
    assert differences(own_model, page, near) == []
    timing = edited(tmp_path, page, "2.20 ms per step", "99.99 ms per step")
    assert differences(own_model, page, timing) == []


def test_a_word_changed_in_shown_text_is_reported(own_model, tmp_path):
    page = "own-model.md"
    path = edited(tmp_path, page, "2 controls, 2 safety margins", "2 controls, 2 safety limits")
    [problem] = differences(own_model, page, path)
    assert problem.startswith(f"{page}, output block 1 (line ") and "text differs" in problem
    assert "shown   unicycle: 3 states, 2 controls, 2 safety limits" in problem
    assert "printed unicycle: 3 states, 2 controls, 2 safety margins" in problem


@pytest.mark.parametrize("marker, error", [
    ("<!-- output -->", "states no tolerance"),
    ("<!-- output: rtol -->", "cannot read tolerance"),
    ('<!-- output: exact; "RMSE {}": atol=0.1 -->', "matches no shown number"),
    ('<!-- output: exact; "no number here": atol=0.1 -->', "exactly one {}"),
    ("<!-- output: rtol=0.1 atl=0.1 -->", "unknown tolerance options ['atl']"),
    ("", "mark it with"),
])
def test_output_markers_state_a_tolerance_that_applies(tmp_path, marker, error):
    page = tmp_path / "page.md"
    page.write_text(f"```python\nprint('a 1.5 m')\n```\n\n{marker}\n```text\na 1.5 m\n```\n")
    with pytest.raises(ValueError, match=re.escape(error)):
        for _, shown in shown_output.page_blocks(page):
            if shown:
                shown.tolerances()


def test_numbers_hashes_and_tolerances_are_read_as_written():
    assert shown_output.NUMBER.findall("fig5_paths.png 840e0695eb86 [-0.43, +0.43] 12% 1e-05"
                                       " x3 (0.5, 6.0) kappa=0.1.") == [
        "-0.43", "+0.43", "12", "1e-05", "0.5", "6.0", "0.1"]
    tol, _ = shown_output.parse_tolerance("rtol=0.02 atol=0.005", "here")
    assert tol.accepts("1.019", "1.0") and not tol.accepts("1.021", "1.0")
    assert tol.accepts("0.004", "0.0") and not tol.accepts("0.006", "0.0")
    exact, _ = shown_output.parse_tolerance("exact", "here")
    assert exact.accepts("0.130", "0.130") and not exact.accepts("0.13", "0.130")
    default, [(pattern, loose)] = shown_output.parse_output_spec(
        'exact; "built: {}; a scene change takes": rtol=0.5', "here")
    assert default.exact and pattern == "built: {}; a scene change takes" and loose.rtol == 0.5

"""Inputs are never silently misread, outputs are usable by others.

Inputs: a ``--set`` item is exactly one key=value (a control character is an error); every
path argument of the command line has ``~`` expanded once, at parse time; sampling scales whose
square (or value) and reciprocal leave the normal float64 range are refused; booleans are never
integers; every count has an upper bound checked when the config is built.
Outputs: files get ``0666 & ~umask`` and directories ``0777 & ~umask``; every JSON file is
strict JSON (null where the writer had NaN or inf), and its readers take the null.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import stat
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from workbench.cli import main, parser, user_path
from workbench.sampling.mppi import MPPIConfig
from workbench.sampling.robust import RMPPIConfig
from workbench.study import TaskOutput
from workbench.study import runner as runner_module
from workbench.study.config_io import ConfigError, parse_sets
from workbench.study.io import (
    atomic_write_json,
    atomic_write_text,
    current_umask,
    dumps_json,
    strict_json,
)
from workbench.study.report_site import build_site
from workbench.study.runner import declare, rebuild_report, resolve_config, run
from workbench.study.spec import Declaration, StudySpec, Summary, registry
from workbench.study.summary import Rate, Spread, to_jsonable
from workbench.validation import MAX_TASKS, integer, scale, writable_dir

REGISTRY = registry()


def _strict_loads(text: str):
    """json.loads that fails on NaN / Infinity tokens (strict JSON)."""
    def bad(token):
        raise AssertionError(f"non-standard JSON token {token}")
    return json.loads(text, parse_constant=bad)


# ============================================================ class 5: inputs silently misread
# ----------------------------------------------------------------------------- --set items
@pytest.mark.parametrize(("item", "name"), [
    ("realisations=2\nsteps=5", "a newline"),
    ("realisations=2\r", "a carriage return"),
    ("methods=[\"bas\",\t\"al\"]", "a tab"),
    ("seed=1\x00", "a control character"),
    ("seed=1\x7f", "a control character"),
    ("seed=1\x85", "a control character"),  # C1 NEL
])
def test_a_set_item_with_a_control_character_is_an_error(item, name):
    with pytest.raises(ConfigError) as exc:
        parse_sets([item])
    msg = str(exc.value)
    assert msg.startswith(f"--set {item!r} is invalid: it contains {name}")
    assert "exactly one key=value on one line" in msg and "--set a=1 --set b=2" in msg


def test_an_escaped_newline_inside_a_toml_string_is_still_allowed():
    assert parse_sets(['label="a\\nb"', "seed=3"]) == {"label": "a\nb", "seed": 3}


def test_the_command_line_refuses_a_set_with_a_newline_before_any_work(capsys):
    t0 = time.perf_counter()
    assert main(["run", "navigation", "--dry-run", "--set", "realisations=2\nsteps=5"]) == 2
    err = capsys.readouterr().err
    assert "--set 'realisations=2\\nsteps=5' is invalid: it contains a newline" in err
    assert time.perf_counter() - t0 < 10


# ----------------------------------------------------------------------------- ~ in paths
@pytest.fixture
def home(tmp_path, monkeypatch):
    home = tmp_path / "home"
    home.mkdir()
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.chdir(cwd)
    return home


def test_every_path_argument_has_its_tilde_expanded_at_parse_time(home):
    args = parser().parse_args(["run", "tracking-demo", "--out", "~/runs/a", "--config",
                                "~/c.toml"])
    assert args.out == home / "runs" / "a" and args.config == home / "c.toml"
    args = parser().parse_args(["show-config", "tracking-demo", "--config", "~/c.toml"])
    assert args.config == home / "c.toml"
    assert parser().parse_args(["report", "--root", "~/r"]).root == home / "r"
    user = Path.home().name  # ~user of the current user, where the system knows it
    if os.path.expanduser(f"~{user}") != f"~{user}":
        assert user_path(f"~{user}/x") == Path(os.path.expanduser(f"~{user}")) / "x"


def test_a_tilde_user_that_does_not_exist_is_a_clear_error(home, capsys):
    with pytest.raises(argparse.ArgumentTypeError, match="cannot expand ~nosuchuser_wb_9"):
        user_path("~nosuchuser_wb_9/runs")
    with pytest.raises(SystemExit) as exc:
        parser().parse_args(["run", "tracking-demo", "--out", "~nosuchuser_wb_9/runs"])
    assert exc.value.code == 2
    assert "--out: '~nosuchuser_wb_9/runs': cannot expand" in capsys.readouterr().err
    # a folder literally named ~name is written ./~name
    assert user_path("./~lit") == Path.cwd() / "~lit"
    with pytest.raises(ValueError, match=r"^--out = '~nosuchuser_wb_9/x' is invalid"):
        writable_dir("--out", "~nosuchuser_wb_9/x")


def test_the_out_check_and_the_write_use_the_same_expanded_path(home, capsys):
    assert main(["run", "tracking-demo", "--workers", "0", "--out", "~/runs/demo"]) == 0
    out = home / "runs" / "demo"
    assert (out / "summary.json").is_file() and (out / "report.md").is_file()
    assert not (Path.cwd() / "~").exists()
    # the library functions expand it too (as writable_dir does)
    assert rebuild_report(REGISTRY["tracking-demo"], "~/runs/demo") == out / "report.md"
    assert writable_dir("--out", "~/w") == home / "w" and (home / "w").is_dir()


# ----------------------------------------------------------------------------- tiny scales
@pytest.mark.parametrize("sigma", [(1e-200, 1e-200), (2.0, 1e-160), (1e200, 1.0)])
def test_a_sigma_whose_square_leaves_the_float64_range_is_refused(sigma):
    i = next(k for k, s in enumerate(sigma) if not 1.5e-154 <= s <= 6.7e153)
    with pytest.raises(ValueError, match=rf"^MPPIConfig\.sigma\[{i}\] = .* is invalid: must be "
                       r"a finite number in \[1\.492e-154, 6\.704e\+153\] \(its square and its "
                       "reciprocal must be normal float64 numbers"):
        MPPIConfig(sigma=sigma)


def test_a_scalar_sigma_names_the_field_and_the_range():
    with pytest.raises(ValueError, match=r"^MPPIConfig\.sigma = 1\.e-200 is invalid: must be a "
                       r"list of standard deviations, one per control, each in \[1\.492e-154"):
        MPPIConfig(sigma=1e-200)


@pytest.mark.parametrize("lam", [1e-320, 1e-310, 4.5e307, 1e308])
def test_a_temperature_whose_reciprocal_is_not_normal_is_refused(lam):
    with pytest.raises(ValueError, match=r"^MPPIConfig\.lam = .* is invalid: must be a finite "
                       r"number in \[2\.225e-308, 4\.494e\+307\]"):
        MPPIConfig(lam=lam)


def test_the_edges_of_the_scale_ranges_are_accepted():
    assert MPPIConfig(sigma=(1.5e-154, 6.7e153), lam=2.3e-308).sigma == (1.5e-154, 6.7e153)
    assert MPPIConfig(lam=4.4e307).lam == 4.4e307
    assert scale("s", 10**3, power=2) == 1000.0
    for bad in (True, np.True_, math.nan, -1.0, 0.0, "1", 10**400):
        with pytest.raises(ValueError, match=r"^s = "):
            scale("s", bad, power=2)


def test_a_tiny_covariance_and_a_tiny_sigma_in_a_study_config_are_refused():
    with pytest.raises(ValueError, match=r"^MPPIConfig\.sigma\[0\] = "):
        MPPIConfig.with_covariance(np.eye(2) * 1e-310)  # positive definite, sigma 1e-155
    with pytest.raises(ConfigError, match=r"sampler: MPPIConfig\.sigma\[0\] = 1\.e-200 is "
                       "invalid"):
        resolve_config(REGISTRY["navigation"], sets=["sampler.sigma=[1e-200, 1e-200]"])
    with pytest.raises(ConfigError, match=r"MPPIConfig\.lam = 1\.e-320 is invalid"):
        resolve_config(REGISTRY["sampling-safety"], sets=["sampler.lam=1e-320"])


# ----------------------------------------------------------------------------- bool is no int
def test_a_bool_is_never_an_integer():
    with pytest.raises(ValueError, match=r"^MPPIConfig\.n_samples = True is invalid"):
        MPPIConfig(n_samples=True)
    with pytest.raises(ValueError, match=r"^RMPPIConfig\.candidate_samples = True is invalid"):
        RMPPIConfig(candidate_samples=True)
    with pytest.raises(ValueError, match=r"^MPPIConfig\.sigma = .* is invalid"):
        MPPIConfig(sigma=(True, 2.0))
    with pytest.raises(ValueError, match=r"^n = False is invalid"):
        integer("n", np.False_)
    nav = resolve_config(REGISTRY["navigation"])
    with pytest.raises(ValueError, match=r"^realisations = True is invalid"):
        dataclasses.replace(nav, realisations=True)
    bound = resolve_config(REGISTRY["free-energy-bound"])
    with pytest.raises(ValueError, match=r"^episodes = True is invalid"):
        dataclasses.replace(bound, episodes=np.True_)
    tracking = resolve_config(REGISTRY["tracking"])
    with pytest.raises(ValueError, match=r"^sweep = 1 is invalid: must be true or false"):
        dataclasses.replace(tracking, sweep=1)
    with pytest.raises(ConfigError, match=r"realisations = True is invalid: expected an integer"):
        resolve_config(REGISTRY["sampling-safety"], sets=["realisations=true"])


# ----------------------------------------------------------------------------- count bounds
@pytest.mark.parametrize(("study", "item", "message"), [
    ("navigation", "realisations=1000000000000",
     r"realisations = 1000000000000 is invalid: must be an integer in \[1, 10000000\]"),
    ("navigation", "realisations=4000000",  # each below the limit, the run above it
     r"realisations = 4000000 is invalid: gives controllers x variances x realisations .* "
     r"\(tasks of a run, at most\) = \d+, above the limit 10000000"),
    ("sampling-safety", "realisations=1000000000000", r"realisations = 1000000000000 is invalid"),
    ("sampling-safety", "realisations=2000000",
     r"realisations = 2000000 is invalid: gives controllers x variances x realisations"),
    ("tracking", "n_seeds=100000000", r"n_seeds = 100000000 is invalid: must be an integer in "
     r"\[1, 10000000\]"),
    ("tracking", "sweep_seeds=1000000", r"sweep_seeds = 1000000 is invalid: gives methods x"),
    ("tracking", "n_rollouts=100000000", r"n_rollouts = 100000000 is invalid"),
    ("free-energy-bound", "episodes=9000000", r"episodes = 9000000 is invalid: gives variances "
     r"x episodes \(tasks of a run\) = 27000000, above the limit 10000000"),
    ("free-energy-bound", "steps=100000000", r"steps = 100000000 is invalid: must be an integer "
     r"in \[2, 10000000\]"),
    ("free-energy-bound", "n_samples=100000000", r"n_samples = 100000000 is invalid: gives "
     r"n_samples \* horizon \* nu"),
    ("free-energy-bound", "grid_angles=100000000", r"grid_angles = 100000000 is invalid"),
    ("navigation", "steps=100000000", r"steps = 100000000 is invalid"),
    ("navigation", "sampler.n_samples=100000000",
     r"MPPIConfig\.n_samples = 100000000 is invalid: gives n_samples \* horizon \* nu"),
    ("navigation", "robust.candidate_samples=10000000",
     r"RMPPIConfig\.candidate_samples = 10000000 is invalid: gives n_candidates \* "
     r"candidate_samples"),
])
def test_a_huge_count_fails_at_once_naming_the_field_value_and_limit(study, item, message):
    t0 = time.perf_counter()
    with pytest.raises(ConfigError, match=message):
        resolve_config(REGISTRY[study], sets=[item])
    assert time.perf_counter() - t0 < 5  # nothing was allocated


def test_mppi_iterations_and_batch_entries_are_bounded():
    with pytest.raises(ValueError, match=r"^MPPIConfig\.iterations = 1000000 is invalid: must "
                       r"be an integer in \[1, 1000\]"):
        MPPIConfig(iterations=10**6)
    with pytest.raises(ValueError, match=r"above the limit 2147483648"):
        MPPIConfig(n_samples=2**21, horizon=1000)


def test_the_framework_refuses_more_tasks_than_its_limit(monkeypatch):
    spec = REGISTRY["tracking-demo"]
    cfg = resolve_config(spec, sets=["q_betas=[0.1, 1.0]"])
    assert len(declare(spec, cfg)[0].tasks) == 2
    monkeypatch.setattr(runner_module, "MAX_TASKS", 1)
    with pytest.raises(ConfigError, match=r"^study 'tracking-demo': the config gives 2 tasks, "
                       r"above the limit 1"):
        declare(spec, cfg)
    assert MAX_TASKS == 10**7


# ============================================================ class 7: outputs others can use
@pytest.fixture
def umask_027():
    old = os.umask(0o027)
    try:
        yield
    finally:
        os.umask(old)


def _mode(p: Path) -> int:
    return stat.S_IMODE(p.stat().st_mode)


def test_current_umask_reads_without_changing_it(umask_027):
    assert current_umask() == 0o027 and current_umask() == 0o027
    assert os.umask(0o027) == 0o027


def test_atomic_writes_follow_the_umask(tmp_path, umask_027):
    atomic_write_text(tmp_path / "a" / "b" / "x.txt", "x")
    assert _mode(tmp_path / "a" / "b" / "x.txt") == 0o640
    assert _mode(tmp_path / "a") == 0o750 and _mode(tmp_path / "a" / "b") == 0o750
    os.umask(0o002)
    atomic_write_json(tmp_path / "y.json", {"a": 1})
    assert _mode(tmp_path / "y.json") == 0o664


def test_a_run_and_the_report_site_follow_the_umask(home, umask_027):
    root = home / "reports"
    assert main(["run", "tracking-demo", "--workers", "0", "--out", str(root / "tracking_demo")]
                ) == 0
    index = build_site(root, REGISTRY)
    files = [p for p in root.rglob("*") if p.is_file()]
    dirs = [root, *(p for p in root.rglob("*") if p.is_dir())]
    assert index in files and root / "tracking_demo" / "report.html" in files
    assert {p.name for p in files} >= {"summary.json", "manifest.json", "run.json",
                                       "config.toml", "report.md", "index.html"}
    assert {str(p.relative_to(root)): oct(_mode(p)) for p in files if _mode(p) != 0o640} == {}
    assert {str(p): oct(_mode(p)) for p in dirs if _mode(p) != 0o750} == {}


# ----------------------------------------------------------------------------- strict JSON
def test_strict_json_writes_null_for_nan_and_inf(tmp_path):
    data = {"inf": math.inf, "list": [math.nan, 1.5], "np": np.float64(-np.inf),
            "arr": np.array([1.0, np.nan]), "rate": to_jsonable(Rate(0, 0)),
            "spread": to_jsonable(Spread.of([])), "int": np.int64(3), "flag": np.bool_(True),
            "tuple": (1, math.inf), 2: "int key"}
    atomic_write_json(tmp_path / "s.json", data)
    text = (tmp_path / "s.json").read_text()
    assert "Infinity" not in text and "NaN" not in text
    back = _strict_loads(text)
    assert back["inf"] is None and back["list"] == [None, 1.5] and back["np"] is None
    assert back["arr"] == [1.0, None] and back["rate"]["value"] is None
    assert back["rate"]["low"] == 0.0 and back["spread"]["mean"] is None
    assert back["int"] == 3 and back["flag"] is True and back["tuple"] == [1, None]
    assert back["2"] == "int key"
    assert strict_json({"x": [np.float32(np.nan)]}) == {"x": [None]}
    assert _strict_loads(dumps_json({"a": math.nan})) == {"a": None}


# a study whose summary holds an inf and whose config holds an inf
@dataclass(frozen=True)
class InfConfig:
    n: int = 2
    limit: float = math.inf
    seed: int = 0


@dataclass(frozen=True)
class Draw:
    i: int


def _inf_run(task, ctx, config):
    return TaskOutput(tables={"draws": {"v": np.array([ctx.rng().standard_normal()])}})


def _inf_tasks(config):
    return Declaration(tuple(Draw(i) for i in range(config.n)), _inf_run,
                       {"limit": config.limit})


def _inf_summary(finished):
    v = finished.store.table("draws")["v"].to_numpy()
    worst = math.inf if finished.config.limit == math.inf else float(v.max())
    return Summary({"worst": worst, "empty": Rate(0, 0), "mean": float(v.mean())}, worst)


def _inf_report(finished, summary):
    path = finished.out / "report.md"
    atomic_write_text(path, f"# inf\n\nworst {summary.value}\n")
    return path


@pytest.fixture
def inf_spec(tmp_path):
    d = tmp_path / "inf_study"
    d.mkdir()
    (d / "quick.toml").write_text("n = 2\n")
    return StudySpec("inf-study", "a summary with an inf", InfConfig, d, _inf_tasks,
                     _inf_summary, _inf_report)


def test_a_summary_with_an_inf_is_written_as_null_and_read_back(inf_spec, tmp_path):
    out = tmp_path / "run"
    run(inf_spec, resolve_config(inf_spec), out, workers=0, progress=False)
    for name in ("summary.json", "manifest.json", "run.json"):
        text = (out / name).read_text()
        assert "Infinity" not in text and "NaN" not in text, name
        _strict_loads(text)
    summary = _strict_loads((out / "summary.json").read_text())
    assert summary["worst"] is None and summary["empty"]["value"] is None
    assert summary["empty"]["n"] == 0 and math.isfinite(summary["mean"])
    manifest = _strict_loads((out / "manifest.json").read_text())
    assert manifest["config"]["limit"] is None  # inf in the config: null in the manifest
    assert "limit = inf" in (out / "config.toml").read_text()
    # the rebuild reads the config back (from config.toml, which keeps the inf)
    (out / "summary.json").unlink()
    rebuild_report(inf_spec, out)
    assert _strict_loads((out / "summary.json").read_text()) == summary


def test_the_dry_run_manifest_is_strict_json(capsys):
    assert main(["run", "navigation", "--dry-run"]) == 0
    shown = _strict_loads(capsys.readouterr().out)
    assert shown["config"]["robust"]["alpha"] is None  # RMPPIConfig.alpha = inf


def test_the_report_site_reads_null_numbers(tmp_path):
    (tmp_path / "bench").mkdir()
    atomic_write_json(tmp_path / "bench" / "bench.json",
                      [{"name": "step", "value": math.nan, "unit": "ms", "baseline": None,
                        "ratio": math.inf}, {"name": "ok", "value": 2.0, "ratio": 3.0}])
    text = build_site(tmp_path, {}).read_text()
    assert "<td>step</td><td>n/a ms</td>" in text and "<td>2 " in text
    assert "Unreadable" not in text

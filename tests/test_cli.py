"""The `workbench` command: help, fast config errors, show-config round trips for every
registered study and profile, runs through the CLI, report rebuilds, Makefile wiring."""

from __future__ import annotations

import contextlib
import io
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from workbench.cli import main
from workbench.study import config_io
from workbench.study.runner import declare, dry_manifest, resolve_config
from workbench.study.spec import StudySpec, registry
from workbench.study.store import study_manifest

ROOT = Path(__file__).parents[1]
REGISTRY = registry()
WORKBENCH = str(Path(sys.executable).parent / "workbench")  # the installed console script


def cli(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    env = {**os.environ, "COLUMNS": "100"}
    return subprocess.run([WORKBENCH, *args], capture_output=True, text=True, timeout=timeout,
                          cwd=ROOT, env=env)


def call(*args: str) -> tuple[int, str]:
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = main(list(args))
    return rc, buf.getvalue()


def test_the_existing_studies_are_registered():
    assert {"tracking", "tracking-demo", "navigation", "free-energy-bound",
            "sampling-safety", "arena", "arena-tuning"} == set(REGISTRY)
    for e in REGISTRY.values():
        assert isinstance(e, StudySpec) and e.profiles and e.default_profile in e.profiles
    assert {"quick", "paper", "full"} <= set(REGISTRY["tracking"].profiles)


def test_help_is_complete():
    top = cli("--help")
    assert top.returncode == 0
    for cmd in ("list", "run", "show-config", "report"):
        assert cmd in top.stdout
    helps = {cmd: cli(cmd, "--help") for cmd in ("list", "run", "show-config", "report")}
    assert all(h.returncode == 0 for h in helps.values())
    for opt in ("--profile", "--config", "--set", "--workers", "--scheduler", "--out",
                "--dry-run", "KEY=VALUE"):
        assert opt in helps["run"].stdout, opt
    for opt in ("--profile", "--config", "--set"):
        assert opt in helps["show-config"].stdout
    assert "--root" in helps["report"].stdout and "STUDY" in helps["report"].stdout.upper()


def test_bad_value_fails_within_seconds_naming_the_key(tmp_path):
    out = tmp_path / "never"
    t0 = time.perf_counter()
    r = cli("run", "tracking", "--set", "noise_std=-1", "--out", str(out))
    assert time.perf_counter() - t0 < 10
    assert r.returncode == 2
    assert "noise_std = -1" in r.stderr and "must be a finite number >= 0" in r.stderr
    assert not out.exists()  # failed before any work


def test_mistyped_key_suggests_the_closest(tmp_path):
    r = cli("run", "tracking", "--set", "noise_sdt=1", "--out", str(tmp_path / "x"))
    assert r.returncode == 2
    assert "unknown key 'noise_sdt'; did you mean 'noise_std'" in r.stderr
    assert "unknown study 'trackin'; did you mean 'tracking'" in cli("run", "trackin").stderr


@pytest.mark.parametrize("args, message", [
    (("--set", "n_seeds=1.5"), "n_seeds = 1.5 is invalid: expected an integer"),
    (("--set", "methods=['bas', 'xx']"), "methods = 'xx' is invalid: unknown method"),
    (("--set", "base.ecbf_noise=sometimes"), "ecbf_noise = 'sometimes' is invalid"),
    (("--profile", "huge"), "--profile 'huge' is invalid: study 'tracking' has the profiles"),
    (("--config", "/nonexistent.toml"), "config file /nonexistent.toml does not exist"),
    (("--workers", "-1"), "--workers = -1 is invalid"),
])
def test_config_errors_before_work(args, message, capsys):
    assert main(["run", "tracking", "--dry-run", *args]) == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("study, profile", [(s, p) for s, e in REGISTRY.items()
                                            for p in e.profiles])
def test_show_config_round_trips_to_an_identical_manifest(study, profile, tmp_path):
    """show-config's output fed back as --config gives the same run (for every study)."""
    rc, text = call("show-config", study, "--profile", profile)
    assert rc == 0
    path = tmp_path / "c.toml"
    path.write_text(text)
    rc, direct = call("run", study, "--profile", profile, "--dry-run")
    rc2, fed_back = call("run", study, "--config", str(path), "--dry-run")
    assert rc == rc2 == 0
    direct, fed_back = json.loads(direct), json.loads(fed_back)
    assert (direct.pop("profile"), fed_back.pop("profile")) == (profile, None)
    assert direct == fed_back
    entry = REGISTRY[study]
    assert resolve_config(entry, profile) == resolve_config(entry, config=path)


def test_set_overrides_change_the_manifest_and_use_aliases():
    entry = REGISTRY["tracking"]
    base = resolve_config(entry, "quick")
    cfg = resolve_config(entry, "quick", sets=["noise_std=5", "methods=['bas']"])
    assert cfg.base.noise_std == 5.0 and cfg.methods == ("bas",)
    assert dry_manifest(entry, cfg)["tasks_sha256"] != dry_manifest(entry, base)["tasks_sha256"]


def test_profile_is_chosen_with_the_flag_never_a_config_key(tmp_path, capsys):
    """A label can never disagree with what ran: ``profile`` is not a config key."""
    assert main(["run", "navigation", "--set", "profile=paper", "--dry-run"]) == 2
    assert "profile = 'paper' is not a config key" in capsys.readouterr().err
    path = tmp_path / "c.toml"
    path.write_text('profile = "tiny"\n')
    assert main(["run", "navigation", "--config", str(path), "--dry-run"]) == 2
    assert "is not a config key" in capsys.readouterr().err
    for e in REGISTRY.values():
        assert "profile" not in {f for f in e.config_type.__dataclass_fields__}


def test_navigation_controller_settings_are_config_fields():
    """The sampler's sigma, lambda, N, T, q_beta, the robust and feedback settings and the
    calibration seed are settable, shown by a dry run and part of every task id."""
    rc, text = call("run", "navigation", "--set", "sampler.sigma=[4.0, 4.0]", "--set",
                    "sampler.lam=5", "--set", "q_beta=0.1", "--set", "calibration_seed=3",
                    "--set", "feedback.q_beta=2", "--dry-run")
    assert rc == 0
    shown = json.loads(text)
    assert shown["config"]["sampler"]["sigma"] == [4.0, 4.0]
    assert shown["config"]["sampler"]["lam"] == 5.0 and shown["config"]["q_beta"] == 0.1
    assert shown["fingerprint"]["mppi"]["sigma"] == [4.0, 4.0]
    assert shown["fingerprint"]["calibration_seed"] == 3
    assert shown["fingerprint"]["feedback"]["q_beta"] == 2.0
    rc, base = call("run", "navigation", "--dry-run")
    assert json.loads(base)["tasks_sha256"] != shown["tasks_sha256"]
    assert main(["run", "navigation", "--set", "sampler.lam=-1", "--dry-run"]) == 2


def test_a_config_files_sizes_are_what_runs(tmp_path):
    """A config file (here: two barrier weights) decides the sizes; run.json records that no
    profile was used, config.toml the sizes."""
    path = tmp_path / "c.toml"
    path.write_text("q_betas = [0.1, 1.0]\n")
    out = tmp_path / "run"
    rc, _ = call("run", "tracking-demo", "--config", str(path), "--workers", "0", "--out",
                 str(out))
    assert rc == 0
    assert [r["q_beta"] for r in json.loads((out / "summary.json").read_text())["rows"]] == \
        [0.1, 1.0]
    record = json.loads((out / "run.json").read_text())
    assert record["profile"] is None and record["tasks"]["total"] == 2
    assert config_io.load(REGISTRY["tracking-demo"].config_type,
                          config_io.read_toml(out / "config.toml")).q_betas == (0.1, 1.0)


def test_run_writes_a_config_that_reproduces_its_manifest(cli_reports):
    root, outputs = cli_reports
    out = root / "tracking_comparison"
    assert "BaS-iLQG" in outputs[1] and "unsafe" in outputs[1]
    assert "q_beta=0.01: cost" in outputs[0]
    stored = json.loads((out / "manifest.json").read_text())
    entry = REGISTRY["tracking"]
    again = dry_manifest(entry, resolve_config(entry, config=out / "config.toml"))
    assert {k: stored[k] for k in again} == json.loads(json.dumps(again))
    assert again == study_manifest(declare(entry, resolve_config(entry, config=out /
                                                                 "config.toml"))[0])


def test_report_rebuilds_from_stored_results(cli_reports):
    root, _ = cli_reports
    for name, d in (("tracking-demo", "tracking_demo"), ("tracking", "tracking_comparison")):
        md = root / d / "report.md"
        before = md.read_text()
        md.unlink()
        rc, _ = call("report", name, "--root", str(root))
        assert rc == 0 and md.is_file() and (root / "index.html").is_file()
        # the same numbers; only the run line (wall time, tasks computed) differs
        strip = [ln for ln in before.splitlines() if "Wall time" not in ln]
        assert [ln for ln in md.read_text().splitlines() if "Wall time" not in ln] == strip


def test_report_of_a_study_that_has_not_run(tmp_path, capsys):
    assert main(["report", "tracking", "--root", str(tmp_path)]) == 2
    assert "no readable manifest.json; run `workbench run tracking" in capsys.readouterr().err


def test_list_names_studies_controllers_and_models():
    rc, out = call("list")
    assert rc == 0
    for word in ("tracking", "tracking-demo", "navigation", "sa_rmppi", "bas_mppi",
                 "double_integrator", "Model.from_expressions"):
        assert word in out


def test_config_io_reads_every_profile_file_strictly():
    for e in REGISTRY.values():
        for p in e.profiles.values():
            config_io.load(e.config_type, config_io.read_toml(p))  # no unknown keys


def test_makefile_targets_call_the_cli():
    r = subprocess.run(["make", "-n", "study-tracking", "PROFILE=full", "WORKERS=3",
                        "SET=noise_std=5"], capture_output=True, text=True, cwd=ROOT)
    assert "workbench run tracking --profile full --workers 3" in r.stdout
    assert "--set noise_std=5" in r.stdout
    r = subprocess.run(["make", "-n", "reports", "study-tracking-demo"], capture_output=True,
                       text=True, cwd=ROOT)
    assert "workbench report" in r.stdout and "workbench run tracking-demo" in r.stdout

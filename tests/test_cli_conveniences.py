"""Command-line conveniences: --version, a dry run's task count and estimated time, the
library's log lines on the terminal (and -q), `workbench report FOLDER` for a run folder
anywhere, `workbench run --out D` writing D/report.html, and clear errors (no traceback) for a
truncated manifest."""

from __future__ import annotations

import contextlib
import io
import json
import logging
import shutil

import pytest

import workbench
import workbench.cli as cli
import workbench.study.report_site as report_site
from workbench.cli import main


def call(*args: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            rc = main(list(args))
        except SystemExit as exc:  # argparse's --version and usage errors
            rc = exc.code
    return rc, out.getvalue(), err.getvalue()


@pytest.fixture(autouse=True)
def assumptions(tmp_path, monkeypatch):
    """A page of assumptions to render (the real one when the repository has it)."""
    if not report_site.ASSUMPTIONS_SOURCE.is_file():
        page = tmp_path / "assumptions.md"
        page.write_text("# Assumptions\n\n## 3.3 The tracking scene {#s3-3}\n\n"
                        "## 6.1 BaS-iLQG {#s6-1}\n\nWith $q_\\beta$.\n")
        monkeypatch.setattr(report_site, "ASSUMPTIONS_SOURCE", page)


def test_version():
    rc, out, _ = call("--version")
    assert rc == 0 and out.strip() == f"workbench {workbench.__version__}"


def test_dry_run_prints_the_task_count_and_an_unknown_time_without_a_record(tmp_path,
                                                                             monkeypatch):
    monkeypatch.chdir(tmp_path)  # no reports/navigation/run.json of an earlier run here
    rc, out, err = call("run", "navigation", "--dry-run", "--out", str(tmp_path / "none"))
    assert rc == 0 and json.loads(out)["n_tasks"] == 281
    assert err.startswith("dry run: 281 tasks; estimated time unknown (no finished run of "
                          "navigation in")


def test_dry_run_estimates_from_the_last_runs_time_per_task(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # no reports/navigation/run.json of an earlier run here
    out = tmp_path / "nav"
    out.mkdir()
    (out / "run.json").write_text(json.dumps({
        "study": "navigation", "profile": "quick", "wall_time_s": 562.0, "backend": "2 workers",
        "tasks": {"total": 281, "computed": 281, "loaded": 0}}))
    rc, _, err = call("run", "navigation", "--profile", "paper", "--dry-run", "--workers", "4",
                      "--out", str(out))
    assert rc == 0
    # 2801 tasks x (562 s / 281 tasks x 2 workers) / 4 workers = 2801 s = 47 min
    assert err.startswith("dry run: 2801 tasks; estimated 47 min on 4 workers (from ")
    assert "562 s for 281 tasks on 2 workers, profile quick; rough" in err
    from studies.navigation import STUDY
    from workbench.study.runner import declare, resolve_config

    first = declare(STUDY, resolve_config(STUDY, "paper"))[0].task_ids()[0]
    (out / "tasks").mkdir()
    (out / "tasks" / f"{first}.npz").write_bytes(b"")  # a stored task is not counted again
    rc, _, err = call("run", "navigation", "--profile", "paper", "--dry-run", "--workers", "4",
                      "--out", str(out))
    assert err.startswith(f"dry run: 2801 tasks (1 already stored in {out}, 2800 to compute); "
                          "estimated 47 min")
    (out / "run.json").write_text('{"study": "navigation", "wall_')  # truncated: no estimate
    assert "estimated time unknown" in call("run", "navigation", "--dry-run", "--out",
                                            str(out))[2]


def test_library_log_lines_reach_the_terminal_and_quiet_silences_them(monkeypatch):
    def chatty(args):
        logging.getLogger("workbench.study").info("tasks: 3 of 5 done")
        logging.getLogger("workbench.study").warning("figure: no x label")
        return 0

    monkeypatch.setattr(cli, "cmd_list", chatty)
    logger = logging.getLogger("workbench")
    before = (logger.level, list(logger.handlers))
    rc, out, err = call("list")
    assert rc == 0 and out == "tasks: 3 of 5 done\n" and err == "figure: no x label\n"
    rc, out, err = call("-q", "list")
    assert out == "" and err == "figure: no x label\n"
    assert (logger.level, list(logger.handlers)) == before  # restored after the command
    assert "-q, --quiet" in call("run", "--help")[1]


def test_report_on_a_run_folder_anywhere(cli_reports, tmp_path):
    folder = tmp_path / "elsewhere" / "my demo"
    shutil.copytree(cli_reports[0] / "tracking_demo", folder)
    (folder / "report.md").write_bytes(b"\xff\xfe not utf-8")  # rebuilt from stored results
    rc, out, err = call("report", str(folder))
    assert rc == 0, err
    assert out.splitlines() == [f"wrote {folder / 'report.md'}", f"wrote {folder / 'report.html'}"]
    html = (folder / "report.html").read_text()
    assert 'href="assumptions.html#s3-3"' in html and "<img" in html
    assert (folder / "assumptions.html").is_file()


def test_report_on_a_reports_root_folder(cli_reports, tmp_path):
    root = tmp_path / "site"
    shutil.copytree(cli_reports[0] / "tracking_demo", root / "tracking_demo")
    rc, out, _ = call("report", str(root))
    assert rc == 0 and out.strip() == f"wrote {root / 'index.html'}"


def test_report_on_a_truncated_manifest_is_a_clear_error(cli_reports, tmp_path):
    folder = tmp_path / "demo"
    shutil.copytree(cli_reports[0] / "tracking_demo", folder)
    manifest = folder / "manifest.json"
    manifest.write_text(manifest.read_text()[:40])
    rc, _, err = call("report", str(folder))
    assert rc == 2 and "Traceback" not in err
    assert str(folder / "manifest.json") in err or f"{folder}: no readable manifest.json" in err
    (folder / "run.json").unlink()  # nothing left that names the study
    rc, _, err = call("report", str(folder))
    assert rc == 2 and "Traceback" not in err
    assert "cannot tell which study wrote this folder" in err and "truncated?" in err
    rc, _, err = call("report", str(tmp_path / "nowhere"))
    assert rc == 2 and "is neither a study" in err


def test_run_with_out_writes_the_html_report(tmp_path):
    out = tmp_path / "run"
    rc, stdout, err = call("run", "tracking-demo", "--workers", "0", "-q", "--out", str(out))
    assert rc == 0, err
    assert f"wrote {out / 'report.html'}" in stdout and "%|" not in err  # -q: no progress bar
    html = (out / "report.html").read_text()
    assert "<table>" in html and 'href="assumptions.html#s3-3"' in html


def test_run_refuses_a_bad_scheduler_before_creating_out(tmp_path):
    """A malformed --scheduler fails with a one-line error and leaves no --out folder."""
    from workbench.cli import main

    out = tmp_path / "never"
    rc = main(["run", "tracking-demo", "--scheduler", "not a url", "--out", str(out)])
    assert rc == 2 and not out.exists()


def test_run_passes_task_timeout_and_allow_mixed(monkeypatch, tmp_path):
    """--task-timeout and --allow-mixed reach the runner."""
    import workbench.study.runner as runner
    from workbench.cli import main

    seen = {}

    def fake_run(*a, **kw):
        seen.update(kw)
        raise runner.ConfigError("stop here")

    monkeypatch.setattr(runner, "run", fake_run)
    rc = main(["run", "tracking-demo", "--task-timeout", "7.5", "--allow-mixed",
               "--out", str(tmp_path / "o")])
    assert rc == 2
    assert seen["task_timeout_s"] == 7.5 and seen["allow_mixed"] is True

"""A run folder belongs to one run (workbench.study.folder): a marker and a lock; a user's files,
another config or another study in the folder are refused with a message saying what to do and
nothing is written; a second concurrent run fails at once; a rerun that computed nothing keeps
the record of the run that did; unreadable manifests and markers are clear errors; a full disk
or a file-size limit while storing a task names the file and leaves no partial file."""

from __future__ import annotations

import errno
import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import study_toy  # tests/study/study_toy.py

from workbench.study import TaskOutput, run_study
from workbench.study import io as study_io
from workbench.study.config_io import ConfigError
from workbench.study.folder import LOCK, MARKER, RunFolderError, differences, locked
from workbench.study.io import StorageError, atomic_write_bytes
from workbench.study.runner import rebuild_report, run
from workbench.study.spec import Declaration, StudySpec, Summary

TESTS = Path(__file__).parent


# ------------------------------------------------------------------ a toy study for the runner
@dataclass(frozen=True)
class OwnerConfig:
    n: int = 4
    scale: float = 1.0
    seed: int = 0


@dataclass(frozen=True)
class Draw:
    i: int


def run_draw(task: Draw, ctx, config: OwnerConfig) -> TaskOutput:
    return TaskOutput(tables={"draws": {"value": np.array([config.scale
                                                           * ctx.rng().standard_normal()])}})


def declare(config: OwnerConfig) -> Declaration:
    return Declaration(tuple(Draw(i) for i in range(config.n)), run_draw,
                       {"scale": config.scale})


def summarise(finished) -> Summary:
    mean = float(finished.store.table("draws")["value"].mean())
    return Summary({"mean": mean}, mean, (f"owner-toy mean {mean:.6f}",))


def report(finished, summary) -> Path:
    path = finished.out / "report.md"
    study_io.atomic_write_text(path, f"# Owner toy\n\n{finished.run_line}\n")
    return path


@pytest.fixture(scope="module")
def spec(tmp_path_factory) -> StudySpec:
    d = tmp_path_factory.mktemp("spec") / "owner_toy"
    d.mkdir()
    (d / "quick.toml").write_text("n = 4\n")
    return StudySpec(name="owner-toy", description="toy", config_type=OwnerConfig, directory=d,
                     tasks=declare, summarise=summarise, report=report)


def _files(root: Path) -> dict[str, tuple[bytes, int]]:
    return {str(p.relative_to(root)): (p.read_bytes(), p.stat().st_mtime_ns)
            for p in sorted(root.rglob("*")) if p.is_file() and p.name != LOCK}


# ------------------------------------------------------------------ ownership
def test_a_new_folder_gets_a_marker_and_the_same_config_continues(spec, tmp_path):
    out = tmp_path / "run"
    first = run(spec, OwnerConfig(), out, workers=0, progress=False)
    marker = json.loads((out / MARKER).read_text())
    assert marker["study"] == "owner_toy" and marker["identity"]["config"]["n"] == 4
    again = run(spec, OwnerConfig(), out, workers=0, progress=False)
    assert (first.run.computed, again.run.computed, again.run.loaded) == (4, 0, 4)


def test_a_folder_holding_a_users_files_is_refused_and_left_untouched(spec, tmp_path):
    out = tmp_path / "mine"
    out.mkdir()
    for name in ("config.toml", "report.md", "summary.json"):
        (out / name).write_text(f"my own {name}\n")
    before = _files(out)
    with pytest.raises(RunFolderError) as info:
        run(spec, OwnerConfig(), out, workers=0, progress=False)
    msg = str(info.value)
    assert "config.toml" in msg and "report.md" in msg and "summary.json" in msg
    assert "--out" in msg and "no workbench run wrote" in msg
    assert _files(out) == before  # nothing written, nothing overwritten
    assert not (out / MARKER).exists() and not (out / "tasks").exists()


def test_another_config_in_a_used_folder_is_refused_naming_the_keys(spec, tmp_path):
    out = tmp_path / "run"
    run(spec, OwnerConfig(), out, workers=0, progress=False)
    before = _files(out)
    with pytest.raises(ConfigError) as info:
        run(spec, OwnerConfig(n=6, scale=2.0), out, workers=0, progress=False)
    msg = str(info.value)
    assert "config.n: 4 in the folder, 6 now" in msg and "config.scale" in msg
    assert str(out) in msg and "--out" in msg and "delete" in msg
    assert f"--config {out / 'config.toml'}" in msg  # how to continue the stored run
    assert _files(out) == before  # no manifest, config.toml or table of the new config


def test_a_study_run_into_another_runs_folder_is_refused(tmp_path):
    """The study API: two runs with different configs into one folder no longer both succeed
    with mixed results."""
    run_study(study_toy.toy_study(4), tmp_path, workers=0, progress=False)
    before = _files(tmp_path)
    with pytest.raises(RunFolderError, match=r"config\.n_tasks: 4 in the folder, 8 now"):
        run_study(study_toy.toy_study(8), tmp_path, workers=0, progress=False)
    assert _files(tmp_path) == before


def test_a_folder_of_another_study_is_refused(tmp_path):
    run_study(study_toy.toy_study(4), tmp_path, workers=0, progress=False)
    other = study_toy.toy_study(4)
    other = type(other)("other_toy", other.tasks, other.run_task, other.seed, other.config)
    with pytest.raises(RunFolderError, match=r"holds a run of the study 'toy' \(see "
                                             r"\.workbench-run\.json\), not of 'other_toy'"):
        run_study(other, tmp_path, workers=0, progress=False)


def test_a_folder_written_before_markers_is_adopted_or_refused_by_its_manifest(tmp_path):
    """A run folder of an earlier version (a manifest, no marker): the same run continues and
    gets its marker; another config is refused like a marked folder's."""
    study = study_toy.toy_study(4)
    run_study(study, tmp_path / "a", workers=0, progress=False)
    run_study(study, tmp_path / "b", workers=0, progress=False)
    for d in ("a", "b"):
        (tmp_path / d / MARKER).unlink()
    result = run_study(study, tmp_path / "a", workers=0, progress=False)
    assert result.loaded == 4 and result.computed == 0
    assert json.loads((tmp_path / "a" / MARKER).read_text())["adopted_from_manifest"] is True
    with pytest.raises(RunFolderError, match=r"manifest\.json.*config\.n_tasks: 4 in the "
                                             r"folder, 8 now|config\.n_tasks: 4 in the folder"):
        run_study(study_toy.toy_study(8), tmp_path / "b", workers=0, progress=False)
    assert not (tmp_path / "b" / MARKER).exists()


def test_differences_name_nested_keys_and_the_task_list():
    a = {"study": "s", "version": 1, "seed": 0, "config": {"m": {"x": 1, "y": [1, 2]}},
         "fingerprint": {}, "n_tasks": 2, "tasks_sha256": "aa"}
    b = {**a, "version": 2, "config": {"m": {"x": 1, "y": [1, 3], "z": True}},
         "n_tasks": 3, "tasks_sha256": "bb"}
    assert differences(a, b) == ["config.m.y: [1, 2] in the folder, [1, 3] now",
                                 "config.m.z: absent in the folder, true now",
                                 "version: 1 in the folder, 2 now",
                                 "n_tasks: 2 in the folder, 3 now", "the task list differs"]


# ------------------------------------------------------------------ the lock
def test_a_second_concurrent_run_fails_at_once_and_a_killed_run_frees_the_folder(tmp_path):
    out = tmp_path / "run"
    code = (f"import sys; sys.path.insert(0, {str(TESTS)!r}); import study_toy; "
            f"study_toy.main([{str(out)!r}, '0', '40', '0.5'])")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, start_new_session=True)
    try:
        t_end = time.monotonic() + 60
        while not (out / "tasks").is_dir() or not any((out / "tasks").glob("*.npz")):
            assert time.monotonic() < t_end and proc.poll() is None, proc.stderr.read()
            time.sleep(0.02)
        before = _files(out / "tasks")
        t0 = time.monotonic()
        with pytest.raises(RunFolderError, match=rf"is in use by another run \(pid {proc.pid} "):
            run_study(study_toy.toy_study(40, 0.5), out, workers=0, progress=False)
        assert time.monotonic() - t0 < 10.0  # at once, not after the other run
        assert set(before) <= set(_files(out / "tasks"))  # the other run went on
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
    # kill -9 released the lock; (allow_mixed: other helpers' edits to the source tree during
    # the test must not make this resume fail; provenance has its own tests)
    result = run_study(study_toy.toy_study(40, 0.0), out, workers=0, progress=False,
                       allow_mixed=True)
    assert result.loaded >= 1 and result.loaded + result.computed == 40


def test_the_lock_is_reentrant_in_its_thread_only(tmp_path):
    errors = []

    def other_thread():
        try:
            with locked(tmp_path):
                pass
        except RunFolderError as exc:
            errors.append(str(exc))

    with locked(tmp_path), locked(tmp_path):  # runner.run holds it while run_study takes it
        t = threading.Thread(target=other_thread)
        t.start()
        t.join()
        probe = subprocess.run(
            [sys.executable, "-c", "import fcntl, os, sys; fd = os.open(sys.argv[1], os.O_RDWR)"
             "\ntry:\n    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)\nexcept "
             "BlockingIOError:\n    sys.exit(3)", str(tmp_path / LOCK)], timeout=30)
        assert probe.returncode == 3  # another process cannot take it either
    assert errors and "in use by another run in this process" in errors[0]
    with locked(tmp_path):  # released after the outer exit
        pass


# ------------------------------------------------------------------ the run record
def test_a_rerun_that_computes_nothing_keeps_the_computing_runs_wall_time(spec, tmp_path,
                                                                          caplog):
    out = tmp_path / "run"
    run(spec, OwnerConfig(), out, workers=0, progress=False, profile="quick")
    first = json.loads((out / "run.json").read_text())
    time.sleep(0.05)
    with caplog.at_level(logging.INFO, logger="workbench.study"):
        run(spec, OwnerConfig(), out, workers=0, progress=False, profile=None)
    record = json.loads((out / "run.json").read_text())
    assert record["wall_time_s"] == first["wall_time_s"] and record["profile"] == "quick"
    assert record["tasks"] == {"total": 4, "computed": 4, "loaded": 0}
    assert record["last_invocation"]["tasks"] == {"total": 4, "computed": 0, "loaded": 4}
    assert record["last_invocation"]["profile"] is None
    line = (out / "report.md").read_text()
    assert f"Wall time {first['wall_time_s']:.1f} s (4 of 4 tasks computed;" in line
    assert any(r.name == "workbench.study" and "owner-toy mean" in r.message
               for r in caplog.records)  # summary lines are logged, not printed
    rebuilt = rebuild_report(spec, out).read_text()
    assert f"Wall time {first['wall_time_s']:.1f} s (4 of 4 tasks computed;" in rebuilt


# ------------------------------------------------------------------ unreadable files
def test_a_cut_short_manifest_is_an_error_naming_the_file(spec, tmp_path):
    out = tmp_path / "run"
    run(spec, OwnerConfig(), out, workers=0, progress=False)
    manifest = out / "manifest.json"
    manifest.write_text(manifest.read_text()[:40])
    with pytest.raises(ConfigError, match=rf"^{manifest} is not valid JSON .*cut short or "
                                          "edited; rerun the study"):
        rebuild_report(spec, out)
    (out / MARKER).unlink()  # an earlier version's folder: the manifest is the only owner
    before = _files(out)
    with pytest.raises(RunFolderError, match=rf"^{manifest} is not valid JSON .*delete {out}"):
        run(spec, OwnerConfig(), out, workers=0, progress=False)
    assert _files(out) == before


def test_a_marked_folder_rewrites_a_cut_short_manifest_but_a_bad_marker_is_an_error(spec,
                                                                                    tmp_path):
    out = tmp_path / "run"
    run(spec, OwnerConfig(), out, workers=0, progress=False)
    (out / "manifest.json").write_text("{")
    again = run(spec, OwnerConfig(), out, workers=0, progress=False)  # the marker owns it
    assert again.run.loaded == 4 and json.loads((out / "manifest.json").read_text())["config"]
    (out / MARKER).write_text("")
    with pytest.raises(RunFolderError, match=rf"^{out / MARKER} is empty .*delete {out} to "
                                             "start over"):
        run(spec, OwnerConfig(), out, workers=0, progress=False)


# ------------------------------------------------------------------ storage errors
@pytest.mark.parametrize("code, words", [
    (errno.ENOSPC, ("ENOSPC", "the disk is full")),
    (errno.EDQUOT, ("EDQUOT", "quota")),
    (errno.EROFS, ("EROFS", "read-only")),
    (errno.EACCES, ("EACCES", "may not write")),
])
def test_a_refused_write_names_the_file_and_the_reason_and_keeps_the_old_content(
        tmp_path, monkeypatch, code, words):
    path = tmp_path / "summary.json"
    path.write_bytes(b"old")

    def refuse(src, dst):
        raise OSError(code, os.strerror(code))

    monkeypatch.setattr(study_io.os, "replace", refuse)
    with pytest.raises(StorageError) as info:
        atomic_write_bytes(path, b"new")
    assert str(path) in str(info.value) and all(w in str(info.value) for w in words)
    assert info.value.errno == code and isinstance(info.value, OSError)
    assert path.read_bytes() == b"old" and sorted(p.name for p in tmp_path.iterdir()) == [
        "summary.json"]  # no temporary file left


def test_a_full_disk_while_storing_a_task_names_the_task_file(tmp_path, monkeypatch):
    real_replace, stored = os.replace, []

    def full_after_two(src, dst):
        if str(dst).endswith(".npz") and len(stored) >= 2:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real_replace(src, dst)
        if str(dst).endswith(".npz"):
            stored.append(dst)

    monkeypatch.setattr(study_io.os, "replace", full_after_two)
    study = study_toy.toy_study(6)
    with pytest.raises(StorageError) as info:
        run_study(study, tmp_path, workers=0, progress=False)
    msg = str(info.value)
    assert f"cannot write {tmp_path / 'tasks'}" in msg and ".npz" in msg and "ENOSPC" in msg
    assert "2 of 6 tasks are finished and stored" in msg and "rerun the same command" in msg
    assert len(list((tmp_path / "tasks").glob("*.npz"))) == 2
    assert not [p for p in tmp_path.rglob("*") if p.name.endswith(".tmp")]


def test_a_file_size_limit_while_storing_a_task_is_a_clear_error(tmp_path):
    """A real EFBIG: RLIMIT_FSIZE in a subprocess (SIGXFSZ ignored); the first task file is
    larger than the limit, the manifest and marker are not."""
    code = f"""
import resource, signal, sys
sys.path.insert(0, {str(TESTS)!r})
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (48_000, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))
import study_toy
from workbench.study import run_study
from workbench.study.io import StorageError
study = study_toy.toy_study(2)
tasks = tuple(type(t)(t.cell, t.seed_index, 20_000) for t in study.tasks)
study = type(study)(study.name, tasks, study.run_task, study.seed, study.config)
try:
    run_study(study, {str(tmp_path)!r}, workers=0, progress=False)
except StorageError as exc:
    print(exc)
    sys.exit(3)
"""
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=120, cwd=TESTS.parents[1])
    assert r.returncode == 3, r.stderr
    assert f"cannot write {tmp_path / 'tasks'}" in r.stdout and "EFBIG" in r.stdout
    assert "ulimit -f" in r.stdout and "Traceback" not in r.stderr
    assert (tmp_path / "manifest.json").is_file()
    assert not list(tmp_path.rglob("*.npz")) and not list(tmp_path.rglob("*.tmp"))

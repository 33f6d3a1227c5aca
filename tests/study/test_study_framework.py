"""The study framework (workbench/study) on a toy study: streams per task key, byte-identical
tidy data with 0/1/2 workers and a Dask LocalCluster, errors recorded with their tracebacks,
resume after a kill, and real SIGINTs (stop within seconds, nothing unfinished recorded)."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import study_toy  # tests/study_toy.py (importable by worker processes)

from workbench.study import (
    Claim,
    Rate,
    RunStore,
    Study,
    TaskOutput,
    md_table,
    run_study,
    supported,
)
from workbench.study.tasks import stream_key

TESTS = Path(__file__).parent
FILES = ("draws.parquet", "draws.csv")


def _bytes(out: Path) -> dict[str, bytes]:
    return {name: (out / name).read_bytes() for name in FILES}


def _snapshot(out: Path) -> dict[str, tuple[str, int]]:
    return {p.name: (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
            for p in (out / "tasks").glob("*.npz")}


def _start(out: Path, workers: int, n_tasks: int, sleep: float) -> subprocess.Popen:
    code = (f"import sys; sys.path.insert(0, {str(TESTS)!r}); import study_toy; "
            f"study_toy.main([{str(out)!r}, '{workers}', '{n_tasks}', '{sleep}'])")
    return subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, start_new_session=True)


def _wait_for(predicate, timeout: float = 30.0) -> None:
    t_end = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < t_end, "timed out"
        time.sleep(0.02)


def _n_done(out: Path) -> int:
    return len(list((out / "tasks").glob("*.npz"))) if (out / "tasks").exists() else 0


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> tuple[Path, dict[str, bytes], str]:
    """An uninterrupted in-process run of the 12-task toy study."""
    out = tmp_path_factory.mktemp("ref")
    run_study(study_toy.toy_study(12), out, workers=0, progress=False)
    return out, _bytes(out), study_toy.summary_json(out)


def test_streams_come_from_seed_and_task_key_not_position(tmp_path, reference):
    study = study_toy.toy_study(12)
    shuffled = Study(study.name, study.tasks[::-1], study.run_task, study.seed, study.config,
                     study.fingerprint)
    run_study(shuffled, tmp_path, workers=0, progress=False)
    ref, _, _ = reference
    a, b = RunStore(ref).table("draws"), RunStore(tmp_path).table("draws")
    key = ["cell", "seed_index", "i"]
    a, b = a.sort_values(key).reset_index(drop=True), b.sort_values(key).reset_index(drop=True)
    assert a.equals(b)
    task = study.tasks[3]
    ctx = study.context(task)
    direct = np.random.default_rng(np.random.SeedSequence(7, spawn_key=stream_key(task)))
    np.testing.assert_array_equal(ctx.rng().standard_normal(4), direct.standard_normal(4))
    np.testing.assert_array_equal(RunStore(ref).arrays(study.task_id(task))["path"],
                                  np.cumsum(ctx.rng().standard_normal(task.n)))


def test_tidy_data_byte_identical_across_workers_and_a_dask_cluster(tmp_path, reference):
    from distributed import LocalCluster

    _, ref_bytes, ref_summary = reference
    study = study_toy.toy_study(12)
    for workers in (1, 2):
        run_study(study, tmp_path / f"w{workers}", workers=workers, progress=False)
        assert _bytes(tmp_path / f"w{workers}") == ref_bytes, workers
    with LocalCluster(n_workers=1, threads_per_worker=2, processes=False, protocol="tcp",
                      host="127.0.0.1", dashboard_address=None) as cluster:
        result = run_study(study, tmp_path / "dask", scheduler=cluster.scheduler_address,
                           progress=False)
    assert result.computed == 12 and result.complete
    assert _bytes(tmp_path / "dask") == ref_bytes
    assert study_toy.summary_json(tmp_path / "dask") == ref_summary
    manifest = json.loads((tmp_path / "dask" / "manifest.json").read_text())
    assert manifest["execution"]["scheduler"].startswith("tcp://127.0.0.1")
    assert manifest["versions"]["pyarrow"] and manifest["machine"]["cpu_count"] >= 1


def test_workers_run_the_initialiser_with_one_thread(tmp_path):
    from distributed import LocalCluster

    study = study_toy.toy_study(4, init=True)
    run_study(study, tmp_path / "local", workers=2, progress=False)
    store = RunStore(tmp_path / "local")
    metas = [store.meta(i) for i in study.task_ids()]
    assert all(m["initialised"] and m["omp"] == "1" and m["threads"] == 1 for m in metas)
    assert os.getpid() not in {m["pid"] for m in metas}
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, protocol="tcp",
                      host="127.0.0.1", dashboard_address=None) as cluster:
        run_study(study, tmp_path / "dask", scheduler=cluster.scheduler_address,
                  progress=False)
    store = RunStore(tmp_path / "dask")
    assert all(store.meta(i)["initialised"] and store.meta(i)["threads"] == 1
               for i in study.task_ids())


@pytest.mark.parametrize("workers", [0, 2])
def test_a_task_that_raises_is_recorded_with_its_traceback_and_reported(tmp_path, caplog,
                                                                        workers):
    result = run_study(study_toy.toy_study(6, fail_seed=1), tmp_path, workers=workers,
                       progress=False)
    assert result.computed == 4 and len(result.errors) == 2 and not result.complete
    assert {e.task["cell"] for e in result.errors} == {"a", "b"}
    for e in result.errors:
        assert "Traceback" in e.traceback and "ValueError: toy failure in cell" in e.traceback
        assert "run_toy" in e.traceback
    assert RunStore(tmp_path).errors() == list(result.errors)
    assert any(r.name == "workbench.study" and r.levelname == "ERROR" and "ERROR" in r.message
               for r in caplog.records)  # status lines are logged (the command line prints them)
    assert not (tmp_path / "draws.parquet").exists()  # no table with silently missing tasks
    with pytest.raises(RuntimeError, match="2 of 6 tasks raised"):
        result.raise_for_errors()


def test_resume_after_a_kill_loses_and_recomputes_nothing(tmp_path, reference):
    out = tmp_path / "run"
    proc = _start(out, workers=1, n_tasks=12, sleep=0.15)
    _wait_for(lambda: _n_done(out) >= 4)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    before = _snapshot(out)
    assert 4 <= len(before) < 12
    result = run_study(study_toy.toy_study(12), out, workers=0, progress=False)
    assert (result.loaded, result.computed) == (len(before), 12 - len(before))
    after = _snapshot(out)
    assert all(after[name] == stamp for name, stamp in before.items())  # untouched
    assert _bytes(out) == reference[1]


@pytest.mark.parametrize("workers", [0, 2])
def test_sigint_stops_within_seconds_and_records_no_unfinished_task(tmp_path, workers):
    """workers=0: the running task swallows the KeyboardInterrupt and returns 'normally'; its
    result must not be recorded. workers=2: the workers ignore SIGINT and are stopped."""
    out = tmp_path / "run"
    proc = _start(out, workers=workers, n_tasks=40, sleep=0.4)
    _wait_for(lambda: _n_done(out) >= 2)
    t0 = time.monotonic()
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=10)
    assert time.monotonic() - t0 < 3.0, err
    assert proc.returncode == 130, err.decode()
    assert b"interrupted" in err
    store = RunStore(out)
    n = _n_done(out)
    assert 2 <= n < 40
    for path in (out / "tasks").glob("*.npz"):
        assert store.is_done(path.stem)
        with np.load(path) as data:
            assert not data["table:draws:interrupted"].any()
    assert not (out / "draws.parquet").exists()
    assert not list((out / "tasks").glob("*.tmp"))


def test_three_random_interrupts_then_rerun_equal_an_uninterrupted_run(tmp_path, reference):
    out = tmp_path / "run"
    rng, codes = np.random.default_rng(3), []
    for attempt, workers in enumerate((0, 2, 0)):
        t_start = time.time_ns()
        proc = _start(out, workers=workers, n_tasks=12, sleep=0.1)
        _wait_for(lambda: proc.poll() is not None or ((out / "manifest.json").exists() and (
            out / "manifest.json").stat().st_mtime_ns > t_start))  # the run has begun
        time.sleep(rng.uniform(0.0, 0.6))
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=10)
        assert proc.returncode in (130, 0), (attempt, err.decode())
        codes.append(proc.returncode)
    assert codes.count(130) >= 2, codes
    result = run_study(study_toy.toy_study(12), out, workers=2, progress=False)
    assert result.loaded + result.computed == 12
    assert _bytes(out) == reference[1]
    assert study_toy.summary_json(out) == reference[2]


def test_invalid_declarations_name_the_field(tmp_path):
    @dataclass
    class Mutable:
        x: int = 1

    @dataclass(frozen=True)
    class Listy:
        xs: list

    study = study_toy.toy_study(4)
    with pytest.raises(ValueError, match=r"^task .*frozen"):
        Study("s", (Mutable(),), study.run_task, 1)
    with pytest.raises(ValueError, match=r"^Listy.xs"):
        Study("s", (Listy([1]),), study.run_task, 1)
    with pytest.raises(ValueError, match=r"^tasks .*declared twice"):
        Study("s", study.tasks + study.tasks[:1], study.run_task, 1)
    with pytest.raises(ValueError, match=r"^run_task .*picklable"):
        Study("s", study.tasks, lambda t, c: None, 1)
    with pytest.raises(ValueError, match=r"^seed"):
        Study("s", study.tasks, study.run_task, -1)
    with pytest.raises(ValueError, match=r"^workers"):
        run_study(study, tmp_path, workers=-1)
    with pytest.raises(ValueError, match=r"^tables\['t'\]\['c'\] .*object"):
        TaskOutput(tables={"t": {"c": np.array([[1], "a"], dtype=object)}})
    with pytest.raises(ValueError, match=r"^tables\['t'\] .*equal length"):
        TaskOutput(tables={"t": {"a": np.zeros(2), "b": np.zeros(3)}})
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match=r"^out .*file"):
        run_study(study, tmp_path / "file")


def test_rate_and_claims():
    a, b = Rate(2, 100), Rate(40, 100)
    assert a.below(b) and b.above(a) and not a.below(Rate(4, 100))
    assert a.contains(0.02) and not a.contains(0.2)
    claims = [Claim("shown", a.below(b), "2% vs 40%"), Claim("hidden", b.below(a))]
    assert supported(claims) == ["- shown"]
    assert md_table(["a", "b"], [[1, 2]]) == ["| a | b |", "|---|---|", "| 1 | 2 |"]


def test_tasks_phrase_names_resumed_tasks_only_when_there_are_some():
    from workbench.study import tasks_phrase

    assert tasks_phrase(2801, 2801) == "2801 of 2801 tasks computed"
    assert tasks_phrase(3, 10) == "3 of 10 tasks computed, 7 resumed from `tasks/`"


@pytest.mark.parametrize("workers", [0, 2])
def test_a_staged_study_runs_the_rounds_it_asks_for(tmp_path, workers):
    """Rounds run one after the other as the stages ask; the task never asked for is not
    run; the tables hold the run tasks only; a rerun computes nothing; the results do not
    depend on the number of workers."""
    study = study_toy.staged_toy()
    res = run_study(study, tmp_path / "a", workers=workers, progress=False)
    assert (res.n_tasks, res.computed, res.loaded) == (8, 8, 0)
    draws = RunStore(tmp_path / "a").table("draws")
    assert sorted(set(draws["cell"])) == ["r0", "r1"]
    assert _n_done(tmp_path / "a") == 8  # round r2 (declared) never ran
    again = run_study(study, tmp_path / "a", workers=workers, progress=False)
    assert (again.n_tasks, again.computed, again.loaded) == (8, 0, 8)
    ref = tmp_path / "ref"
    run_study(study, ref, workers=0, progress=False)
    assert _bytes(tmp_path / "a") == _bytes(ref)


def test_stages_may_only_choose_declared_tasks(tmp_path):
    study = study_toy.staged_toy()
    bad = Study(study.name, study.tasks[:4], study.run_task, study.seed, study.config,
                study.fingerprint, stages=study.stages)
    with pytest.raises(ValueError, match=r"^stages"):
        run_study(bad, tmp_path, workers=0, progress=False)

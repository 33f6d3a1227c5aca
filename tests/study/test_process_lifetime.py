"""Processes end: local workers die with their coordinator (even on kill -9), a task over its
time limit is stopped and recorded as an error (local workers, in this process, Dask), and a
malformed or unreachable scheduler fails within seconds before anything is written."""

from __future__ import annotations

import math
import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from workbench.study import RunStore, Study, TaskOutput, run_study
from workbench.study.config_io import ConfigError

TESTS = Path(__file__).parent
LINUX = sys.platform.startswith("linux")


@dataclass(frozen=True)
class Nap:
    i: int
    seconds: float


def nap(task: Nap, ctx) -> TaskOutput:
    """Sleeps, then returns its index (a task that hangs when ``seconds`` is large)."""
    time.sleep(task.seconds)
    return TaskOutput(tables={"naps": {"slept": np.array([float(task.seconds)])}})


def nap_study(*seconds: float) -> Study:
    return Study("naps", tuple(Nap(i, float(s)) for i, s in enumerate(seconds)), nap, seed=0,
                 config={"seconds": [float(s) for s in seconds]})


def coordinator(out: str, workers: int, *seconds: float) -> None:
    """Entry point of a coordinator subprocess."""
    run_study(nap_study(*seconds), out, workers=workers, progress=False)


def _proc_stat(pid: int) -> list[str] | None:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None


def _workers_of(pid: int) -> list[int]:
    """Spawned worker processes whose parent is ``pid``."""
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            stat = _proc_stat(int(d.name))
            try:
                if stat and int(stat[1]) == pid and b"spawn_main" in (d / "cmdline").read_bytes():
                    out.append(int(d.name))
            except OSError:
                pass
    return out


def _running(pid: int) -> bool:
    stat = _proc_stat(pid)
    return stat is not None and stat[0] != "Z"  # a zombie has ended


# ------------------------------------------------------------ workers die with the coordinator
@pytest.mark.skipif(not LINUX, reason="reads /proc")
def test_workers_die_when_their_coordinator_is_killed(tmp_path):
    code = (f"import sys; sys.path.insert(0, {str(TESTS)!r}); import test_process_lifetime as "
            f"t; t.coordinator({str(tmp_path / 'run')!r}, 2, 60, 60, 60, 60)")
    proc = subprocess.Popen([sys.executable, "-c", code], stderr=subprocess.PIPE,
                            start_new_session=True)
    workers: list[int] = []
    try:
        t_end = time.monotonic() + 60
        while len(workers) < 2:
            assert time.monotonic() < t_end and proc.poll() is None, proc.stderr.read()
            time.sleep(0.1)
            workers = _workers_of(proc.pid)
        time.sleep(1.0)  # the workers are in their first (60 s) task
        assert all(_running(w) for w in workers)
        os.kill(proc.pid, signal.SIGKILL)  # as an out-of-memory kill or a CI timeout would
        proc.wait()
        t_end = time.monotonic() + 10
        while any(_running(w) for w in workers) and time.monotonic() < t_end:
            time.sleep(0.05)
        assert not any(_running(w) for w in workers), "workers outlived their coordinator"
    finally:
        for pid in [proc.pid, *workers]:
            if _running(pid):
                os.kill(pid, signal.SIGKILL)
        proc.communicate()


def test_a_worker_whose_coordinator_is_already_gone_exits_at_start():
    """The race: the coordinator ends before the worker asked to be killed with it."""
    code = ("import os, sys; from workbench.study.execute import die_with_parent; "
            "die_with_parent(int(sys.argv[1])); print('alive')")
    gone = subprocess.run([sys.executable, "-c", code, "1"], capture_output=True, text=True,
                          timeout=60)
    assert gone.returncode == 1 and "alive" not in gone.stdout
    here = subprocess.run([sys.executable, "-c", code, str(os.getpid())], capture_output=True,
                          text=True, timeout=60)
    assert here.returncode == 0 and "alive" in here.stdout


# ------------------------------------------------------------------ time limits
def test_a_local_task_over_its_time_limit_is_stopped_and_recorded(tmp_path):
    t0 = time.monotonic()
    result = run_study(nap_study(120, 0, 0), tmp_path, workers=1, progress=False,
                       task_timeout_s=1.5)
    assert time.monotonic() - t0 < 60  # not 120 s
    assert result.computed == 2 and len(result.errors) == 1
    err = result.errors[0]
    assert err.task["i"] == 0 and "task timed out after 1.5 s" in err.headline()
    assert "worker process was stopped" in err.traceback
    assert [e.task_id for e in RunStore(tmp_path).errors()] == [err.task_id]
    assert not RunStore(tmp_path).is_done(err.task_id)


def test_in_this_process_the_time_limit_is_checked_when_the_task_returns(tmp_path):
    result = run_study(nap_study(0.5, 0), tmp_path, workers=0, progress=False,
                       task_timeout_s=0.2)
    assert result.computed == 1 and len(result.errors) == 1
    assert "task timed out after 0.2 s" in result.errors[0].headline()
    assert "its result is not kept" in result.errors[0].traceback
    assert not RunStore(tmp_path).is_done(result.errors[0].task_id)
    again = run_study(nap_study(0.5, 0), tmp_path, workers=0, progress=False)  # no limit
    assert again.computed == 1 and again.loaded == 1 and again.complete


def test_a_dask_task_over_its_time_limit_is_cancelled_and_recorded(tmp_path):
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=2, processes=False, protocol="tcp",
                      host="127.0.0.1", dashboard_address=None) as cluster:
        t0 = time.monotonic()
        result = run_study(nap_study(4, 0), tmp_path, scheduler=cluster.scheduler_address,
                           progress=False, task_timeout_s=0.5)
        assert time.monotonic() - t0 < 3.5  # recorded before the task would have returned
    assert result.computed == 1 and len(result.errors) == 1
    assert "task timed out after 0.5 s" in result.errors[0].headline()


@pytest.mark.parametrize("value", [0, -1.0, math.nan, math.inf, True, "5"])
def test_the_time_limit_is_validated_before_anything_is_written(tmp_path, value):
    with pytest.raises(ValueError, match=r"^task_timeout_s = .* is invalid"):
        run_study(nap_study(0), tmp_path / "run", workers=0, task_timeout_s=value)
    assert not (tmp_path / "run").exists()


# ------------------------------------------------------------------ the scheduler
@pytest.mark.parametrize("address", ["nonsense", "tcp://host", "http://host:8786",
                                     "tcp://host:0", "tcp://host:70000", "tcp://:8786", ""])
def test_a_malformed_scheduler_fails_at_once_before_anything_is_written(tmp_path, address):
    t0 = time.monotonic()
    with pytest.raises(ConfigError, match=r"^scheduler = .* is invalid: .*tcp://host:8786"):
        run_study(nap_study(0), tmp_path / "run", scheduler=address, progress=False)
    assert time.monotonic() - t0 < 5.0 and not (tmp_path / "run").exists()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("address", [f"tcp://127.0.0.1:{_free_port()}",  # refused
                                     "tcp://no-such-host.invalid:8786",  # no such name
                                     "tcp://10.255.255.1:8786"])  # no answer, no route or proxy
def test_an_unreachable_scheduler_fails_within_seconds_before_anything_is_written(tmp_path,
                                                                                  address):
    t0 = time.monotonic()
    with pytest.raises(ConfigError, match=r"(cannot reach a Dask scheduler at|is not a Dask "
                                          r"scheduler).*check"):  # a proxy may accept
        run_study(nap_study(0), tmp_path / "run", scheduler=address, progress=False)
    assert time.monotonic() - t0 < 20.0  # a hang check (the limits are 5 and 10 s)
    assert not (tmp_path / "run").exists()


def test_a_port_that_is_not_a_dask_scheduler_fails_within_seconds(tmp_path):
    """Something listens but stays silent (the Dask client itself would wait for ever)."""
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen(8)
        address = f"tcp://127.0.0.1:{server.getsockname()[1]}"
        t0 = time.monotonic()
        with pytest.raises(ConfigError, match=r"something listens at 127\.0\.0\.1:\d+ but it "
                                              r"is not a Dask scheduler \(it accepted"):
            run_study(nap_study(0), tmp_path / "run", scheduler=address, progress=False)
        assert time.monotonic() - t0 < 20.0
    assert not (tmp_path / "run").exists()

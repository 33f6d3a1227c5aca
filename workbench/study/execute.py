"""Run a study's pending tasks: in this process, in local worker processes, or on a Dask cluster.

Only the coordinating process writes results, one finished task at a time (atomically), so an
interrupted or killed run keeps every task it finished and nothing else; a rerun computes only
the rest. SIGINT/SIGTERM set a stop flag and stop the run within about a second: local workers
ignore SIGINT and are terminated, Dask futures are cancelled. A task that finishes after the
stop flag is set is discarded, whatever it returns (a task may swallow KeyboardInterrupt).
"""

from __future__ import annotations

import _thread
import contextlib
import os
import signal
import socket
import sys
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from multiprocessing import connection, get_context
from pathlib import Path
from typing import Any

from tqdm import tqdm

from workbench.study.store import RunStore, TaskError, TaskRecord
from workbench.study.tasks import Study, TaskContext, TaskOutput
from workbench.validation import fail

THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
_STOP = threading.Event()


class StudyInterrupted(KeyboardInterrupt):
    """The run was stopped by SIGINT/SIGTERM; finished tasks are stored, rerun to continue."""


@dataclass(frozen=True)
class RunResult:
    """What a run did: task counts, errors (with tracebacks), wall time, whether every task is
    finished (then the tidy tables were written)."""

    root: Path
    n_tasks: int
    computed: int
    loaded: int
    errors: tuple[TaskError, ...]
    wall_time_s: float

    @property
    def complete(self) -> bool:
        return not self.errors

    def raise_for_errors(self) -> None:
        if self.errors:
            lines = "\n".join(f"  {e.headline()}" for e in self.errors)
            raise RuntimeError(f"{len(self.errors)} of {self.n_tasks} tasks raised (tracebacks "
                               f"in {self.root / 'errors.json'}):\n{lines}")


def _execute(run_task: Callable, task: Any, ctx: TaskContext) -> TaskRecord:
    """Run one task; an exception becomes an error record with its traceback."""
    t0 = time.perf_counter()
    worker = f"{socket.gethostname()}:{os.getpid()}"
    try:
        out = run_task(task, ctx)
        if not isinstance(out, TaskOutput):
            raise TypeError(f"run_task returned {type(out).__name__}, expected TaskOutput")
        return TaskRecord(ctx.task_id, output=out, elapsed_s=time.perf_counter() - t0,
                          worker=worker)
    except Exception:
        return TaskRecord(ctx.task_id, error=traceback.format_exc(),
                          elapsed_s=time.perf_counter() - t0, worker=worker)


def limit_threads() -> None:
    """Set the thread environment of a worker to one thread (before any OpenMP library loads)."""
    for name in THREAD_ENV:
        os.environ[name] = "1"


# ---------------------------------------------------------------------- local worker processes
def _worker_main(conn, run_task: Callable, init: Callable | None) -> None:
    # Only the coordinator decides when to stop: SIGINT stays ignored and blocked (a solver's
    # own handler cannot catch it), the worker leaves the terminal's process group, and SIGTERM
    # (sent by the coordinator) ends it at once.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    os.setpgrp()
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})
    limit_threads()
    init_error = None
    try:
        if init is not None:
            init()
    except Exception:
        init_error = "worker_init failed:\n" + traceback.format_exc()
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        if msg is None:
            return
        task, ctx = msg
        rec = (TaskRecord(ctx.task_id, error=init_error) if init_error
               else _execute(run_task, task, ctx))
        try:
            conn.send(rec)
        except Exception:
            conn.send(TaskRecord(ctx.task_id, error="result could not be sent back:\n"
                                 + traceback.format_exc()))


@contextlib.contextmanager
def _spawn_env():
    """Children inherit one-thread settings and an ignored SIGINT from the moment they start."""
    saved = {k: os.environ.get(k) for k in THREAD_ENV}
    limit_threads()
    in_main = threading.current_thread() is threading.main_thread()
    old = signal.signal(signal.SIGINT, signal.SIG_IGN) if in_main else None
    try:
        yield
    finally:
        if in_main:
            signal.signal(signal.SIGINT, old)
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


class _Worker:
    def __init__(self, mp, run_task, init):
        self.conn, child = mp.Pipe()
        with _spawn_env():
            self.proc = mp.Process(target=_worker_main, args=(child, run_task, init), daemon=True)
            self.proc.start()
        child.close()
        self.item = None

    def stop(self, hard: bool) -> None:
        if not hard:
            with contextlib.suppress(OSError):
                self.conn.send(None)
            self.proc.join(5)
        if self.proc.is_alive():
            self.proc.terminate()
            self.proc.join(2)
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join()
        self.conn.close()


def _local(study: Study, pending: list, workers: int) -> Iterator[tuple[Any, TaskRecord]]:
    mp = get_context("spawn")
    queue = deque(pending)
    pool = [_Worker(mp, study.run_task, study.worker_init) for _ in range(workers)]
    hard = True
    try:
        while queue or any(w.item is not None for w in pool):
            for w in pool:
                if w.item is None and queue:
                    w.item = queue.popleft()
                    with contextlib.suppress(OSError):  # a dead worker is handled below
                        w.conn.send(w.item)
            busy = [w for w in pool if w.item is not None]
            connection.wait([w.conn for w in busy] + [w.proc.sentinel for w in busy], 0.5)
            for i, w in enumerate(pool):
                if w.item is None:
                    continue
                item, rec = w.item, None
                with contextlib.suppress(EOFError, OSError):
                    if w.conn.poll():
                        rec = w.conn.recv()
                if rec is None and not w.proc.is_alive():
                    rec = TaskRecord(item[1].task_id, error=f"worker process died (exit code "
                                     f"{w.proc.exitcode}) while running this task")
                    w.stop(hard=True)
                    pool[i] = _Worker(mp, study.run_task, study.worker_init)
                if rec is not None:
                    w.item = None
                    yield item, rec
        hard = False
    finally:
        for w in pool:
            w.stop(hard)


def _in_process(study: Study, pending: list) -> Iterator[tuple[Any, TaskRecord]]:
    for task, ctx in pending:
        rec = _execute(study.run_task, task, ctx)
        if _STOP.is_set():  # the task swallowed the interrupt: its result is not trusted
            raise StudyInterrupted
        yield (task, ctx), rec


# ---------------------------------------------------------------------- signals and the run
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def _on_signal(signum, frame) -> None:
    _STOP.set()
    raise StudyInterrupted


def _watch(done: threading.Event) -> None:
    """Take SIGINT/SIGTERM off the process with sigtimedwait (they are blocked in every thread
    the run starts), set the stop flag and interrupt the main thread once. A C library that
    installs its own SIGINT handler (OSQP does, and then swallows the signal) never sees it."""
    while not done.is_set():
        if signal.sigtimedwait(STOP_SIGNALS, 0.1) is not None and not _STOP.is_set():
            _STOP.set()
            _thread.interrupt_main(signal.SIGINT)


@contextlib.contextmanager
def _stop_on_signals():
    _STOP.clear()
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {s: signal.signal(s, _on_signal) for s in STOP_SIGNALS}
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
    done = threading.Event()
    watcher = threading.Thread(target=_watch, args=(done,), name="study-signals", daemon=True)
    watcher.start()
    try:
        yield
    finally:
        done.set()
        watcher.join()
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        for s, h in old.items():
            signal.signal(s, h)


def run_study(study: Study, out: Path | str, *, workers: int = 2, scheduler: Any = None,
              progress: bool = True) -> RunResult:
    """Run (or continue) ``study`` in the directory ``out``.

    workers: 0 runs tasks in this process; N >= 1 in N spawned worker processes (one thread
    each). scheduler: a Dask scheduler address (or a ``distributed.Client``) instead of local
    workers. Writes the manifest first, each finished task as it arrives, the errors, and the
    tidy tables once every task is finished. Raises :class:`StudyInterrupted` on SIGINT/SIGTERM.
    """
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 0:
        raise fail("workers", workers, "must be an integer >= 0 (0 = in this process)")
    t0 = time.perf_counter()
    store = RunStore(Path(out))
    backend = ({"scheduler": scheduler if isinstance(scheduler, str) else repr(scheduler)}
               if scheduler is not None else {"workers": workers})
    ids = study.task_ids()
    threads = 1 if (workers or scheduler is not None) else max(1, os.cpu_count() or 1)
    errors: list[TaskError] = []
    computed, records, bar = 0, None, None
    with _stop_on_signals():
        try:
            store.write_manifest(study, backend)
            done = store.finished(ids)
            pending = [(t, study.context(t, threads))
                       for t, i in zip(study.tasks, ids, strict=True) if i not in done]
            bar = tqdm(total=len(ids), initial=len(done), desc=study.name, unit="task",
                       file=sys.stderr, disable=not progress, smoothing=0.05,
                       dynamic_ncols=True)
            if not pending:
                records = (r for r in ())
            elif scheduler is not None:
                from workbench.study.cluster import dask_records
                records = dask_records(study, pending, scheduler, _execute)
            elif workers == 0:
                records = _in_process(study, pending)
            else:
                records = _local(study, pending, min(workers, len(pending)))
            for (task, _), rec in records:
                if _STOP.is_set():
                    raise StudyInterrupted
                if rec.ok:
                    store.save(task, rec)
                    computed += 1
                else:
                    errors.append(store.save_error(task, rec))
                    bar.set_postfix(errors=len(errors))
                bar.update()
            records.close()
            bar.close()
            store.write_errors(errors)
            for e in errors:
                print(f"{study.name}: ERROR {e.headline()}", file=sys.stderr)
            if not errors:
                store.write_tables(store.build_tables(study))
        except KeyboardInterrupt:
            _STOP.set()
            if records is not None:
                records.close()  # stops the workers at once
            if bar is not None:
                bar.close()
            n = len(store.finished(ids))
            print(f"\n{study.name}: interrupted; {n} of {len(ids)} tasks finished and stored in "
                  f"{store.root}; rerun the same command to continue", file=sys.stderr)
            raise StudyInterrupted from None
        finally:
            if records is not None:
                records.close()
    return RunResult(store.root, len(ids), computed, len(done), tuple(errors),
                     time.perf_counter() - t0)

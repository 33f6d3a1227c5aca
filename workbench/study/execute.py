"""Run a study's pending tasks: in this process, in local worker processes, or on a Dask cluster.

Only the coordinating process writes results, one finished task at a time (atomically), so an
interrupted or killed run keeps every task it finished and nothing else; a rerun computes only
the rest. Before anything is written the run checks the scheduler (when one is given) and claims
its folder (:mod:`workbench.study.folder`: one run per folder, locked while it runs).

Interrupts: during a run SIGINT/SIGTERM are blocked and taken by a watcher thread, so a C library
with its own SIGINT handler (OSQP) cannot swallow them; the watcher sets a stop flag and
interrupts the main thread. Local workers never see SIGINT (own process group, blocked) and are
terminated; Dask futures are cancelled. A task that finishes after the stop flag is set is
discarded, whatever it returns (a task may swallow KeyboardInterrupt).

Workers end with their coordinator: on Linux each worker asks the kernel to SIGKILL it when the
coordinator ends (``prctl(PR_SET_PDEATHSIG)``), however the coordinator ends (``kill -9``, an
out-of-memory kill, a CI timeout), and exits at once if the coordinator ended before it could
ask; elsewhere a thread in each worker checks every second that its parent is still there. (The
kernel ties the signal to the thread that started the worker: :func:`run_study` starts and stops
its workers in the calling thread, before it returns.)

Time limit (``task_timeout_s``, default None: none): a local worker whose task runs longer
(counted from when the worker begins it, so its start-up does not count) is stopped (and
replaced) and the task is recorded as an error ``task timed out after N s``
(retried on the next run, like any error); on a Dask cluster the task is cancelled (see
:mod:`workbench.study.cluster`); in this process (``workers=0``) a task cannot be stopped, so
the limit is checked when it returns: a task that took longer is recorded as the same error and
its result is not kept, so that every back end keeps the same tasks.

Provenance: each task is stored with the evaluator, its result-changing settings and code hash
of the process that computed it (:mod:`workbench.study.provenance`). Continuing a run whose
stored tasks were computed by other code, another evaluator or other settings than this process
would use is refused (:class:`MixedResultsError`) unless ``allow_mixed=True``.

Status lines go to the ``workbench.study`` logger (errors and interrupts as ERROR/WARNING).
"""

from __future__ import annotations

import _thread
import contextlib
import ctypes
import logging
import os
import signal
import socket
import sys
import threading
import time
import traceback
from collections import Counter, deque
from collections.abc import Callable, Generator, Iterator
from dataclasses import dataclass
from multiprocessing import connection, get_context
from pathlib import Path
from typing import Any

from tqdm import tqdm

import workbench.study.provenance as provenance
from workbench.study.folder import RunFolderError, claim
from workbench.study.io import StorageError
from workbench.study.store import RunStore, TaskError, TaskRecord, study_manifest
from workbench.study.tasks import Study, TaskContext, TaskOutput
from workbench.study.threads import THREAD_ENV, limit_threads
from workbench.validation import fail, flag, real

_STOP = threading.Event()
log = logging.getLogger("workbench.study")
PR_SET_PDEATHSIG = 1
_STARTED = "started"  # a worker's notice that it began the task it was given


class StudyInterrupted(KeyboardInterrupt):
    """The run was stopped by SIGINT/SIGTERM; finished tasks are stored, rerun to continue."""


class TasksFailed(RuntimeError):
    """Some tasks raised (a timeout is one): each is recorded in ``errors.json`` with its
    traceback and retried on the next run; the message lists them, one line each."""


class MixedResultsError(RunFolderError):
    """Stored tasks were computed by other code or another evaluator than this run would use."""


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

    def raise_for_errors(self, shown: int = 10) -> None:
        """:class:`TasksFailed` listing the first ``shown`` tasks that raised, one line each."""
        if self.errors:
            lines = [f"  {e.headline()}" for e in self.errors[:shown]]
            if len(self.errors) > shown:
                lines.append(f"  ... and {len(self.errors) - shown} more")
            raise TasksFailed(f"{len(self.errors)} of {self.n_tasks} tasks raised (tracebacks "
                              f"in {self.root / 'errors.json'}; a rerun retries them):\n"
                              + "\n".join(lines))


def check_workers(workers: Any) -> int:
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 0:
        raise fail("workers", workers, "must be an integer >= 0 (0 = in this process)")
    return workers


def check_timeout(task_timeout_s: Any) -> float | None:
    """None (no limit) or a finite number of seconds > 0."""
    if task_timeout_s is None:
        return None
    return real("task_timeout_s", task_timeout_s, 0.0, strict=True)


def _timeout_text(timeout: float, how: str) -> str:
    return (f"TimeoutError: task timed out after {timeout:g} s (task_timeout_s = {timeout:g}); "
            f"{how}")


def _execute(run_task: Callable, task: Any, ctx: TaskContext) -> TaskRecord:
    """Run one task; an exception becomes an error record with its traceback. A finished
    task carries the evaluator and code hash of this process."""
    t0 = time.perf_counter()
    worker = f"{socket.gethostname()}:{os.getpid()}"
    try:
        out = run_task(task, ctx)
        if not isinstance(out, TaskOutput):
            raise TypeError(f"run_task returned {type(out).__name__}, expected TaskOutput")
        return TaskRecord(ctx.task_id, output=out, elapsed_s=time.perf_counter() - t0,
                          worker=worker, provenance=provenance.current(run_task))
    except Exception:
        return TaskRecord(ctx.task_id, error=traceback.format_exc(),
                          elapsed_s=time.perf_counter() - t0, worker=worker)


# ---------------------------------------------------------------------- local worker processes
def _watch_parent(parent_pid: int) -> None:
    while True:
        time.sleep(1.0)
        if os.getppid() != parent_pid:
            os._exit(1)


def die_with_parent(parent_pid: int) -> None:
    """Make this process end when ``parent_pid`` (its parent) ends: on Linux the kernel sends
    SIGKILL when the parent ends (PR_SET_PDEATHSIG); elsewhere a thread checks every second.
    Exits at once (code 1) if the parent has already gone (the process was reparented)."""
    armed = False
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            armed = libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0
        except (OSError, AttributeError):
            armed = False
    if os.getppid() != parent_pid:  # the parent ended before the signal was asked for
        os._exit(1)
    if not armed:
        threading.Thread(target=_watch_parent, args=(parent_pid,), daemon=True,
                         name="parent-watch").start()


def _worker_main(conn, run_task: Callable, init: Callable | None, parent_pid: int) -> None:
    # Only the coordinator decides when to stop: SIGINT stays ignored and blocked (a solver's
    # own handler cannot catch it), the worker leaves the terminal's process group, and SIGTERM
    # (sent by the coordinator) ends it at once. It ends with the coordinator, however that ends.
    die_with_parent(parent_pid)
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
        with contextlib.suppress(OSError):
            conn.send(_STARTED)  # the time limit counts from here, not from the worker's start
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
            self.proc = mp.Process(target=_worker_main,
                                   args=(child, run_task, init, os.getpid()), daemon=True)
            self.proc.start()
        child.close()
        self.item = None
        self.started: float | None = None  # when the worker began its item

    def give(self, item) -> None:
        self.item, self.started = item, None
        with contextlib.suppress(OSError):  # a dead worker is handled by the pool
            self.conn.send(item)

    def receive(self) -> TaskRecord | None:
        """The record of the item, if it has come back (notes the start notice on the way)."""
        while self.conn.poll():
            msg = self.conn.recv()
            if msg == _STARTED:
                self.started = time.monotonic()
            else:
                return msg
        return None

    def over(self, timeout: float | None) -> bool:
        return (timeout is not None and self.started is not None
                and time.monotonic() - self.started > timeout)

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


def _local(study: Study, pending: list, workers: int,
           timeout: float | None) -> Generator[tuple[Any, TaskRecord], None, None]:
    mp = get_context("spawn")
    queue = deque(pending)
    pool = [_Worker(mp, study.run_task, study.worker_init) for _ in range(workers)]
    hard = True
    try:
        while queue or any(w.item is not None for w in pool):
            for w in pool:
                if w.item is None and queue:
                    w.give(queue.popleft())
            busy = [w for w in pool if w.item is not None]
            wait_s = 0.5
            running = [w.started for w in busy if w.started is not None]
            if timeout is not None and running:
                left = min(running) + timeout - time.monotonic()
                wait_s = min(wait_s, max(left, 0.0) + 0.01)
            connection.wait([w.conn for w in busy] + [w.proc.sentinel for w in busy], wait_s)
            for i, w in enumerate(pool):
                if w.item is None:
                    continue
                item, rec = w.item, None
                with contextlib.suppress(EOFError, OSError):
                    rec = w.receive()
                if rec is None and not w.proc.is_alive():
                    rec = TaskRecord(item[1].task_id, error=f"worker process died (exit code "
                                     f"{w.proc.exitcode}) while running this task")
                elif rec is None and timeout is not None and w.over(timeout):
                    rec = TaskRecord(item[1].task_id, error=_timeout_text(
                        timeout, "its worker process was stopped"))
                else:
                    if rec is not None:
                        w.item = None
                        yield item, rec
                    continue
                w.stop(hard=True)
                pool[i] = _Worker(mp, study.run_task, study.worker_init)
                yield item, rec
        hard = False
    finally:
        for w in pool:
            w.stop(hard)


def _in_process(study: Study, pending: list,
                timeout: float | None) -> Generator[tuple[Any, TaskRecord], None, None]:
    for task, ctx in pending:
        rec = _execute(study.run_task, task, ctx)
        if _STOP.is_set():  # the task swallowed the interrupt: its result is not trusted
            raise StudyInterrupted
        if timeout is not None and rec.elapsed_s > timeout:
            rec = TaskRecord(ctx.task_id, error=_timeout_text(
                timeout, f"it ran {rec.elapsed_s:.3g} s in this process, which cannot stop a "
                "task early (local workers, workers >= 1, stop it at the limit); its result is "
                "not kept"), elapsed_s=rec.elapsed_s, worker=rec.worker)
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


@contextlib.contextmanager
def scheduler_client(scheduler: Any) -> Iterator[tuple[Any, str | None]]:
    """(client, address) for a scheduler address or Client, connected before anything is
    written (malformed or unreachable: an error within seconds); (None, None) without one. A
    client made here is closed on exit."""
    if scheduler is None:
        yield None, None
        return
    from workbench.study.cluster import connect  # loads distributed: only with a scheduler

    client, own, address = connect(scheduler)
    try:
        yield client, address
    finally:
        if own:
            client.close()


def _origin(p: dict) -> str:
    """A task's provenance in words: evaluator, its settings (when any), code hash."""
    sets = p.get("settings")
    shown = "" if not sets else ", settings " + ", ".join(
        f"{k}={v!r}" for k, v in sorted(sets.items()))
    return f"evaluator {p.get('evaluator')!r}{shown}, code {str(p.get('code_sha256'))[:12]}"


def _mixed(store: RunStore, headers: dict, current: dict) -> MixedResultsError | None:
    """The error for stored tasks computed by other code or another evaluator, or None."""
    other: Counter[str] = Counter()
    for h in headers.values():
        p = h.get("provenance")
        if p != current:
            other["no record (stored by an earlier version)" if not p else _origin(p)] += 1
    if not other:
        return None
    n = sum(other.values())
    groups = "; ".join(f"{k}: {v}" for k, v in sorted(other.items()))
    return MixedResultsError(
        f"{n} of {len(headers)} stored tasks in {store.root} were computed by other code or "
        f"another evaluator or evaluator setting than this run would use ({_origin(current)}; "
        f"stored: {groups}). Reusing them would mix results "
        "(another evaluator draws other noise, so common random numbers would break). To "
        "recompute everything, choose a fresh folder with --out or delete this one; to reuse "
        "them anyway, pass allow_mixed=True (command line: --allow-mixed)")


def refuse_mixed(study: Study, root: Path | str) -> None:
    """Raise :class:`MixedResultsError` if stored tasks of ``study`` in ``root`` (a claimed
    folder) were computed by other code or another evaluator than this process would use."""
    store = RunStore(Path(root))
    err = _mixed(store, store.headers(study.task_ids()), provenance.current(study.run_task))
    if err is not None:
        raise err


def run_study(study: Study, out: Path | str, *, workers: int = 2, scheduler: Any = None,
              progress: bool = True, task_timeout_s: float | None = None,
              allow_mixed: bool = False) -> RunResult:
    """Run (or continue) ``study`` in the directory ``out``.

    workers: 0 runs tasks in this process; N >= 1 in N spawned worker processes (one thread
    each). scheduler: a Dask scheduler address (or a ``distributed.Client``) instead of local
    workers; checked (and connected) before anything is written. task_timeout_s: time limit of
    one task in seconds (None: none); a task over it is recorded as an error. allow_mixed: reuse
    stored tasks that other code or another evaluator computed (else
    :class:`MixedResultsError`). Claims ``out`` (:func:`workbench.study.folder.claim`), writes
    the manifest, each finished task as it arrives, the errors, and the tidy tables once every
    task is finished. Raises :class:`StudyInterrupted` on SIGINT/SIGTERM and
    :class:`~workbench.study.io.StorageError` when a result file cannot be written.
    """
    workers = check_workers(workers)
    timeout = check_timeout(task_timeout_s)
    allow_mixed = flag("allow_mixed", allow_mixed)
    current = provenance.current(study.run_task)
    with scheduler_client(scheduler) as (client, address), \
            claim(Path(out), study_manifest(study)):
        return _run_claimed(study, RunStore(Path(out)), workers, client, address, progress,
                            timeout, allow_mixed, current)


def _run_claimed(study: Study, store: RunStore, workers: int, client: Any, address: str | None,
                 progress: bool, timeout: float | None, allow_mixed: bool,
                 current: dict) -> RunResult:
    t0 = time.perf_counter()
    backend: dict[str, Any] = ({"scheduler": address} if client is not None
                               else {"workers": workers})
    backend["task_timeout_s"] = timeout
    ids = study.task_ids()
    threads = 1 if (workers or client is not None) else max(1, os.cpu_count() or 1)
    errors: list[TaskError] = []
    computed, bar = 0, None
    records: Generator[tuple[Any, TaskRecord], None, None] | None = None
    headers = store.headers(ids)
    done = set(headers)
    mixed = _mixed(store, headers, current)
    if mixed is not None and not allow_mixed:
        raise mixed
    if mixed is not None:
        log.warning("%s: %s", study.name, str(mixed).split(". Reusing")[0]
                    + "; reused (allow_mixed)")
        backend["allow_mixed"] = True
    id_of = dict(zip(study.tasks, ids, strict=True))
    targets = list(study.tasks)
    with _stop_on_signals():
        try:
            store.write_manifest(study, backend, provenance.describe(study.run_task))
            targets = study.stage(store.outputs_of(id_of))
            bar = tqdm(total=len(targets), initial=len(done & {id_of[t] for t in targets}),
                       desc=study.name, unit="task", file=sys.stderr, disable=not progress,
                       smoothing=0.05, dynamic_ncols=True)
            while True:  # one pass per stage (a study without stages has one)
                pending = [(t, study.context(t, threads)) for t in targets
                           if id_of[t] not in done]
                if not pending:
                    break
                if client is not None:
                    from workbench.study.cluster import dask_records
                    records = dask_records(study, pending, client, _execute, timeout)
                elif workers == 0:
                    records = _in_process(study, pending, timeout)
                else:
                    records = _local(study, pending, min(workers, len(pending)), timeout)
                for (task, _), rec in records:
                    if _STOP.is_set():
                        raise StudyInterrupted
                    if rec.ok:
                        store.save(task, rec)
                        done.add(rec.task_id)
                        computed += 1
                    else:
                        errors.append(store.save_error(task, rec))
                        bar.set_postfix(errors=len(errors))
                    bar.update()
                records.close()
                if errors or study.stages is None:
                    break
                more = study.stage(store.outputs_of(id_of))
                bar.total += len(more) - len(targets)
                bar.refresh()
                targets = more
            bar.close()
            store.write_errors(errors)
            for e in errors:
                log.error("%s: ERROR %s", study.name, e.headline())
            if not errors:
                store.write_tables(store.build_tables(study, targets))
        except KeyboardInterrupt:
            _STOP.set()
            if records is not None:
                records.close()  # stops the workers at once
            if bar is not None:
                bar.close()
            n = len(store.finished(id_of[t] for t in targets))
            log.warning("%s: interrupted; %d of %d tasks finished and stored in %s; rerun the "
                        "same command to continue", study.name, n, len(targets), store.root)
            raise StudyInterrupted from None
        except StorageError as exc:
            if records is not None:
                records.close()
            if bar is not None:
                bar.close()
            n = len(store.finished(id_of[t] for t in targets))
            raise exc.with_advice(
                f"{n} of {len(targets)} tasks are finished and stored; once there is room (or the "
                "limit is raised), rerun the same command to continue") from exc
        finally:
            if records is not None:
                records.close()
    return RunResult(store.root, len(targets), computed, len(targets) - computed
                     - len(errors), tuple(errors), time.perf_counter() - t0)

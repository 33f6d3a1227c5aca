"""Dask ``distributed`` back end: the same task records, computed on a cluster's workers.

:func:`connect` checks the address (:func:`workbench.study.scheduler.check_scheduler`: format,
then a TCP connection within 5 s) and connects the client (at most :data:`CLIENT_TIMEOUT_S`), so
a wrong or unreachable scheduler fails within seconds, before the run writes anything.

A task time limit (``task_timeout_s``) counts from the moment a task is handed to the cluster;
so that waiting in the queue does not count, only as many tasks are handed over at a time as
the cluster has worker threads. A task over the limit is cancelled and recorded as an error;
Dask cannot stop a running Python function, so its worker thread may go on until the function
returns (its result is discarded).

The repository's ``studies`` is not installed (:mod:`workbench.study.checkout`): each task's
function, description and context travel pickled as bytes (:func:`run_pickled`), so the
scheduler, which unpickles the task graph, never imports them; each worker first puts the
checkout beside its own ``workbench`` on ``sys.path``. Start the workers from an editable install
of the same revision.
"""

from __future__ import annotations

import os
import pickle
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable, Generator
from typing import Any

from distributed import Client, wait
from distributed.diagnostics.plugin import WorkerPlugin

from workbench.study.checkout import has_checkout_studies, use_checkout_studies
from workbench.study.scheduler import SchedulerError, check_scheduler
from workbench.study.store import TaskRecord
from workbench.study.tasks import Study
from workbench.study.threads import limit_threads
from workbench.validation import fail

CLIENT_TIMEOUT_S = 10.0


class WorkerInit(WorkerPlugin):
    """Sets up each worker: the repository's ``studies`` first on ``sys.path`` (from the checkout
    beside the worker's ``workbench``, :mod:`workbench.study.checkout`), the one-thread
    environment, then the study's worker initialiser. The initialiser travels pickled and is
    loaded only after the path is set, since it may live in ``studies``."""

    def __init__(self, init: Callable[[], None] | None):
        self.init = None if init is None else pickle.dumps(init)
        self.client_pid = os.getpid()

    def setup(self, worker) -> None:
        _use_checkout()
        if os.getpid() != self.client_pid:  # not the caller's own process (processes=False)
            limit_threads()
        if self.init is not None:
            pickle.loads(self.init)()


def _use_checkout() -> None:
    if has_checkout_studies():
        use_checkout_studies()


def run_pickled(execute: Callable[..., TaskRecord], payload: bytes) -> TaskRecord:
    """Run one task on a worker: ``execute(run_task, task, ctx)`` from the pickled
    ``(run_task, task, ctx)``. The study's objects (which live in ``studies``) travel as bytes,
    so that the scheduler, which unpickles the task graph, never imports them, and they are
    loaded here after the checkout's ``studies`` is first on ``sys.path``."""
    _use_checkout()
    run_task, task, ctx = pickle.loads(payload)
    return execute(run_task, task, ctx)


def connect(scheduler: Any) -> tuple[Client, bool, str]:
    """(client, whether it is ours to close, address for the manifest) for an address or a
    ``distributed.Client``; :class:`~workbench.study.scheduler.SchedulerError` when the address
    is malformed or no scheduler answers there within seconds."""
    if isinstance(scheduler, Client):
        address = getattr(scheduler.scheduler, "address", None) or repr(scheduler)
        return scheduler, False, address
    if not isinstance(scheduler, str):
        raise fail("scheduler", scheduler, "must be a Dask scheduler address (tcp://host:8786) "
                   "or a distributed.Client")
    address = check_scheduler(scheduler)
    # The client's own timeout does not cover the greeting it waits for after connecting: a
    # thread with a deadline does.
    result: list = []

    def make() -> None:
        try:
            result.append(Client(address, timeout=f"{CLIENT_TIMEOUT_S:g}s"))
        except Exception as exc:  # a refused or garbled answer (not a Dask scheduler)
            result.append(exc)

    maker = threading.Thread(target=make, daemon=True, name="scheduler-connect")
    maker.start()
    maker.join(CLIENT_TIMEOUT_S + 2.0)
    if result and isinstance(result[0], Client):
        return result[0], True, address
    exc = result[0] if result else None
    reason = f"{type(exc).__name__}: {exc}" if exc is not None else "no answer"
    reason = reason if len(reason) <= 200 else reason[:197] + "..."
    raise SchedulerError(f"scheduler = {scheduler!r}: no Dask scheduler answered within "
                         f"{CLIENT_TIMEOUT_S:g} s ({reason}); check the address and that a "
                         "Dask scheduler (not another service) listens there") from exc


def _timeout_record(item, timeout: float) -> TaskRecord:
    return TaskRecord(item[1].task_id, error=(
        f"TimeoutError: task timed out after {timeout:g} s (task_timeout_s = {timeout:g}, "
        "counted from when the cluster got it); it was cancelled on the cluster"))


def dask_records(study: Study, pending: list, client: Client, execute: Callable,
                 task_timeout_s: float | None = None
                 ) -> Generator[tuple[Any, TaskRecord], None, None]:
    """Submit the pending tasks to the cluster (all at once, or as many as it has threads when
    there is a time limit); yield records as they finish. Closing the iterator (e.g. on an
    interrupt) cancels what is left."""
    futures: dict = {}
    started: dict = {}
    queue = deque(pending)
    window = len(queue)
    if task_timeout_s is not None:
        window = max(1, sum(client.nthreads().values()))
    try:
        client.register_plugin(WorkerInit(study.worker_init), name=f"{study.name}-init")
        remaining: set = set()
        while queue or remaining:
            while queue and len(remaining) < window:
                item = queue.popleft()
                task, ctx = item
                fut = client.submit(run_pickled, execute,
                                    pickle.dumps((study.run_task, task, ctx)), pure=False)
                futures[fut], started[fut] = item, time.monotonic()
                remaining.add(fut)
            try:  # short waits, so that an interrupt acts within a second
                finished, remaining = wait(remaining, timeout=0.5, return_when="FIRST_COMPLETED")
            except TimeoutError:
                finished = set()
            for fut in sorted(finished, key=lambda f: f.key):
                item = futures[fut]
                try:
                    rec = fut.result()
                except Exception:  # the worker died or the result could not be transferred
                    rec = TaskRecord(item[1].task_id, error=traceback.format_exc())
                yield item, rec
            if task_timeout_s is not None:
                now = time.monotonic()
                late = sorted((f for f in remaining if now - started[f] > task_timeout_s),
                              key=lambda f: f.key)
                if late:
                    client.cancel(late)
                    remaining -= set(late)
                    for fut in late:
                        yield futures[fut], _timeout_record(futures[fut], task_timeout_s)
    finally:
        if futures:
            client.cancel(list(futures))

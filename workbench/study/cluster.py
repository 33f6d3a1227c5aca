"""Dask ``distributed`` back end: the same task records, computed on a cluster's workers."""

from __future__ import annotations

import traceback
from collections.abc import Callable, Iterator
from typing import Any

from distributed import Client, wait
from distributed.diagnostics.plugin import WorkerPlugin

from workbench.study.store import TaskRecord
from workbench.study.tasks import Study


class WorkerInit(WorkerPlugin):
    """Runs the study's worker initialiser (and the one-thread environment) on each worker."""

    def __init__(self, init: Callable[[], None] | None):
        self.init = init

    def setup(self, worker) -> None:
        from workbench.study.execute import limit_threads

        limit_threads()
        if self.init is not None:
            self.init()


def dask_records(study: Study, pending: list, scheduler: Any,
                 execute: Callable) -> Iterator[tuple[Any, TaskRecord]]:
    """Submit every pending task to the scheduler (an address or a Client); yield records as
    they finish. Closing the iterator (e.g. on an interrupt) cancels what is left."""
    own = not isinstance(scheduler, Client)
    client = Client(scheduler, timeout=30) if own else scheduler
    futures: dict = {}
    try:
        client.register_plugin(WorkerInit(study.worker_init), name=f"{study.name}-init")
        for item in pending:
            task, ctx = item
            futures[client.submit(execute, study.run_task, task, ctx, pure=False)] = item
        remaining = set(futures)
        while remaining:  # short waits, so that an interrupt acts within a second
            try:
                finished, remaining = wait(remaining, timeout=0.5, return_when="FIRST_COMPLETED")
            except TimeoutError:
                continue
            for fut in sorted(finished, key=lambda f: f.key):
                item = futures[fut]
                try:
                    rec = fut.result()
                except Exception:  # the worker died or the result could not be transferred
                    rec = TaskRecord(item[1].task_id, error=traceback.format_exc())
                yield item, rec
    finally:
        if futures:
            client.cancel(list(futures))
        if own:
            client.close()

"""The one-thread environment of a study worker: local worker processes and Dask workers run
one task at a time on one core, so BLAS and OpenMP libraries are told to use one thread before
any of them loads."""

from __future__ import annotations

import os

THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def limit_threads() -> None:
    """Set the thread environment of a worker to one thread (before any OpenMP library loads)."""
    for name in THREAD_ENV:
        os.environ[name] = "1"

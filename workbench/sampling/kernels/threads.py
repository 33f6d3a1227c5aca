"""How many OpenMP threads a kernel call uses, so that a machine shared with other work never
makes a multi-threaded call much slower than a single-threaded one.

An OpenMP parallel loop ends when every thread of the team has finished its share. When the
other processes of the machine keep its cores busy, a team thread may wait milliseconds for a
core, and a 2-thread call of a sub-millisecond kernel then takes the scheduler's time slice
(measured on 2 busy cores: N = 256, T = 40 SAIS, 0.22 ms on 1 thread, 8 ms on 2). Two rules
prevent that:

* **Wait policy.** Idle team threads sleep instead of spinning (``OMP_WAIT_POLICY=passive``,
  set in the environment before the first kernel library loads the OpenMP runtime, unless the
  user set ``OMP_WAIT_POLICY`` or ``GOMP_SPINCOUNT``): a spinning thread burns the core the
  other thread needs, and the scheduler then deschedules it for a whole time slice.
* **Adaptive count** (the default; :func:`set_threads` ``adaptive=False`` turns it off). A call
  runs on the configured count n, except on 1 thread when

  - the batch is small: N T < :data:`SMALL_WORK` sample-steps (starting and joining the team
    costs more than the second thread saves), or
  - the other processes keep the cores busy: from the machine's CPU time (``/proc/stat``) minus
    this process's own, over the last :data:`WINDOW_S` seconds, the cores they leave free;
    the call uses min(n, max(1, floor(free + :data:`FREE_MARGIN`))) threads, so on 2 cores
    other processes using more than half a core give 1 thread.

  Kernel results never depend on the thread count (every sample's noise comes from the seed
  and its sample number), so the rule changes times only. Without ``/proc/stat`` (not Linux)
  only the small-batch rule applies.

Measured with two busy processes on a 2-core machine (``benchmarks/threads.py``), 2-thread
over 1-thread time: spinning threads, fixed count (before) 18x (SAIS N = 256, T = 40), 2.4x
(N = 1024, T = 100), 1.55x (SA-RMPPI step); both rules 1.0x, 1.0x, 1.0-1.1x. Sleeping threads
with a fixed count took 0.7-1.0x on the SA-RMPPI step, but up to 6x for small batches on a
more heavily loaded machine.
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import NotRequired, TypedDict

from workbench.validation import flag, integer

# sample-steps (N T) below which a call runs on 1 thread: about 0.25 ms of float64 work; at
# N = 256, T = 40 (10240) two sleeping-policy threads were already 1.2x faster on a quiet machine
SMALL_WORK = 8192
WINDOW_S = 0.25  # seconds of CPU accounting behind each load estimate
FREE_MARGIN = 0.5  # cores: use k threads when at least k - FREE_MARGIN cores are free
WAIT_ENV = {"OMP_WAIT_POLICY": "passive"}  # set before the OpenMP runtime loads, unless given


class _ThreadState(TypedDict):
    max: int | None  # the configured maximum (None until a library or set_threads sets it)
    adaptive: bool
    default: NotRequired[bool]  # True (or absent): max is OpenMP's default, not set_threads'


_STATE: _ThreadState = {"max": None, "adaptive": True}
_APPLIED: dict[int, int] = {}  # OS thread -> count last applied to its OpenMP setting
_SETTERS: list[Callable[[int], object]] = []  # wb_set_threads of every loaded library


def prepare_runtime() -> None:
    """Put the wait policy in the environment before the first kernel library (and with it
    the OpenMP runtime) is loaded; a user's ``OMP_WAIT_POLICY``/``GOMP_SPINCOUNT`` wins."""
    if "OMP_WAIT_POLICY" in os.environ or "GOMP_SPINCOUNT" in os.environ:
        return
    os.environ.update(WAIT_ENV)


def register(setter: Callable[[int], object], default: int) -> None:
    """A newly loaded library's thread setter; ``default`` its OpenMP default count (the
    configured maximum until :func:`set_threads` is called)."""
    _SETTERS.append(setter)
    n = _STATE["max"]
    if n is None:
        n = _STATE["max"] = max(1, int(default))
        _STATE["default"] = True
    setter(n)
    _APPLIED.pop(threading.get_ident(), None)


def set_threads(n: int | str, adaptive: bool = True) -> None:
    """At most ``n`` OpenMP threads per kernel call (``"auto"``: one per core), for every kernel
    library loaded so far and later. ``adaptive`` (default) lowers the count of a call to 1 for
    small batches or when other processes keep the cores busy (module docstring); False uses
    exactly n. OpenMP's setting is per calling thread; study workers run with 1."""
    if n == "auto":
        n = _cores()
    integer("threads", n, 1)
    flag("adaptive", adaptive)
    _STATE.update({"max": int(n), "adaptive": bool(adaptive), "default": False})
    _APPLIED.clear()
    for s in _SETTERS:
        s(int(n))


@contextmanager
def using(n: int | str, adaptive: bool = False) -> Iterator[None]:
    """:func:`set_threads` (``n``, ``adaptive``) inside the block, the previous setting after
    it (benchmarks: ``with using(1): ...`` times exactly one thread)."""
    saved = _STATE.copy()
    set_threads(n, adaptive)
    try:
        yield
    finally:
        _STATE.update(saved)
        if "default" not in saved:
            _STATE.pop("default", None)
        _APPLIED.clear()
        for s in _SETTERS:
            s(int(saved["max"] or 1))


def get_threads() -> int | None:
    """The count of the last :func:`set_threads` (None: never set; OpenMP's default)."""
    return None if _STATE.get("default", True) else _STATE["max"]


def is_adaptive() -> bool:
    return bool(_STATE["adaptive"])


def threads_for(work: int) -> int:
    """The thread count a kernel call of ``work`` sample-steps (N T) uses now."""
    n = _STATE["max"] or 1
    if n == 1 or not _STATE["adaptive"]:
        return n
    if work < SMALL_WORK:
        return 1
    free = _LOAD.free_cores()
    if free is None:
        return n
    return max(1, min(n, math.floor(free + FREE_MARGIN)))


def apply(setter: Callable[[int], object], work: int) -> int:
    """Set the calling thread's OpenMP count for a call of ``work`` sample-steps (only when it
    changes); returns the count."""
    k = threads_for(work)
    tid = threading.get_ident()
    if _APPLIED.get(tid) != k:
        setter(k)
        _APPLIED[tid] = k
    return k


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


class _LoadProbe:
    """Cores left free by other processes, from /proc/stat (all CPUs' busy time) minus this
    process's CPU time, over windows of at least WINDOW_S seconds."""

    def __init__(self) -> None:
        self._hz = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
        self._last: tuple[float, float, float] | None = None
        self._free: float | None = None
        self._ok = os.path.exists("/proc/stat")
        self._lock = threading.Lock()

    def _read(self) -> tuple[float, float, int, int] | None:
        """(busy CPU seconds of the machine, this process's CPU seconds, CPUs, running)."""
        try:
            with open("/proc/stat", "rb") as fh:
                text = fh.read().decode()
        except OSError:
            return None
        lines = text.splitlines()
        f = [int(v) for v in lines[0].split()[1:]]
        # user nice system idle iowait irq softirq steal ...
        busy = (f[0] + f[1] + f[2] + f[5] + f[6] + (f[7] if len(f) > 7 else 0)) / self._hz
        ncpu = sum(1 for ln in lines[1:] if ln.startswith("cpu"))
        running = next((int(ln.split()[1]) for ln in lines if ln.startswith("procs_running")),
                       1)
        return busy, time.process_time(), max(1, ncpu), running

    def free_cores(self) -> float | None:
        if not self._ok:
            return None
        now = time.monotonic()
        with self._lock:
            if self._last is not None and now - self._last[0] < WINDOW_S:
                return self._free
            r = self._read()
            if r is None:
                self._ok = False
                return None
            busy, own, ncpu, running = r
            cores = min(ncpu, _cores())
            if self._last is None:  # first call: the processes running right now, but us
                self._free = cores - max(0, running - 1)
            else:
                t0, busy0, own0 = self._last
                others = max(0.0, (busy - busy0) - (own - own0)) / (now - t0)
                self._free = cores - others
            self._last = (now, busy, own)
            return self._free


_LOAD = _LoadProbe()


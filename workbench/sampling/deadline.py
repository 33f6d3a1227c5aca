"""A step that returns within a stated time (``MPPIConfig.deadline_s``).

With a deadline, a step draws its samples in ``MPPIConfig.deadline_chunks`` chunks (each from
its own seed) while they fit. Before each chunk it estimates what the rest of the step costs
from the controller's recent steps (:class:`DeadlineHistory`), modelling a chunk's time as its
samples times a rate plus a stall (the process waiting for a core: on a loaded machine whole
scheduler slices of several milliseconds, whatever the chunk's size): the rate is the recent
chunks' time over their samples (stalls included on average), the stall kept free is the
largest excess of a recent chunk (or tail) over what was expected of it. The tail (joining the
chunks, weighting the samples and finishing the step, after the last chunk) grows with the
samples: each sample is charged the recent steps' median tail per sample (the controller's
first step, with its first calls, only until a later step has one: a step's tail is not free
before any was measured), and a guard of :data:`GUARD` of the deadline is kept free. The chunks
are joined into buffers the controller keeps (:class:`JoinBuffers`). Each chunk is sized so
that it ends in time even at 1 / :data:`SLOWDOWN` of the recent speed: a chunk that fits so
is drawn whole, else in parts, each of what fits then, until not even the least chunk
(:func:`least_chunk`) fits; a further MPPI iteration starts only when its least chunk fits.
The first chunk of a step always runs, shrunk to what fits (at least the least chunk), so a
step still returns a plan when the deadline is too short. The work before the samples (for
the robust controllers: the selection and the feedback gains) is never cut.

A step can therefore exceed its deadline only when the work before the samples plus the least
chunk does not fit, or when the machine stalls the process for longer than its recent steps
saw; :attr:`DeadlineReport.missed` counts it, and ``make bench`` measures the overshoot under a
load of 2 against :data:`STATED_MARGIN` (see the README).

During a step with a deadline (:func:`deadline_step`) numpy's BLAS runs on one thread and
Python's cyclic garbage collector is paused, both for the whole process and both restored when
the step returns: under a load of 2 BLAS's worker threads competed with the kernels and the
load for the cores (the controllers drew 1.3-1.5x fewer samples and missed the margin more
often), and a full collection, which costs 50-55 ms of CPU in a process that has run a few
thousand steps, fell inside a step about once in 4000-8000 steps. Paused, a collection runs
at the caller's first allocation after the step, between steps.

Truncation follows the wall clock: results with a deadline depend on timing and are not
reproducible bit for bit. Without a deadline (the default) nothing changes: one batch per
iteration, exactly as before.
"""

from __future__ import annotations

import functools
import gc
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np

from workbench.sampling.kernels.threads import threads_for

B = TypeVar("B")


@dataclass(frozen=True)
class DeadlineReport:
    """What the deadline did in one step: ``samples`` drawn of ``planned`` (per iteration
    planned: n_samples), ``iterations`` run, ``truncated`` (work was cut), ``elapsed_s`` of the
    controller's own clock at its return, ``missed`` (elapsed over the deadline); ``chunks``:
    each chunk's (samples, wall seconds, process CPU seconds, threads), and ``tail_s`` from
    the last chunk to the return (where an overrun's time went)."""

    deadline_s: float
    samples: int
    planned: int
    iterations: int
    truncated: bool
    elapsed_s: float
    chunks: tuple[tuple[int, float, float, int], ...] = ()
    tail_s: float = 0.0

    @property
    def missed(self) -> bool:
        return self.elapsed_s > self.deadline_s


GUARD = 0.1  # share of the deadline kept free for the jitter of a loaded machine
# a chunk is sized to end in time even when it runs this many times slower than the recent
# chunks did (on a loaded 2-core VM, the CPU time per sample doubled from one step to the next
# when the other core's process competed for the same physical core)
SLOWDOWN = 2.0
WINDOW = 50  # recent chunks the short rate, and recent steps the tail, look back over
# recent chunks the stall and the long rate look back over: long stalls are rare (on a 2-core
# VM under a load of 2, waits of 8-12 ms came once in about 5000 slices), and a quiet spell of
# a few steps must not make the rate forget the load that comes back
STALL_WINDOW = 400
# what ``make bench`` checks the largest overshoot against over 1000 steps under a load of 2:
# this share of the deadline (BaS-MPPI and SA-RMPPI at 20 and 50 Hz, navigation map)
STATED_MARGIN = 0.25


class _Window:
    """The last ``n`` chunks (samples, seconds) of one thread count with their running totals,
    so that a rate costs no pass over the chunks (it is read several times per chunk)."""

    def __init__(self, n: int) -> None:
        self.items: deque[tuple[int, float]] = deque()
        self.n, self.size, self.sec = n, 0, 0.0

    def push(self, size: int, sec: float) -> None:
        self.items.append((size, sec))
        self.size, self.sec = self.size + size, self.sec + sec
        if len(self.items) > self.n:
            old_size, old_sec = self.items.popleft()
            self.size, self.sec = self.size - old_size, self.sec - old_sec

    def rate(self) -> float:
        return self.sec / self.size


class DeadlineHistory:
    """A controller's recent chunks (samples and seconds, the last :data:`STALL_WINDOW` per
    thread count), their excess over the rate then expected (the last :data:`STALL_WINDOW`)
    and its step tails (seconds per sample from the last chunk to the step's return, the last
    :data:`WINDOW` steps after the first)."""

    def __init__(self) -> None:
        # per thread count: (the last WINDOW chunks, the last STALL_WINDOW chunks)
        self.chunks: dict[int, tuple[_Window, _Window]] = {}
        self.excess: deque[float] = deque(maxlen=STALL_WINDOW)
        self.tail: deque[float] = deque(maxlen=WINDOW)  # seconds per sample of each tail
        self.first_tail = 0.0  # the first step's tail per sample: charged until another
        self.steps = 0

    def rate(self, threads: int = 1) -> float:
        """Seconds per sample of a chunk on ``threads`` threads: the chunks' time over their
        samples on that count, the slower of the last :data:`WINDOW` and the last
        :data:`STALL_WINDOW`, and never faster than on fewer threads (under load more threads
        can be slower, and a chunk's count is chosen by the kernels as it starts); with none
        on that count, also a full loss from the counts above it (0 before any chunk)."""
        of = {q: max(short.rate(), long.rate()) for q, (short, long) in self.chunks.items()}
        fewer = [r for q, r in of.items() if q < threads]
        if threads in of:
            return max([of[threads], *fewer])
        return max(fewer + [r * q / threads for q, r in of.items() if q > threads],
                   default=0.0)

    def tail_rate(self) -> float:
        """The median of the recent steps' tail per sample; before the second step's, the
        first step's (0 before any step)."""
        return float(np.median(self.tail)) if self.tail else self.first_tail

    def end_step(self, samples: int, tail_s: float) -> None:
        """Record a step's tail. The first step's (first calls) is only kept as the tail
        charged until a later step's is known: it never enters the median or the stall."""
        self.steps += 1
        if samples < 1:
            return
        if self.steps == 1:
            self.first_tail = tail_s / samples
            return
        if self.tail:
            self.excess.append(max(0.0, tail_s - samples * self.tail_rate()))
        self.tail.append(tail_s / samples)

    def stall(self) -> float:
        """The largest recent excess of a chunk over the rate expected before it (0 before
        any)."""
        return max(self.excess, default=0.0)

    def add(self, size: int, seconds: float, threads: int = 1) -> None:
        if self.chunks:
            self.excess.append(max(0.0, seconds - size * self.rate(threads)))
        windows = self.chunks.setdefault(threads, (_Window(WINDOW), _Window(STALL_WINDOW)))
        for w in windows:
            w.push(max(size, 1), seconds)


class JoinBuffers:
    """Where a controller joins a step's chunks: one flat array per field, room for
    ``capacity`` samples (more if a join needs it), allocated with every page written at its
    first join and reused by the later ones. A joined array is a contiguous view of it, valid
    until the controller's next join of that field. (A fresh array per step page-faulted tens
    of MB in a controller's first steps: a join of 8192 samples took 13-78 ms under a load of
    2, against 0.1-1 ms once the memory was mapped.)"""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self.arrays: dict[str, np.ndarray] = {}

    def cat(self, name: str, parts: list[np.ndarray], axis: int = 0) -> np.ndarray:
        """``np.concatenate(parts, axis)``, written into the buffer ``name``."""
        first = parts[0]
        ax = axis % first.ndim
        n = sum(p.shape[ax] for p in parts)
        per_sample = math.prod(first.shape[:ax] + first.shape[ax + 1:])
        buf = self.arrays.get(name)
        if buf is None or buf.dtype != first.dtype or buf.size < per_sample * n:
            buf = self.arrays[name] = np.ones(per_sample * max(n, self.capacity), first.dtype)
        shape = (*first.shape[:ax], n, *first.shape[ax + 1:])
        return np.concatenate(parts, axis=ax, out=buf[:per_sample * n].reshape(shape))


def new_arrays(name: str, parts: list[np.ndarray], axis: int = 0) -> np.ndarray:
    """``np.concatenate(parts, axis)`` into a new array: :meth:`JoinBuffers.cat` without
    buffers (``name`` is not used)."""
    return np.concatenate(parts, axis=axis)


def least_chunk(chunk: int) -> int:
    """The fewest samples a shortened chunk draws: an eighth of a chunk (at least 1)."""
    return max(1, math.ceil(chunk / 8))


class StepClock:
    """The deadline of one step, started at the step's first line, with the controller's
    history of recent steps (a new one for a controller's first step). ``threads_of(n)``: the
    thread count a chunk of ``n`` samples runs on (the kernels choose it per call, from the
    batch's size and the load: :func:`kernel_threads` gives it for a horizon)."""

    def __init__(self, deadline_s: float, t0: float, history: DeadlineHistory | None = None,
                 threads_of: Callable[[int], int] = lambda n: 1):
        self.deadline_s, self.t0 = deadline_s, t0
        self.threads_of = threads_of
        self.history = history if history is not None else DeadlineHistory()
        self.samples = 0
        self.iterations = 0
        self.truncated = False
        self.sampled_at: float | None = None
        self.chunks: list[tuple[int, float, float, int]] = []

    def room(self, threads: int = 1) -> float:
        """How many samples fit now on ``threads`` threads (may be < 0): the time left after
        the guard, the largest recent stall and the tail of the samples drawn so far, over the
        recent rate on that count plus the tail per sample (inf before any chunk)."""
        h = self.history
        tail = h.tail_rate()
        left = (self.deadline_s * (1.0 - GUARD) - (time.perf_counter() - self.t0)
                - h.stall() - tail * self.samples)
        per = h.rate(threads) + tail
        return left / per if per > 0 else (math.inf if left > 0 else -math.inf)

    def fits(self, size: int) -> float:
        """:meth:`room` for a chunk of ``size`` samples on the count it would run on; when
        only part of it fits and that part would run on another count, the room on that
        count (the smaller of the two)."""
        k = self.threads_of(size)
        room = self.room(k)
        if room < size * SLOWDOWN and room >= SLOWDOWN:
            k2 = self.threads_of(int(room / SLOWDOWN))
            if k2 != k:
                room = min(room, self.room(k2))
        return room

    def drew(self, size: int, seconds: float, threads: int = 1, cpu_s: float = 0.0) -> None:
        self.history.add(size, seconds, threads)
        self.chunks.append((size, seconds, cpu_s, threads))
        self.samples += size
        self.sampled_at = time.perf_counter()

    def report(self, planned: int) -> DeadlineReport:
        now = time.perf_counter()
        tail = 0.0
        if self.sampled_at is not None:
            tail = now - self.sampled_at
            self.history.end_step(self.samples, tail)
        return DeadlineReport(self.deadline_s, self.samples, planned, self.iterations,
                              self.truncated, now - self.t0, tuple(self.chunks), tail)


def kernel_threads(horizon: int) -> Callable[[int], int]:
    """``threads_of`` for a sampler of ``horizon`` steps: the count its kernels choose for
    ``n`` samples now (:func:`workbench.sampling.kernels.threads.threads_for`)."""
    return lambda n: threads_for(n * horizon)


def chunk_sizes(n: int, chunks: int) -> list[int]:
    """``n`` samples in at most ``chunks`` near-equal chunks, larger ones first."""
    k = min(n, chunks)
    return [n // k + (1 if i < n % k else 0) for i in range(k)]


def sample_within(clock: StepClock, n: int, chunks: int, draw: Callable[[int, int], B],
                  rng: np.random.Generator, join: Callable[[list[B]], B]) -> B | None:
    """Draw ``n`` samples in chunks (``draw(size, seed)``, seeds from ``rng``) while they
    fit, each sized to need at most 1 / :data:`SLOWDOWN` of the time left at the recent rate
    (a chunk that runs that much slower than the recent ones still ends in time): a chunk
    that does not fit whole is drawn in parts, each of what fits then, until not even the
    least chunk fits. None when nothing of a later iteration fits. The first chunk of the
    step's first iteration always runs."""
    parts: list[B] = []
    for size in chunk_sizes(n, chunks):
        least = least_chunk(size)
        while size > 0:
            room = clock.fits(size) / SLOWDOWN + 1e-6  # a sample lost to rounding still fits
            take = size if room >= size else (int(room) if room >= least else 0)
            if take < size:
                clock.truncated = True
                if take == 0 and not parts and not clock.iterations:
                    take = least  # the step's first chunk always runs
            if take == 0:
                break
            k = clock.threads_of(take)
            t, c = time.perf_counter(), time.process_time()
            parts.append(draw(take, int(rng.integers(0, 2**63))))
            clock.drew(take, time.perf_counter() - t, k, time.process_time() - c)
            size -= take
        if size > 0:
            break
    if not parts:
        return None
    clock.iterations += 1
    return parts[0] if len(parts) == 1 else join(parts)


@functools.cache
def _blas():  # the BLAS libraries loaded when a deadline step first runs (numpy's among them)
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController().select(user_api="blas")


S = TypeVar("S")


def deadline_step(step: Callable[..., S]) -> Callable[..., S]:
    """A controller's ``step`` that, when its config has a deadline (``self.cfg.deadline_s``),
    runs with BLAS on one thread and Python's cyclic garbage collector paused; both are
    restored when it returns (the collector stays off if it was off). Both are process-wide
    while the step runs (about 10 us to set and restore)."""

    @functools.wraps(step)
    def limited(self: Any, *args: Any, **kwargs: Any) -> S:
        if self.cfg.deadline_s is None:
            return step(self, *args, **kwargs)
        collecting = gc.isenabled()
        gc.disable()
        try:
            with _blas().limit(limits=1):
                return step(self, *args, **kwargs)
        finally:
            if collecting:
                gc.enable()

    return limited

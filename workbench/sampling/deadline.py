"""A step that returns within a stated time (``MPPIConfig.deadline_s``).

With a deadline, a step draws its samples in ``MPPIConfig.deadline_chunks`` chunks (each from
its own seed) while they fit. Before each chunk it estimates what the rest of the step costs
from the controller's recent steps (:class:`DeadlineHistory`): the 90th percentile of the
recent chunks' time per sample, the longest recent tail (weighting the samples and finishing
the step, after the last chunk) and a guard of :data:`GUARD` of the deadline for the jitter of
a loaded machine. A chunk that fits is drawn whole; when only part of one fits, that part is
drawn (at least :func:`least_chunk` samples) and sampling stops; a further MPPI iteration starts
only when its least chunk fits. The first chunk of a step always runs, shrunk to what fits (at
least the least chunk), so a step still returns a plan when the deadline is too short. The work
before the samples (for the robust controllers: the selection and the feedback gains) is never
cut.

A step can therefore exceed its deadline only when the work before the samples plus the least
chunk does not fit, or when the machine stalls the process for longer than its recent steps
saw; :attr:`DeadlineReport.missed` counts it, and ``make bench`` measures the overshoot under a
load of 2 against :data:`STATED_MARGIN` (see the README).

Truncation follows the wall clock: results with a deadline depend on timing and are not
reproducible bit for bit. Without a deadline (the default) nothing changes: one batch per
iteration, exactly as before.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

import numpy as np

B = TypeVar("B")


@dataclass(frozen=True)
class DeadlineReport:
    """What the deadline did in one step: ``samples`` drawn of ``planned`` (per iteration
    planned: n_samples), ``iterations`` run, ``truncated`` (work was cut), ``elapsed_s`` of the
    controller's own clock at its return, ``missed`` (elapsed over the deadline)."""

    deadline_s: float
    samples: int
    planned: int
    iterations: int
    truncated: bool
    elapsed_s: float

    @property
    def missed(self) -> bool:
        return self.elapsed_s > self.deadline_s


GUARD = 0.1  # share of the deadline kept free for the jitter of a loaded machine
# the recent chunks' time per sample the next chunk is judged by: a high quantile, as a loaded
# machine runs some chunks at half speed (the median let steps overrun by a chunk's worth; the
# slowest chunk made one preempted small chunk set the pace for WINDOW steps)
PER_SAMPLE_QUANTILE = 0.9
WINDOW = 50  # recent steps (and chunks) the estimates look back over
# what ``make bench`` checks the largest overshoot against over 1000 steps under a load of 2:
# this share of the deadline (BaS-MPPI and SA-RMPPI at 20 and 50 Hz, navigation map)
STATED_MARGIN = 0.25


class DeadlineHistory:
    """A controller's recent chunk costs (seconds per sample) and step tails (seconds from the
    last chunk to the step's return), over the last :data:`WINDOW` of each."""

    def __init__(self) -> None:
        self.per_sample: deque[float] = deque(maxlen=WINDOW)
        self.tail: deque[float] = deque(maxlen=WINDOW)


def least_chunk(chunk: int) -> int:
    """The fewest samples a shortened chunk draws: an eighth of a chunk (at least 1)."""
    return max(1, math.ceil(chunk / 8))


class StepClock:
    """The deadline of one step, started at the step's first line, with the controller's
    history of recent steps (a new one for a controller's first step)."""

    def __init__(self, deadline_s: float, t0: float, history: DeadlineHistory | None = None):
        self.deadline_s, self.t0 = deadline_s, t0
        self.history = history if history is not None else DeadlineHistory()
        self.samples = 0
        self.iterations = 0
        self.truncated = False
        self.sampled_at: float | None = None

    def room(self) -> float:
        """How many samples fit now (may be < 0): the time left after the expected tail and
        the guard, over the slowest recent time per sample (inf before any chunk)."""
        h = self.history
        left = (self.deadline_s * (1.0 - GUARD) - (time.perf_counter() - self.t0)
                - (max(h.tail) if h.tail else 0.0))
        per = float(np.quantile(h.per_sample, PER_SAMPLE_QUANTILE)) if h.per_sample else 0.0
        return left / per if per > 0 else (math.inf if left > 0 else -math.inf)

    def drew(self, size: int, seconds: float) -> None:
        self.history.per_sample.append(seconds / max(size, 1))
        self.samples += size
        self.sampled_at = time.perf_counter()

    def report(self, planned: int) -> DeadlineReport:
        now = time.perf_counter()
        if self.sampled_at is not None:
            self.history.tail.append(now - self.sampled_at)
        return DeadlineReport(self.deadline_s, self.samples, planned, self.iterations,
                              self.truncated, now - self.t0)


def chunk_sizes(n: int, chunks: int) -> list[int]:
    """``n`` samples in at most ``chunks`` near-equal chunks, larger ones first."""
    k = min(n, chunks)
    return [n // k + (1 if i < n % k else 0) for i in range(k)]


def sample_within(clock: StepClock, n: int, chunks: int, draw: Callable[[int, int], B],
                  rng: np.random.Generator, join: Callable[[list[B]], B]) -> B | None:
    """Draw ``n`` samples in chunks (``draw(size, seed)``, seeds from ``rng``) while they
    fit, the last one shortened to what fits; None when not even the least chunk of a later
    iteration fits. The first chunk of the step's first iteration always runs."""
    parts: list[B] = []
    for size in chunk_sizes(n, chunks):
        least = least_chunk(size)
        room = clock.room()
        room = room + 1e-6  # a whole sample lost to rounding is not a sample that does not fit
        take = size if room >= size else (int(room) if room >= least else 0)
        if take < size:
            clock.truncated = True
            if take == 0 and not parts and not clock.iterations:
                take = least  # the step's first chunk always runs
        if take == 0:
            break
        t = time.perf_counter()
        parts.append(draw(take, int(rng.integers(0, 2**63))))
        clock.drew(take, time.perf_counter() - t)
        if take < size:
            break
    if not parts:
        return None
    clock.iterations += 1
    return parts[0] if len(parts) == 1 else join(parts)

"""A step that returns within a stated time (``MPPIConfig.deadline_s``).

With a deadline, a step draws its samples in ``MPPIConfig.deadline_chunks`` chunks (each from
its own seed) and, before each chunk after the first, checks that the time already spent plus
twice the longest chunk of this step still fits (the next chunk, and as much again in reserve
for weighting the samples and for the jitter of a loaded machine): when it does not, the step
stops sampling and weights the samples drawn so far; a further MPPI iteration starts only
when one chunk of it fits. The first chunk always runs, so a step still returns a plan when
the deadline is too short: the work before the samples (for the robust controllers: the
selection and the feedback gains, never cut) plus one chunk is the least a step costs, and a
step can exceed its deadline by about the time of a chunk, more when the process is preempted
(:attr:`DeadlineReport.missed` counts it).

Truncation follows the wall clock: results with a deadline depend on timing and are not
reproducible bit for bit. Without a deadline (the default) nothing changes: one batch per
iteration, exactly as before.
"""

from __future__ import annotations

import time
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


class StepClock:
    """The deadline of one step, started at the step's first line."""

    def __init__(self, deadline_s: float, t0: float):
        self.deadline_s, self.t0 = deadline_s, t0
        self.chunk_s = 0.0  # the longest chunk of this step so far
        self.samples = 0
        self.iterations = 0
        self.truncated = False

    def fits(self) -> bool:
        """Whether one more chunk, with as much again in reserve, fits before the deadline
        (records a cut when it does not)."""
        ok = time.perf_counter() - self.t0 + 2.0 * self.chunk_s <= self.deadline_s
        self.truncated = self.truncated or not ok
        return ok

    def report(self, planned: int) -> DeadlineReport:
        return DeadlineReport(self.deadline_s, self.samples, planned, self.iterations,
                              self.truncated, time.perf_counter() - self.t0)


def chunk_sizes(n: int, chunks: int) -> list[int]:
    """``n`` samples in at most ``chunks`` near-equal chunks, larger ones first."""
    k = min(n, chunks)
    return [n // k + (1 if i < n % k else 0) for i in range(k)]


def sample_within(clock: StepClock, n: int, chunks: int, draw: Callable[[int, int], B],
                  rng: np.random.Generator, join: Callable[[list[B]], B]) -> B | None:
    """Draw ``n`` samples in chunks (``draw(size, seed)``, seeds from ``rng``) while the next
    chunk fits; None when not even the first chunk of a later iteration fits. The first chunk of
    the step's first iteration always runs."""
    parts: list[B] = []
    for size in chunk_sizes(n, chunks):
        if (parts or clock.iterations) and not clock.fits():
            break
        t = time.perf_counter()
        parts.append(draw(size, int(rng.integers(0, 2**63))))
        clock.chunk_s = max(clock.chunk_s, time.perf_counter() - t)
        clock.samples += size
    if not parts:
        return None
    clock.iterations += 1
    return parts[0] if len(parts) == 1 else join(parts)

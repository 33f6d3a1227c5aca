"""Equal-budget automatic tuning with optuna: every candidate gets the same number of trials,
each trial the same number of episodes, and the same declared objective.

The tuner is generic: a search space of named real parameters (log or linear scale, integer or
not), a starting point (the hand-tuned values, always evaluated first so a tuned result is never
worse on the training episodes than the hand-tuned one), and an objective ``params -> score``
to maximise. The sampler is optuna's TPE seeded from the budget's seed, so a tuning run is
reproducible.

The best training score overstates how good a point is: it is the maximum of many noisy
estimates. :func:`select` therefore scores the hand-tuned start and the best few training trials
once more on held-out validation episodes (the same episodes for every candidate) and keeps the
tuned point only when it beats the start there.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

from workbench.validation import MAX_TASKS, at_most, fail, flag, integer, real

MAX_TRIALS = 10**5  # objective evaluations of one tuning run
MAX_EPISODES = 10**5  # training episodes of one trial
MAX_SEED = 2**32 - 1  # optuna's TPE sampler seeds a NumPy RandomState: [0, 2^32 - 1]


@dataclass(frozen=True)
class Param:
    """One tuned parameter: ``name`` in [``low``, ``high``], sampled on a log scale by
    default, as an integer when ``integer``."""

    name: str
    low: float
    high: float
    log: bool = True
    integer: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise fail("Param.name", self.name, "must be a non-empty string")
        lo = real(f"Param({self.name}).low", self.low)
        hi = real(f"Param({self.name}).high", self.high)
        if not lo < hi:
            raise fail(f"Param({self.name}).high", self.high, f"must exceed low = {lo:g}")
        flag(f"Param({self.name}).log", self.log)
        flag(f"Param({self.name}).integer", self.integer)
        if self.log and lo <= 0:
            raise fail(f"Param({self.name}).low", self.low, "must be > 0 on a log scale")

    def contains(self, value: float) -> bool:
        return self.low <= value <= self.high


@dataclass(frozen=True)
class TuningBudget:
    """The budget every tuned controller gets: ``trials`` objective evaluations (the first is
    the hand-tuned starting point), each over ``episodes`` training episodes; ``seed`` seeds the
    search. Then the start and the best ``finalists`` trials are each scored on ``validation``
    held-out episodes (:func:`select`; 0 and 0: no validation). Limits: trials <=
    :data:`MAX_TRIALS`, episodes and validation <= :data:`MAX_EPISODES`, trials x episodes and
    (finalists + 1) x validation <= :data:`~workbench.validation.MAX_TASKS`, seed in
    [0, 2^32 - 1]."""

    trials: int = 8
    episodes: int = 8
    seed: int = 0
    validation: int = 8
    finalists: int = 2

    def __post_init__(self) -> None:
        integer("tuning.trials", self.trials, 1, MAX_TRIALS)
        integer("tuning.episodes", self.episodes, 1, MAX_EPISODES)
        at_most("tuning.episodes", self.episodes, int(self.trials) * int(self.episodes),
                MAX_TASKS, "trials x episodes (training episodes of one tuned controller)")
        integer("tuning.seed", self.seed, 0, MAX_SEED)
        integer("tuning.validation", self.validation, 0, MAX_EPISODES)
        integer("tuning.finalists", self.finalists, 0, MAX_TRIALS)
        if (self.validation == 0) != (self.finalists == 0):
            raise fail("tuning.finalists", self.finalists,
                       f"must be 0 exactly when validation is 0 (validation = "
                       f"{self.validation}): a validation step scores at least one finalist")
        at_most("tuning.validation", self.validation,
                (int(self.finalists) + 1) * int(self.validation), MAX_TASKS,
                "(finalists + 1) x validation (validation episodes of one tuned controller)")

    @property
    def total_episodes(self) -> int:
        """Training episodes of one tuned controller (validation episodes not counted)."""
        return self.trials * self.episodes


@dataclass(frozen=True)
class Trial:
    number: int
    params: dict[str, float]
    score: float


@dataclass(frozen=True)
class TuningResult:
    """The best parameters, their score, every trial in order, the budget and the objective's
    description."""

    best: dict[str, float]
    score: float
    start_score: float
    trials: tuple[Trial, ...]
    budget: TuningBudget
    objective: str


def tune(space: Sequence[Param], objective: Callable[[dict[str, float], int], float],
         budget: TuningBudget, start: Mapping[str, float], *, description: str = "",
         ) -> TuningResult:
    """Maximise ``objective(params, trial_number)`` over ``space`` with ``budget.trials``
    evaluations; trial 0 evaluates ``start`` (clipped to nothing: it must lie in the space).
    A non-finite score counts as the worst possible. Returns the best trial (the earliest on
    ties, so the hand-tuned start wins a tie)."""
    import optuna

    names = [p.name for p in space]
    if len(set(names)) != len(names):
        raise fail("space", names, "parameter names must be distinct")
    missing = [n for n in names if n not in start]
    if missing:
        raise fail("start", dict(start), f"needs a value for every parameter; missing {missing}")
    for p in space:
        if not p.contains(float(start[p.name])):
            raise fail(f"start.{p.name}", start[p.name],
                       f"must lie in the search range [{p.low:g}, {p.high:g}]")
    optuna.logging.set_verbosity(logging.WARNING)
    study = optuna.create_study(direction="maximize",
                                sampler=optuna.samplers.TPESampler(seed=budget.seed))
    study.enqueue_trial({p.name: (int(start[p.name]) if p.integer else float(start[p.name]))
                         for p in space})
    trials: list[Trial] = []

    def run(trial) -> float:
        params = {}
        for p in space:
            if p.integer:
                params[p.name] = float(trial.suggest_int(p.name, int(p.low), int(p.high),
                                                         log=p.log))
            else:
                params[p.name] = trial.suggest_float(p.name, p.low, p.high, log=p.log)
        score = float(objective(params, trial.number))
        if not math.isfinite(score):
            score = -math.inf
        trials.append(Trial(trial.number, params, score))
        return score if math.isfinite(score) else -1e300

    study.optimize(run, n_trials=budget.trials)
    best = max(trials, key=lambda t: (t.score, -t.number))
    return TuningResult(best.params, best.score, trials[0].score, tuple(trials), budget,
                        description)


HAND, TUNED = "hand", "tuned"  # what a selection keeps


@dataclass(frozen=True)
class Selection:
    """What :func:`select` kept: ``kept`` is :data:`TUNED` (``params`` is ``candidate``'s) or
    :data:`HAND` (``params`` is the start's: no finalist beat it on validation).
    ``candidate`` is the search's best on validation (the start itself when no trial beat the
    start on training); ``scored`` every validated trial with its validation score, the start
    first."""

    kept: str
    params: dict[str, float]
    start: Trial
    candidate: Trial
    start_validation: float
    candidate_validation: float
    scored: tuple[tuple[Trial, float], ...]


def finalists(result: TuningResult, k: int) -> tuple[Trial, ...]:
    """The best ``k`` trials whose training score beats the start's (trial 0), best first
    (the earlier on ties)."""
    start = result.trials[0]
    better = [t for t in result.trials[1:] if t.score > start.score]
    return tuple(sorted(better, key=lambda t: (-t.score, t.number))[:k])


def select(result: TuningResult, validate: Callable[[dict[str, float]], float],
           k: int) -> Selection:
    """Score the start and :func:`finalists` (``k``) on ``validate`` (``params -> score``, to
    maximise; it must score every candidate on the same episodes) and keep the finalist with
    the best validation score if it beats the start's strictly, else the start. Ties between
    finalists go to the better training score; a non-finite validation score counts as the
    worst."""
    def score(params: dict[str, float]) -> float:
        v = float(validate(dict(params)))
        return v if math.isfinite(v) else -math.inf

    start = result.trials[0]
    scored = [(start, score(start.params))]
    scored += [(t, score(t.params)) for t in finalists(result, k)]
    hand = scored[0][1]
    best, best_score = max(scored[1:], key=lambda ts: ts[1], default=scored[0])
    kept = TUNED if best_score > hand else HAND
    return Selection(kept, dict(best.params if kept == TUNED else start.params), start, best,
                     hand, best_score, tuple(scored))

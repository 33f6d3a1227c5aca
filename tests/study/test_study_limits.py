"""Tuning budgets and the statistics helpers: counts are integers, never bools, within
documented limits; the message names the field, the value and the allowed range."""

from __future__ import annotations

import numpy as np
import pytest

from workbench.study.stats import (
    mcnemar_exact,
    paired_difference_interval,
    pooled_paired,
    wilson_interval,
)
from workbench.study.tuning import MAX_SEED, Param, TuningBudget, tune
from workbench.validation import MAX_TASKS


def test_a_budget_whose_total_episodes_exceed_the_task_limit_is_refused():
    """Before: trials = episodes = 10**5 (10**10 training episodes) was accepted."""
    with pytest.raises(ValueError, match=r"^tuning\.episodes = 100000 is invalid: gives trials x "
                       r"episodes \(training episodes of one tuned controller\) = 10000000000, "
                       rf"above the limit {MAX_TASKS}; lower it$"):
        TuningBudget(trials=10**5, episodes=10**5)
    assert TuningBudget(trials=100, episodes=10**5).total_episodes == MAX_TASKS


def test_a_budget_seed_outside_what_the_sampler_takes_is_refused_at_construction():
    """Before: seed 2**40 was accepted and tune() failed inside optuna / NumPy
    ("Seed must be between 0 and 2**32 - 1")."""
    with pytest.raises(ValueError, match=rf"^tuning\.seed = {2**40} is invalid: must be an "
                       rf"integer in \[0, {MAX_SEED}\]$"):
        TuningBudget(seed=2**40)
    res = tune([Param("a", 0.1, 1.0)], lambda p, t: -p["a"], TuningBudget(trials=2, seed=MAX_SEED),
               {"a": 0.5})
    assert len(res.trials) == 2


@pytest.mark.parametrize(("kw", "message"), [
    (dict(trials=True), r"^tuning\.trials = True is invalid: must be an integer in \[1, 100000\]"),
    (dict(episodes=np.True_), r"^tuning\.episodes = True is invalid: must be an integer in "
     r"\[1, 100000\]"),
    (dict(trials=10**6), r"^tuning\.trials = 1000000 is invalid: must be an integer in "
     r"\[1, 100000\]"),
])
def test_budget_counts_refuse_bools_and_huge_values(kw, message):
    """Guard (refused before as well): bools and the per-field limits."""
    with pytest.raises(ValueError, match=message):
        TuningBudget(**kw)


@pytest.mark.parametrize(("call", "message"), [
    (lambda: wilson_interval(True, 3), r"^successes = True is invalid: must be an integer in "
     r"\[0, 3\]$"),
    (lambda: wilson_interval(0, True), r"^n = True is invalid: must be an integer >= 1$"),
    (lambda: wilson_interval(np.True_, 3), r"^successes = True is invalid"),
    (lambda: wilson_interval(1, 3, z=float("nan")), r"^z = nan is invalid: must be a finite "
     "number > 0$"),
    (lambda: mcnemar_exact(True, 2), r"^b = True is invalid: must be an integer >= 0$"),
    (lambda: mcnemar_exact(2, np.False_), r"^c = False is invalid: must be an integer >= 0$"),
    (lambda: paired_difference_interval(3, True, 2, 1), r"^b = True is invalid"),
    (lambda: paired_difference_interval(3, 1, 2, 1, z=-1.0), r"^z = -1\. is invalid"),
])
def test_stats_counts_are_integers_not_bools(call, message):
    """Before: True counted as 1 (wilson_interval(True, 3) gave an interval, mcnemar_exact
    (True, 2) a p-value) and z = nan gave the interval [0, 1]."""
    with pytest.raises(ValueError, match=message):
        call()


def test_stats_still_take_numpy_integers():
    assert wilson_interval(np.int64(3), np.int64(3))[1] == 1.0
    assert mcnemar_exact(np.int32(0), 0) == 1.0
    with pytest.raises(ValueError, match=r"^strata\[0\]\.a = True is invalid"):
        pooled_paired([(True, 2, 3, 4)])
    assert pooled_paired([(np.int64(1), 2, 3, 4)]).n == 10

"""Equal-budget tuning: the budget is spent exactly, the hand-tuned start is trial 0, the search
is reproducible in its seed and improves on a known objective; the validation step ships the
tuned point only when it beats the start on held-out episodes; tuned values enter a
controller's settings where they should; bad budgets and values name the field."""

from __future__ import annotations

import math

import pytest

from workbench.sampling.mppi import MPPIConfig
from workbench.sampling.threshold import AlphaRule
from workbench.scenarios.methods import MethodSettings, names
from workbench.scenarios.tuned import ControllerSettings, shipped, space
from workbench.study.tuning import Param, TuningBudget, finalists, select, tune

SPACE = (Param("a", 0.01, 100.0), Param("b", -5.0, 5.0, log=False),
         Param("n", 1, 50, log=False, integer=True))


def objective(p, trial):
    # maximum at a = 1, b = 2, n = 20
    return -(math.log10(p["a"]) ** 2) - (p["b"] - 2.0) ** 2 - ((p["n"] - 20) / 10) ** 2


def test_budget_start_and_improvement():
    start = {"a": 50.0, "b": -4.0, "n": 3}
    calls = []

    def counted(p, t):
        calls.append((t, dict(p)))
        return objective(p, t)

    res = tune(SPACE, counted, TuningBudget(trials=40, episodes=1, seed=3), start)
    assert len(calls) == len(res.trials) == 40
    assert calls[0] == (0, {"a": 50.0, "b": -4.0, "n": 3.0})
    assert res.start_score == pytest.approx(objective(start, 0))
    assert res.score == max(t.score for t in res.trials)
    assert res.score > res.start_score + 30  # far better than the poor start
    assert all(float(t.params["n"]).is_integer() for t in res.trials)
    assert all(p.contains(t.params[p.name]) for t in res.trials for p in SPACE)
    again = tune(SPACE, objective, TuningBudget(trials=40, episodes=1, seed=3), start)
    assert [t.params for t in again.trials] == [t.params for t in res.trials]


def test_a_tie_keeps_the_start():
    res = tune(SPACE, lambda p, t: 1.0, TuningBudget(trials=5), {"a": 1.0, "b": 0.0, "n": 5})
    assert res.best == {"a": 1.0, "b": 0.0, "n": 5.0}


def test_non_finite_scores_rank_last():
    res = tune(SPACE, lambda p, t: math.nan if t else -1.0, TuningBudget(trials=4),
               {"a": 1.0, "b": 0.0, "n": 5})
    assert res.score == -1.0 and res.trials[1].score == -math.inf


START = {"a": 50.0, "b": -4.0, "n": 3}


def training_search():
    return tune(SPACE, objective, TuningBudget(trials=12, episodes=1, seed=3), START)


def test_hand_is_kept_when_the_best_training_trials_are_worse_on_validation():
    """The stand-in validation prefers the start: the search's best training trials (far
    better on training) lose there, so the start is shipped, marked hand."""
    res = training_search()
    calls = []

    def validate(p):
        calls.append(p)
        return -abs(math.log10(p["a"] / START["a"]))  # best at the start's a

    sel = select(res, validate, 3)
    assert sel.kept == "hand" and sel.params == res.trials[0].params
    assert sel.candidate.number != 0 and sel.candidate.score > res.start_score
    assert sel.candidate_validation < sel.start_validation
    # the start and the three best trials that beat it on training, nothing else
    top = sorted(res.trials[1:], key=lambda t: -t.score)[:3]
    assert calls[0] == res.trials[0].params and calls[1:] == [t.params for t in top]
    assert [t for t, _ in sel.scored] == [res.trials[0], *top]


def test_the_tuned_point_best_on_validation_is_shipped_when_it_beats_the_hand_point():
    res = training_search()
    sel = select(res, lambda p: objective(p, 0), 3)  # validation agrees with training
    best = max(res.trials, key=lambda t: t.score)
    assert sel.kept == "tuned" and sel.params == best.params == sel.candidate.params
    assert sel.candidate_validation > sel.start_validation
    # validation disagrees on the order of the finalists: the second best on training ships
    second = finalists(res, 3)[1]
    sel = select(res, lambda p: 1.0 if p == second.params else -100.0 + objective(p, 0), 3)
    assert sel.kept == "tuned" and sel.params == second.params


def test_a_tie_on_validation_keeps_the_hand_point_and_nothing_better_on_training_is_not_scored():
    res = training_search()
    sel = select(res, lambda p: 0.5, 3)
    assert sel.kept == "hand" and sel.params == res.trials[0].params
    flat = tune(SPACE, lambda p, t: 1.0 if t == 0 else 0.0, TuningBudget(trials=4), START)
    calls = []
    sel = select(flat, lambda p: calls.append(p) or 9.0, 3)
    assert finalists(flat, 3) == () and len(calls) == 1
    assert sel.kept == "hand" and sel.candidate == flat.trials[0]
    nan = select(res, lambda p: 0.0 if p == res.trials[0].params else math.nan, 3)
    assert nan.kept == "hand" and nan.candidate_validation == -math.inf


@pytest.mark.parametrize("make, field", [
    (lambda: TuningBudget(trials=0), r"tuning\.trials"),
    (lambda: TuningBudget(validation=0), r"tuning\.finalists"),
    (lambda: TuningBudget(validation=-1, finalists=0), r"tuning\.validation"),
    (lambda: TuningBudget(validation=10**5, finalists=10**3), r"tuning\.validation"),
    (lambda: TuningBudget(episodes=0), r"tuning\.episodes"),
    (lambda: Param("a", 0.0, 1.0), r"Param\(a\)\.low"),
    (lambda: Param("a", 2.0, 1.0), r"Param\(a\)\.high"),
    (lambda: tune(SPACE, objective, TuningBudget(trials=1), {"a": 1.0, "b": 0.0}), "start"),
    (lambda: tune(SPACE, objective, TuningBudget(trials=1), {"a": 1e3, "b": 0.0, "n": 5}),
     r"start\.a"),
])
def test_bad_input_names_the_field(make, field):
    with pytest.raises(ValueError, match=rf"^{field}"):
        make()


BASE = ControllerSettings(MPPIConfig(sigma=(5.0, 5.0), lam=10.0), 0.01, AlphaRule(kappa=0.1),
                          MethodSettings())


def test_tuned_values_enter_the_settings():
    s = BASE.with_values("sa_rmppi", {"sigma_scale": 0.5, "lam": 2.0, "kappa": 0.3})
    assert s.sampler.sigma == (2.5, 2.5) and s.sampler.lam == 2.0 and s.rule.kappa == 0.3
    assert s.sampler.n_samples == BASE.sampler.n_samples and s.q_beta == 0.01
    g = BASE.with_values("gatekeeper", {"gatekeeper.horizon": 40.4})
    assert g.methods.gatekeeper.horizon == 40 and isinstance(g.methods.gatekeeper.horizon, int)
    p = BASE.with_values("cbf_projection", {"cbf_projection.gamma": 0.3})
    assert p.methods.cbf_projection.gamma == 0.3
    assert BASE.values("sa_rmppi") == {"sigma_scale": 1.0, "lam": 10.0, "kappa": 0.1}
    with pytest.raises(ValueError, match=r"^params"):
        BASE.with_values("bas_mppi", {"kappa": 0.3})  # not tuned for a non-robust method
    with pytest.raises(ValueError, match=r"^params\.lam"):
        BASE.with_values("bas_mppi", {"lam": 1e6})
    # every method's hand values lie in its own search space
    for m in names():
        vals = BASE.values(m)
        assert set(vals) == {p.name for p in space(m)}
        assert all(p.contains(vals[p.name]) for p in space(m))


def test_shipped_defaults_are_in_range():
    for (sys_, ctrl), t in shipped().items():
        ranges = {p.name: p for p in space(ctrl)}
        assert set(t.params) <= set(ranges), (sys_, ctrl)
        assert all(ranges[k].contains(v) for k, v in t.params.items())
        assert t.budget.trials >= 1 and t.score >= t.start_score

"""The arena's declared comparisons: rounds are added only for undecided ones, a decided one
stops (its later data, run for another comparison, is not looked at), a staged run resumes to
the same tasks, and the summary's decisions are the looks of the stored pairs."""

from __future__ import annotations

import json

import numpy as np
import pytest

from studies.arena import STUDY
from studies.arena.config import Comparison, DecisionSettings, DisturbanceSpec
from studies.arena.decisions import design, looks, members, stages
from studies.arena.tasks import plan
from workbench.study import RunStore
from workbench.study.runner import declare, profile_config
from workbench.study.runner import run as run_study
from workbench.study.sequential import detectable, run_looks

V50, V100 = DisturbanceSpec(level=50.0), DisturbanceSpec(level=100.0)


def config(**kw):
    base = {"controllers": ("bas_mppi", "sa_rmppi"), "systems": ("double_integrator",),
            "disturbances": (V50, V100), "test_maps": 5, "realisations": 10,
            "decision": DecisionSettings(rounds=3)}
    return profile_config(STUDY, "tiny", **{**base, **kw})


def fake_outputs(rule):
    """Outputs of every task from ``rule(task) -> crashed`` (all tasks finished)."""
    def outputs(task):
        return {"episodes": {"crashed": np.array([rule(task)]), "reached": np.array([False])}}
    return outputs


def _rule(task) -> bool:
    """Level 50: SA-RMPPI never crashes, BaS-MPPI always (decided at the first look).
    Level 100: each crashes in a third of the episodes, on different ones (about 45 %
    discordant pairs, no difference: too few pairs to decide before the last look)."""
    if task.disturbance == V50.label:
        return task.controller == "bas_mppi"
    if task.controller == "sa_rmppi":
        return (7 * task.map_seed + task.realisation) % 3 == 0
    return (task.map_seed + 5 * task.realisation) % 3 == 1


def test_rounds_only_for_undecided_comparisons():
    cfg = config()
    p = plan(cfg)
    wanted = stages(cfg, p.rounds, fake_outputs(_rule))
    by_round = {r: {t for t in wanted if cfg.round_of(t.map_seed) == r} for r in range(3)}
    assert by_round[0] == set(p.rounds[0][""])
    # level 50 decided at look 1: no later round of it
    assert all(t.disturbance == V100.label for r in (1, 2) for t in by_round[r])
    m50, m100 = members(cfg)
    import pandas as pd

    ep = pd.DataFrame([{**t.columns(), "crashed": _rule(t), "reached": False}
                       for t in wanted])
    l50, l100 = looks(cfg, ep, m50), looks(cfg, ep, m100)
    assert [x.decision for x in l50] == ["superior"]
    assert [x.decision for x in l100] == ["continue", "continue", "undecided"]
    assert by_round[1] and by_round[2]  # every round ran for it, both controllers
    assert {t.controller for t in by_round[2]} == {"bas_mppi", "sa_rmppi"}
    # a member's looks are those of the sequential design on its per-round counts
    ref = run_looks(design(cfg), [50], [0], [50])
    assert (l50[0].low, l50[0].high) == (ref[0].low, ref[0].high)


def test_stages_wait_for_a_round_to_finish():
    cfg = config()
    p = plan(cfg)
    done = set(p.rounds[0][""][:-1])  # one round-0 task missing

    def outputs(task):
        return fake_outputs(_rule)(task) if task in done else None

    assert stages(cfg, p.rounds, outputs) == list(p.rounds[0][""])


def test_declared_comparisons_are_checked_and_expanded():
    with pytest.raises(ValueError, match=r"^comparisons\[0\]\.first"):
        config(comparisons=(Comparison("rmppi", "bas_mppi"),))
    with pytest.raises(ValueError, match=r"^comparisons\[0\]\.disturbances"):
        config(comparisons=(Comparison("sa_rmppi", "bas_mppi", disturbances=("kick(1)",)),))
    with pytest.raises(ValueError, match=r"^comparisons\.metric"):
        Comparison("sa_rmppi", "bas_mppi", metric="speed")
    with pytest.raises(ValueError, match=r"^decision\.margin"):
        DecisionSettings(margin=0.0)
    cfg = config(comparisons=(Comparison("sa_rmppi", "bas_mppi", disturbances=(V100.label,)),
                              Comparison("bas_mppi", "sa_rmppi", metric="success")))
    assert len(members(cfg)) == 1 + 2
    assert design(cfg).comparisons == 3
    # test maps of every round are disjoint from the tuning maps
    with pytest.raises(ValueError, match=r"^test_seed"):
        config(test_seed=0, tuning_seed=11, tuning_maps=1)


@pytest.fixture(scope="module")
def staged_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("staged")
    cfg = profile_config(STUDY, "tiny", controllers=("bas_mppi", "sa_rmppi"),
                         systems=("double_integrator",), disturbances=(V50,), test_maps=1,
                         realisations=2, decision=DecisionSettings(rounds=2))
    return cfg, out, run_study(STUDY, cfg, out, workers=0, progress=False)


def test_a_staged_run_adds_its_round_and_resumes_to_the_same_tasks(staged_run):
    cfg, out, outcome = staged_run
    ep = RunStore(out).table("episodes")
    # 2 pairs cannot decide anything: the second round ran
    assert sorted(set(ep["map_seed"])) == [1000, 1001]
    data = json.loads((out / "summary.json").read_text())
    (row,) = data["decisions"]
    assert (row["looks"], row["n"], row["verdict"]) == (2, 4, "undecided")
    dz = design(cfg)
    disc = max((row["b"] + row["c"]) / 4, 1 / 4)  # no discordant pair: one assumed
    assert row["detectable"] == pytest.approx(
        detectable(4, disc, dz.alpha, dz.power, dz.looks, dz.comparisons), rel=1e-12)
    assert row["detectable"] > 0.3  # four pairs detect only a large difference
    assert outcome.run.n_tasks == len(ep) == 8
    study, _ = declare(STUDY, cfg)
    assert len(study.tasks) == 8
    again = run_study(STUDY, cfg, out, workers=0, progress=False)
    assert again.run.computed == 0 and again.run.n_tasks == 8
    assert json.loads((out / "summary.json").read_text()) == data
    text = outcome.report.read_text()
    assert "Declared comparisons and their verdicts" in text and "undecided" in text

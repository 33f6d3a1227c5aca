"""The arena's tuning: the test, training and validation map ranges are pairwise disjoint at
config time; the arena refuses shipped values tuned or validated on its test maps, tuned
without validation, or tuned on another definition of their system; the objective is one
function; a tiny tuning run ships entries with their provenance (the hash of each system as
the run defined it) and keeps the tuned point only when it beats the hand point on
validation."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from studies.arena import STUDY as ARENA
from studies.arena.tasks import settings
from studies.arena.tuning import check, objective_value, ship, system_hashes
from studies.arena_tuning import STUDY
from workbench.scenarios import tuned as tuned_module
from workbench.scenarios.systems import SYSTEMS, definition, definition_hash, system
from workbench.scenarios.tuned import (
    Evaluation,
    MapSeeds,
    Tuned,
    TunedFileError,
    check_usable,
    shipped,
    write,
)
from workbench.study import RunStore
from workbench.study.runner import profile_config
from workbench.study.runner import run as run_study
from workbench.study.tuning import TuningBudget


def tiny(**overrides):
    return profile_config(STUDY, "tiny", **overrides)


@pytest.mark.parametrize("overrides, field, words", [
    ({"test_seed": 3, "tuning_seed": 0, "tuning_maps": 4}, "test_seed",
     "test maps 3..4 overlap the tuning maps 0..3"),
    ({"validation_seed": 3, "validation_maps": 2, "tuning_seed": 0, "tuning_maps": 4},
     "validation_seed", "validation maps 3..4 overlap the tuning maps 0..3"),
    ({"validation_seed": 999, "validation_maps": 2, "test_seed": 1000},
     "validation_seed", "validation maps 999..1000 overlap the test maps 1000..1001"),
])
def test_the_three_map_ranges_are_pairwise_disjoint(overrides, field, words):
    with pytest.raises(ValueError, match=rf"^{field} = \d+ is invalid: {words}"):
        tiny(**overrides)
    base = tiny()
    assert not set(base.validation_seeds()) & set(base.tuning_seeds() + base.map_seeds())


def test_a_tuning_run_needs_validation_and_every_map_each_trial():
    with pytest.raises(ValueError, match=r"^tuning\.validation = 0 is invalid: must be >= 1"):
        check(tiny(tuning=TuningBudget(trials=2, episodes=1, validation=0, finalists=0)))
    with pytest.raises(ValueError, match=r"^tuning\.episodes = 1 is invalid: .*\(2: seeds"):
        check(tiny(tuning_maps=2))
    with pytest.raises(ValueError, match=r"^tuning\.validation = 1 is invalid: .*\(3: seeds"):
        check(tiny(validation_maps=3))
    for profile in ("tiny", "quick", "verdict"):
        check(profile_config(STUDY, profile))


def test_the_objective():
    assert objective_value([True, False, True, True], [0.0, 10.0, 2.0, 0.0]) == pytest.approx(
        0.75 - 0.01 * 3.0)
    assert objective_value(np.array([1.0]), np.array([0.5])) == pytest.approx(0.995)
    with pytest.raises(ValueError, match=r"^success"):
        objective_value([], [])
    with pytest.raises(ValueError, match=r"^success"):
        objective_value([1, 0], [0.0])


def entry(controller: str, train: tuple[int, ...], val: tuple[int, ...] | None,
          system_hash: str | None = None) -> Tuned:
    hand = {"sigma_scale": 1.0, "lam": 10.0} | ({"kappa": 0.1} if controller != "bas_mppi"
                                                 else {})
    return Tuned("double_integrator", controller, "tuned", hand, hand, hand, TuningBudget(),
                 "x", "velocity_variance(50)",
                 Evaluation((MapSeeds("spec", train),), 8, 0.1, 0.2),
                 Evaluation(None, None, None, None) if val is None else
                 Evaluation((MapSeeds("spec", val),), 8, 0.1, 0.2),
                 system_hash or definition_hash("double_integrator"))


def test_the_arena_refuses_tuned_values_tuned_on_its_test_maps(tmp_path, monkeypatch):
    """Where the arena resolves a tuned setting: disjoint maps pass; overlapping training or
    validation maps, or no validation, are refused naming the pair, the seeds and the file."""
    path = tmp_path / "tuned.json"
    monkeypatch.setattr(tuned_module, "SHIPPED", path)
    cfg = profile_config(ARENA, "tiny", tunings=("hand", "tuned"), test_maps=3)  # 1000..1002
    write([entry("bas_mppi", (0, 1, 2, 3), (500, 501)),
           entry("sa_rmppi", (0, 1, 1001), (500,)),
           entry("rmppi", (0,), (1002, 1003))], path)
    assert settings(cfg, "double_integrator", "bas_mppi", "tuned").sampler.lam == 10.0
    for controller, kind, seeds in (("sa_rmppi", "training", "[1001]"),
                                    ("rmppi", "validation", "[1002]")):
        with pytest.raises(TunedFileError) as info:
            settings(cfg, "double_integrator", controller, "tuned")
        msg = str(info.value)
        assert f"(double_integrator, {controller}) in {path}" in msg, msg
        assert f"spec maps {seeds} among their {kind} maps" in msg, msg
    write([entry("bas_mppi", (0, 1, 2, 3), None)], path)
    with pytest.raises(TunedFileError, match=r"\(double_integrator, bas_mppi\) in .*no "
                       r"validation score.*rerun `make tune-arena`"):
        settings(cfg, "double_integrator", "bas_mppi", "tuned")
    assert settings(cfg, "double_integrator", "bas_mppi", "hand").sampler.lam == 10.0


def test_the_arena_refuses_tuned_values_of_a_redefined_system(tmp_path, monkeypatch):
    """Values tuned before the system's definition changed (here its disturbance scale), or
    whose definition was not recorded, are refused where the arena resolves them, naming the
    pair, the file and both hashes."""
    path = tmp_path / "tuned.json"
    monkeypatch.setattr(tuned_module, "SHIPPED", path)
    cfg = profile_config(ARENA, "tiny", tunings=("hand", "tuned"), test_maps=3)
    old = definition_hash("double_integrator")
    write([entry("bas_mppi", (0, 1, 2, 3), (500, 501), old)], path)
    assert settings(cfg, "double_integrator", "bas_mppi", "tuned").sampler.lam == 10.0
    monkeypatch.setitem(SYSTEMS, "double_integrator", dataclasses.replace(
        system("double_integrator"), level_scale=2.0))
    new = definition_hash("double_integrator")
    assert new != old
    with pytest.raises(TunedFileError) as info:
        settings(cfg, "double_integrator", "bas_mppi", "tuned")
    msg = str(info.value)
    for words in (f"(double_integrator, bas_mppi) in {path}", old, new,
                  "definition changed since tuning", "rerun `make tune-arena`"):
        assert words in msg, msg
    d = json.loads(path.read_text())
    d["tuned"][0]["system_hash"] = None
    path.write_text(json.dumps(d))
    with pytest.raises(TunedFileError, match=r"\(double_integrator, bas_mppi\) in .*no system "
                       r"hash.*rerun `make tune-arena`"):
        settings(cfg, "double_integrator", "bas_mppi", "tuned")


def test_a_tiny_tuning_run_ships_its_provenance(tmp_path, monkeypatch):
    cfg = tiny(systems=("double_integrator",), controllers=("bas_mppi", "sa_rmppi"),
               tuning=TuningBudget(trials=3, episodes=1, validation=1, finalists=2))
    out = tmp_path / "run"
    outcome = run_study(STUDY, cfg, out, workers=0, progress=False)
    store = RunStore(out)
    trials, best = store.table("trials"), store.table("best")
    assert len(trials) == 2 * 3 and len(best) == 2
    for _, r in best.iterrows():  # the shipping rule, from the stored scores
        t = trials[trials["task_id"] == r["task_id"]].sort_values("trial")
        start = t.iloc[0]
        assert r["training_hand"] == start["score"]
        assert r["validation_hand"] == start["validation"]
        scored = t[t["validation"].notna()]
        assert scored.iloc[0]["trial"] == 0
        assert set(scored["trial"].iloc[1:]) == set(t[t["score"] > start["score"]].nlargest(
            2, "score")["trial"])
        beats = r["validation_tuned"] > r["validation_hand"]
        assert r["kept"] == ("tuned" if beats else "hand")
        assert json.loads(r["params"]) == json.loads(
            r["tuned"] if beats else start["params"])
        assert json.loads(r["hand"]) == json.loads(start["params"])
    target = tmp_path / "tuned.json"
    ship(out, target)
    entries = shipped(target)
    assert set(entries) == {("double_integrator", "bas_mppi"), ("double_integrator", "sa_rmppi")}
    for t in entries.values():
        assert t.training.maps == (MapSeeds("spec", (0,)),)
        assert t.validation.maps == (MapSeeds("spec", (500,)),)
        assert (t.training.episodes, t.validation.episodes) == (1, 1)
        assert t.disturbance == "velocity_variance(50)" and t.budget == cfg.tuning
        assert t.params and t.kept in ("tuned", "hand")
        check_usable(t, ["spec"], cfg.map_seeds())
    text = outcome.report.read_text()
    assert "validation, hand" in text and "validation, tuned" in text
    assert "spec seeds 500..500" in text
    # the system hash is that of the run's stored fingerprint, which round-trips to the live
    # definition's hash while the system is unchanged
    stored = json.loads((out / "manifest.json").read_text())["fingerprint"]["system_values"]
    h = definition_hash(stored["double_integrator"])
    assert stored["double_integrator"] == json.loads(json.dumps(definition("double_integrator")))
    assert h == definition_hash("double_integrator") == system_hashes(out)["double_integrator"]
    assert {t.system_hash for t in entries.values()} == {h}
    assert f"double_integrator {h}" in text
    summary = json.loads((out / "summary.json").read_text())
    assert {e["system_hash"] for e in summary["tuned"]} == {h}
    # shipped after the system was redefined: the run's definition is recorded, not the new
    # one, also from a summary written before entries carried a hash; the arena refuses it
    monkeypatch.setitem(SYSTEMS, "double_integrator", dataclasses.replace(
        system("double_integrator"), disturbed=("vx",)))
    assert definition_hash("double_integrator") != h
    for e in summary["tuned"]:
        del e["system_hash"]
    (out / "summary.json").write_text(json.dumps(summary))
    later = tmp_path / "later.json"
    ship(out, later)
    for t in shipped(later).values():
        assert t.system_hash == h
        with pytest.raises(TunedFileError, match="definition changed since tuning"):
            check_usable(t, ["spec"], cfg.map_seeds())
    # a summary whose hash disagrees with the run's manifest is not shipped
    summary["tuned"][0]["system_hash"] = "0" * 16
    (out / "summary.json").write_text(json.dumps(summary))
    with pytest.raises(TunedFileError, match=r"records system hash 0{16}, but the run's "
                       r"manifest defines double_integrator as"):
        ship(out, tmp_path / "bad.json")

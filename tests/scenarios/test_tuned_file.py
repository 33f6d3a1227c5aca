"""The shipped tuned values' file: the format round-trips with its provenance; an older,
damaged or hand-broken file is refused with an error that names it and says to rerun the
tuning; an entry tuned without validation, on maps an evaluation tests on, on another
definition of its system or on an unrecorded one, is refused for use, naming the system, the
controller and the file. A system's definition hash is stable and follows every value of the
definition."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from workbench.scenarios.systems import (
    DEFINITION_FIELDS,
    SYSTEMS,
    definition,
    definition_hash,
    register_system,
    system,
    unregister_system,
)
from workbench.scenarios.tuned import (
    FORMAT,
    Evaluation,
    MapSeeds,
    Tuned,
    TunedFileError,
    check_usable,
    scores,
    shipped,
    space,
    tuned,
    write,
)
from workbench.study.io import dumps_json
from workbench.study.tuning import TuningBudget

HAND = {"sigma_scale": 1.0, "lam": 10.0, "kappa": 0.1}
BEST = {"sigma_scale": 0.5, "lam": 2.0, "kappa": 0.3}


def entry(**kw) -> Tuned:
    d = dict(system="double_integrator", controller="sa_rmppi", kept="tuned", params=BEST,
             hand=HAND, tuned=BEST, budget=TuningBudget(trials=8, episodes=8, validation=8,
                                                 finalists=3),
             objective="success", disturbance="velocity_variance(50)",
             training=Evaluation((MapSeeds("spec", (0, 1, 2, 3)),), 8, 0.5, 0.9),
             validation=Evaluation((MapSeeds("spec", (500, 501, 502, 503)),), 8, 0.6, 0.7),
             system_hash=definition_hash("double_integrator"))
    d.update(kw)
    return Tuned(**d)


def test_the_format_round_trips(tmp_path):
    path = tmp_path / "tuned.json"
    a = entry()
    b = entry(system="unicycle", controller="bas_mppi", kept="hand",
              params={"sigma_scale": 1.0, "lam": 0.3}, hand={"sigma_scale": 1.0, "lam": 0.3},
              tuned={"sigma_scale": 2.0, "lam": 1.0},
              training=Evaluation((MapSeeds("spec", (0, 1)), MapSeeds("corridor", (0, 1))), 8,
                                  -0.1, float("-inf")),
              validation=Evaluation((MapSeeds("spec", (7,)),), 4, 0.2, 0.1), system_hash=None)
    write([b, a], path)
    data = json.loads(path.read_text())
    assert data["format"] == FORMAT == 3
    assert [(e["system"], e["kept"]) for e in data["tuned"]] == [("double_integrator", "tuned"),
                                                                 ("unicycle", "hand")]
    e = data["tuned"][0]
    assert e["training"] == {"maps": [{"family": "spec", "seeds": [0, 1, 2, 3]}], "episodes": 8,
                             "hand": 0.5, "tuned": 0.9}
    assert e["validation"]["maps"][0]["seeds"] == [500, 501, 502, 503]
    assert e["budget"] == {"trials": 8, "episodes": 8, "seed": 0, "validation": 8,
                           "finalists": 3}
    assert data["tuned"][1]["training"]["tuned"] is None  # strict JSON: -inf is null
    assert e["system_hash"] == definition_hash("double_integrator")
    assert data["tuned"][1]["system_hash"] is None
    back = shipped(path)
    assert back[("double_integrator", "sa_rmppi")] == a
    assert back[("double_integrator", "sa_rmppi")].source == path
    assert back[("unicycle", "bas_mppi")].as_dict() == {
        **b.as_dict(), "training": {**b.training.as_dict(), "tuned": None}}
    assert tuned("unicycle", "bas_mppi", path).params == {"sigma_scale": 1.0, "lam": 0.3}
    s = scores(path)
    assert [(r.system, r.kept, r.training_hand, r.validation_tuned, r.validation_episodes)
            for r in s] == [("double_integrator", "tuned", 0.5, 0.7, 8),
                            ("unicycle", "hand", -0.1, 0.1, 4)]
    write([entry(kept="hand", params=HAND)], path)  # a rewritten file is read again
    assert tuned("double_integrator", "sa_rmppi", path).params == HAND
    assert tuned("unicycle", "bas_mppi", path) is None


def good(tmp_path) -> dict:
    write([entry()], tmp_path / "good.json")
    return json.loads((tmp_path / "good.json").read_text())


def refused(tmp_path, text: str, *words: str) -> None:
    path = tmp_path / "bad.json"
    path.write_text(text)
    with pytest.raises(TunedFileError) as info:
        shipped(path)
    msg = str(info.value)
    assert msg.startswith(str(path)) and "rerun `make tune-arena`" in msg, msg
    for w in words:
        assert w in msg, msg


def test_a_damaged_file_is_refused_naming_it(tmp_path):
    refused(tmp_path, '{"format": 3, "tuned": [', "cannot be read as JSON")
    refused(tmp_path, "[]", "not a tuned-values file")


def test_an_older_format_is_refused_naming_it(tmp_path):
    old = {"tuned": [{"system": "double_integrator", "controller": "bas_mppi",
                      "params": {"lam": 2.0}, "score": 1.0, "start_score": 0.5,
                      "budget": {"trials": 16, "episodes": 4, "seed": 0}, "objective": "x",
                      "training": "4 episodes per trial on maps spec-0"}]}
    refused(tmp_path, json.dumps(old), "older format", "format 3")
    refused(tmp_path, json.dumps({**good(tmp_path), "format": 1}), "format 1")


def test_format_2_is_refused_naming_the_file(tmp_path):
    """A file of the format before entries carried their system's hash: well formed then,
    refused now, naming the file and saying to rerun the tuning."""
    d = good(tmp_path)
    for e in d["tuned"]:
        del e["system_hash"]
    refused(tmp_path, json.dumps({**d, "format": 2}), "is in format 2",
            "this version reads format 3")
    refused(tmp_path, json.dumps(d), "missing ['system_hash']")  # and not in format 3


@pytest.mark.parametrize("edit, words", [
    (lambda e: e.update(params={}), ("entry 0 (double_integrator, sa_rmppi)", "params",
                                     "hand-tuned point")),
    (lambda e: e.update(params={"lam": None}), ("params.lam", "finite number")),
    (lambda e: e.update(kept="best"), ("kept",)),
    (lambda e: e.update(params=HAND), ("kept is 'tuned' but params differ from 'tuned'",)),
    (lambda e: e.update(kept="hand"), ("kept is 'hand' but params differ from 'hand'",)),
    (lambda e: e.update(hand={}), ("hand",)),
    (lambda e: e.pop("validation"), ("missing ['validation']",)),
    (lambda e: e.update(note="hand edit"), ("unknown ['note']",)),
    (lambda e: e.update(system_hash="abc"), ("system_hash", "16 hex digits")),
    (lambda e: e.update(system_hash=12), ("system_hash", "16 hex digits")),
    (lambda e: e["budget"].update(trials=0), ("budget", "tuning.trials")),
    (lambda e: e["training"].update(maps=None), ("training.maps",)),
    (lambda e: e["validation"].update(episodes=None), ("validation.episodes",)),
    (lambda e: e["validation"]["maps"][0].update(seeds=[1.5]), ("validation.maps[0].seeds",)),
])
def test_a_hand_broken_entry_is_refused_naming_the_file_and_the_entry(tmp_path, edit, words):
    d = good(tmp_path)
    edit(d["tuned"][0])
    refused(tmp_path, json.dumps(d), *words)


def test_a_repeated_pair_is_refused(tmp_path):
    d = good(tmp_path)
    d["tuned"].append(d["tuned"][0])
    refused(tmp_path, json.dumps(d), "entry 1", "repeats (double_integrator, sa_rmppi)")
    with pytest.raises(TunedFileError, match="repeats"):
        write([entry(), entry()], tmp_path / "twice.json")


def test_an_entry_without_validation_is_refused_for_use(tmp_path):
    path = tmp_path / "t.json"
    write([entry(validation=Evaluation(None, None, None, None))], path)
    t = tuned("double_integrator", "sa_rmppi", path)  # it reads: the file is well formed
    with pytest.raises(TunedFileError) as info:
        check_usable(t, ["spec"], range(1000, 1003))
    msg = str(info.value)
    assert "(double_integrator, sa_rmppi)" in msg and str(path) in msg
    assert "validation" in msg and "rerun `make tune-arena`" in msg


@pytest.mark.parametrize("kind, seeds", [("training", range(3, 6)),
                                         ("validation", range(503, 510))])
def test_an_entry_tuned_on_the_test_maps_is_refused_for_use(tmp_path, kind, seeds):
    path = tmp_path / "t.json"
    write([entry()], path)
    t = tuned("double_integrator", "sa_rmppi", path)
    with pytest.raises(TunedFileError) as info:
        check_usable(t, ["spec"], seeds)
    msg = str(info.value)
    common = "[3]" if kind == "training" else "[503]"
    assert re.search(rf"spec maps {re.escape(common)} among their {kind} maps", msg), msg
    assert "(double_integrator, sa_rmppi)" in msg and str(path) in msg
    # the same seeds of another family, and disjoint seeds, are fine
    assert check_usable(t, ["corridor"], seeds) is t
    assert check_usable(t, ["spec", "corridor"], range(1000, 1020)) is t


def test_params_outside_the_search_space_are_refused_for_use(tmp_path):
    path = tmp_path / "t.json"
    partial = {"sigma_scale": 0.5, "lam": 2.0}
    write([entry(params=partial, tuned=partial),
           entry(controller="rmppi", params={**BEST, "lam": 1e6}, tuned={**BEST, "lam": 1e6})],
          path)
    with pytest.raises(TunedFileError, match=r"set \['lam', 'sigma_scale'\]"):
        check_usable(tuned("double_integrator", "sa_rmppi", path), ["spec"], [1000])
    with pytest.raises(TunedFileError, match=r"lam = 1e\+06, outside"):
        check_usable(tuned("double_integrator", "rmppi", path), ["spec"], [1000])


def test_the_shipped_file_reads():
    """Every shipped entry is in format 3, sets its controller's whole search space within
    range, and was tuned on maps disjoint from its validation maps."""
    ship = shipped()
    assert ship
    for (s, c), t in ship.items():
        ranges = {p.name: p for p in space(c)}
        assert set(t.params) == set(ranges), (s, c)
        assert all(ranges[k].contains(v) for k, v in t.params.items())
        for m in t.validation.maps or ():
            assert not set(m.seeds) & set(t.training.seeds(m.family)), (s, c)


def test_an_entry_without_a_system_hash_is_refused_for_use(tmp_path):
    path = tmp_path / "t.json"
    write([entry(system_hash=None)], path)
    t = tuned("double_integrator", "sa_rmppi", path)  # it reads: the file is well formed
    assert t.system_hash is None
    with pytest.raises(TunedFileError) as info:
        check_usable(t, ["spec"], range(1000, 1003))
    msg = str(info.value)
    assert "(double_integrator, sa_rmppi)" in msg and str(path) in msg, msg
    assert "no system hash" in msg and "rerun `make tune-arena`" in msg, msg


def test_an_entry_tuned_on_another_definition_of_its_system_is_refused_for_use(tmp_path):
    path = tmp_path / "t.json"
    stale = definition_hash({**definition("double_integrator"), "level_scale": 2.0})
    write([entry(system_hash=stale)], path)
    t = tuned("double_integrator", "sa_rmppi", path)
    with pytest.raises(TunedFileError) as info:
        check_usable(t, ["spec"], range(1000, 1003))
    msg = str(info.value)
    now = definition_hash("double_integrator")
    assert stale != now
    for words in ("(double_integrator, sa_rmppi)", str(path), stale, now,
                  "the system's definition changed since tuning",
                  "rerun `make tune-arena`"):
        assert words in msg, msg
    write([entry()], path)  # the current definition's hash passes
    assert check_usable(tuned("double_integrator", "sa_rmppi", path), ["spec"], [1000])


def test_the_definition_hash_is_stable():
    """A fixed value for fixed values (the SHA-256 of the sorted, compact JSON: a change to
    the hashing shows here), the same in another process, in any key order, for tuples or
    lists, for integers or floats, and after a JSON round trip through a run's stored
    fingerprint."""
    fixed = {"lam": 10, "Q": (1, 2.0), "disturbed": ("vx",), "cost_form": "goal",
             "fw": {"mu": 1e-6}}
    assert definition_hash(fixed) == "d2e47f94648fc49d"
    d = definition("double_integrator")
    h = definition_hash("double_integrator")
    assert len(h) == 16 and int(h, 16) >= 0
    assert h == definition_hash(system("double_integrator")) == definition_hash(d)
    code = ("from workbench.scenarios.systems import definition_hash as h; "
            "print(h('double_integrator'))")
    root = str(Path(__file__).resolve().parents[2])
    other = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                           check=True, cwd=root,
                           env={**os.environ, "PYTHONHASHSEED": "123", "PYTHONPATH": root})
    assert other.stdout.strip() == h
    assert definition_hash(dict(reversed(list(d.items())))) == h
    listed = {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}
    assert isinstance(d["Q"], tuple) and definition_hash(listed) == h
    assert definition_hash({**d, "lam": int(d["lam"])}) == h  # 10 and 10.0: the same weight
    for name in SYSTEMS:
        stored = json.loads(dumps_json({"system_values": {name: definition(name)}}))
        assert definition_hash(stored["system_values"][name]) == definition_hash(name), name


CHANGES = {"Q": {"Q": (1.0, 1.0, 0.1, 0.2)}, "S": {"S": (10.0, 10.0, 1.0, 2.0)},
           "sigma": {"sigma": (5.0, 4.0)}, "lam": {"lam": 11.0}, "q_beta": {"q_beta": 0.02},
           "disturbed": {"disturbed": ("vx",)}, "scale": {"scale": 0.5},
           "level_scale": {"level_scale": 0.9}, "cost_form": {"cost_form": "goal"}}


@pytest.mark.parametrize("field", DEFINITION_FIELDS)
def test_the_definition_hash_follows_every_value(field):
    """A system that differs from the double integrator in one value of its definition has
    another hash, read by name from the registry as the arena reads it."""
    base = system("double_integrator")
    fw = base.feedback_weights
    change = CHANGES.get(field) or {"feedback_weights": dataclasses.replace(fw, q_beta=2.0)}
    assert set(change) == {field}
    twin = dataclasses.replace(base, name="definition_twin", **change)
    register_system(twin)
    try:
        assert definition_hash("definition_twin") != definition_hash("double_integrator")
        same = dataclasses.replace(base, name="definition_same")
        assert definition_hash(same) == definition_hash("double_integrator")
    finally:
        unregister_system("definition_twin")


@pytest.mark.parametrize("field", ["Q", "R", "q_beta", "mu", "mu_max"])
def test_the_definition_hash_follows_every_feedback_weight(field):
    base = system("double_integrator")
    fw = base.feedback_weights
    v = getattr(fw, field)
    new = tuple(x + 1.0 for x in v) if isinstance(v, tuple) else v * 2.0
    other = dataclasses.replace(base, feedback_weights=dataclasses.replace(fw, **{field: new}))
    assert definition_hash(other) != definition_hash(base)

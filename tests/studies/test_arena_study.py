"""The arena: config errors name the field, common random numbers hold within a (system, map,
disturbance, realisation), the summary's cells and pooled comparisons are the tidy data's, the
tuned section records parameters and budget, and the verdict text is generated."""

from __future__ import annotations

import json

import casadi as ca
import numpy as np
import pytest

from studies.arena import STUDY
from studies.arena.config import ArenaConfig, DisturbanceSpec
from studies.arena.episodes import setup
from studies.arena.summary import pairs
from studies.arena.tasks import hand_settings, where
from workbench.scenarios.maps import MapFamily
from workbench.study import Rate, RunStore
from workbench.study.runner import profile_config
from workbench.study.runner import run as run_study
from workbench.study.stats import pooled_paired
from workbench.study.tuning import TuningBudget

CELL_FIELDS = {"controller", "system", "map", "disturbance", "safety", "ci_low", "ci_high", "n",
               "mean_step_ms"}
POOLED_FIELDS = {"b", "c", "p_value", "difference", "low", "high", "n_maps"}


def tiny(**overrides):
    return profile_config(STUDY, "tiny", **overrides)


@pytest.mark.parametrize("overrides, field", [
    ({"systems": ("double_integrator", "hovercraft")}, "systems"),
    ({"controllers": ("bas_mppi", "lqr")}, "controllers"),
    ({"tunings": ("hand", "best")}, "tunings"),
    ({"families": (MapFamily("spec"), MapFamily("spec"))}, "families"),
    ({"realisations": 0}, "realisations"),
    ({"test_seed": 1, "tuning_seed": 0, "tuning_maps": 4}, "test_seed"),
])
def test_bad_config_names_the_field(overrides, field):
    with pytest.raises(ValueError, match=rf"^{field}"):
        tiny(**overrides)


@pytest.mark.parametrize("name, value", [("lam", 50.0), ("sigma", (0.1, 0.1))])
def test_sampler_values_the_arena_sets_per_system_are_refused(name, value):
    """sigma and lambda come from each system (hand) or its tuned values: a value given in
    the config would be recorded and ignored, so it is refused."""
    from dataclasses import replace

    base = tiny()
    with pytest.raises(ValueError, match=rf"^sampler\.{name} = .*set per system"):
        tiny(sampler=replace(base.sampler, **{name: value}))


def test_zero_budget_unknown_family_and_disturbance_name_the_field():
    with pytest.raises(ValueError, match=r"^disturbances\.model"):
        DisturbanceSpec("gust")
    with pytest.raises(ValueError, match=r"^tuning\.trials"):
        TuningBudget(trials=0)
    with pytest.raises(ValueError, match=r"^map\.family"):
        MapFamily("maze")


def test_start_inside_a_generated_obstacle_names_the_field():
    with pytest.raises(ValueError, match=r"^map\.start"):
        tiny(families=(MapFamily("spec", start=(5.0 - 1.4, 5.0)),))


def test_pairs_each_once_with_ablations():
    p = pairs(("bas_mppi", "sa_rmppi", "rmppi"))
    assert p == [("sa_rmppi", "rmppi"), ("rmppi", "bas_mppi"), ("sa_rmppi", "bas_mppi")]
    assert pairs(("bas_mppi", "sa_rmppi", "tube_mppi")) == [
        ("sa_rmppi", "bas_mppi"), ("tube_mppi", "bas_mppi"), ("tube_mppi", "sa_rmppi")]


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("arena")
    cfg = tiny()
    return cfg, out, run_study(STUDY, cfg, out, workers=0, progress=False)


def test_common_random_numbers(tiny_run):
    """w_k = x_{k+1} - F(x_k, u_k) is one sequence per (system, map, disturbance,
    realisation), whatever the controller; different realisations differ."""
    cfg, out, _ = tiny_run
    store = RunStore(out)
    ep = store.table("episodes")
    seqs: dict[tuple, list[np.ndarray]] = {}
    for _, r in ep.iterrows():
        plant = setup(where(cfg, r["system"], r["family"], int(r["map_seed"])),
                      hand_settings(cfg, r["system"])).plant
        f = ca.Function("f", [plant.x, plant.u], [plant.x_next])
        a = store.arrays(r["task_id"])
        X, U = a["X"], a["U"]
        w = np.array([X[k + 1] - np.asarray(f(X[k], U[k])).ravel() for k in range(len(U))])
        seqs.setdefault((r["system"], r["map"], r["disturbance"], r["realisation"]),
                        []).append(w)
    assert len(seqs) == 2 * 2 * 2 * 2
    for ws in seqs.values():
        assert len(ws) == len(cfg.controllers)
        n = min(len(w) for w in ws)
        for w in ws[1:]:
            np.testing.assert_allclose(w[:n], ws[0][:n], rtol=0, atol=1e-12)
    keys = sorted(seqs)
    a, b = seqs[keys[0]][0], seqs[keys[1]][0]
    n = min(len(a), len(b))
    assert not np.allclose(a[:n], b[:n])


def test_summary_is_the_data(tiny_run):
    cfg, out, outcome = tiny_run
    store = RunStore(out)
    ep, timing = store.table("episodes"), store.table("timing")
    data = json.loads((out / "summary.json").read_text())
    cells = data["cells"]
    assert len(cells) == 3 * 2 * 2 * 2
    for c in cells:
        assert CELL_FIELDS <= set(c)
        rows = ep[(ep["controller"] == c["controller"]) & (ep["system"] == c["system"])
                  & (ep["map"] == c["map"]) & (ep["disturbance"] == c["disturbance"])]
        rate = Rate.of(~rows["crashed"].to_numpy(bool))
        assert (c["n"], c["safety"], c["ci_low"], c["ci_high"]) == (
            rate.n, rate.value, rate.low, rate.high)
        t = timing[timing["task_id"].isin(rows["task_id"])]
        assert c["mean_step_ms"] == pytest.approx(t["mean_cpu_ms"].mean(), rel=1e-12)
    pooled = data["pooled"]
    assert pooled
    for p in pooled:
        assert POOLED_FIELDS <= set(p)
        if p["disturbance"] == "all" or ":" in p["first"]:
            continue
        x = ep[(ep["controller"] == p["first"]) & (ep["system"] == p["system"])
               & (ep["disturbance"] == p["disturbance"])]
        y = ep[(ep["controller"] == p["second"]) & (ep["system"] == p["system"])
               & (ep["disturbance"] == p["disturbance"])]
        m = x.merge(y, on=["map", "realisation"], suffixes=("_1", "_2"))
        strata = []
        for _, g in m.groupby("map"):
            s1, s2 = ~g["crashed_1"].to_numpy(bool), ~g["crashed_2"].to_numpy(bool)
            strata.append((int(np.sum(s1 & s2)), int(np.sum(s1 & ~s2)),
                           int(np.sum(~s1 & s2)), int(np.sum(~s1 & ~s2))))
        ref = pooled_paired(strata)
        assert (p["b"], p["c"], p["n_maps"]) == (ref.b, ref.c, 2)
        assert p["p_value"] == pytest.approx(ref.p_value, rel=1e-12)
    tuned = data["tuned"]
    assert set(tuned) == {f"{s}/{c}" for s in cfg.systems for c in cfg.controllers}
    assert all("hand" in e and "searched" in e for e in tuned.values())
    assert {m["map"] for m in data["maps"]} == {"spec-1000", "spec-1001"}
    text = outcome.report.read_text()
    assert data["verdict"]["text"][0] in text
    assert "SPEC" not in text and (out / "frontier.png").stat().st_size > 10_000


def test_task_count_of_the_profiles():
    from studies.arena.decisions import design, members
    from studies.arena.tasks import plan
    from workbench.study.sequential import plan_pairs

    v = profile_config(STUDY, "verdict")
    assert v.test_maps >= 12 and {d.label for d in v.disturbances} == {
        "velocity_variance(50)", "velocity_variance(100)"}
    # round 0: the grid; rounds 1-3: both controllers of each of the 4 declared comparisons
    assert len(plan(v).tasks) == 2 * 12 * 2 * 2 * 5 + 3 * 4 * 2 * 12 * 5
    dz = design(v)
    assert len(members(v)) == dz.comparisons == 4
    # sized to decide: the budget covers the planned pairs at the declared difference
    assert dz.max_pairs >= plan_pairs(dz.margin, v.decision.discordance, dz.alpha, dz.power,
                                      dz.looks, dz.comparisons)
    assert isinstance(profile_config(STUDY, "quick"), ArenaConfig)


def test_moving_obstacles_and_other_families_run(tmp_path):
    """Corridor maps with moving circles and occupancy maps: the episode's crash check uses the
    moving scene (its stored path is checked against the scene of each step here)."""
    cfg = tiny(controllers=("bas_mppi",), systems=("double_integrator",),
               families=(MapFamily("corridor", moving=2, speed=1.0), MapFamily("occupancy")),
               test_maps=1, realisations=1, disturbances=(DisturbanceSpec(level=10.0),))
    run_study(STUDY, cfg, tmp_path, workers=0, progress=False)
    store = RunStore(tmp_path)
    ep = store.table("episodes")
    assert set(ep["family"]) == {"corridor", "occupancy"}
    from studies.arena.episodes import arena_map

    r = ep[ep["family"] == "corridor"].iloc[0]
    m = arena_map(MapFamily("corridor", moving=2, speed=1.0), int(r["map_seed"]))
    X = store.arrays(r["task_id"])["X"]
    at = m.moving_scene(0.02)
    for k in range(len(X)):  # the path never enters a circle of the scene of its time
        h = min(float(np.sum((X[k, :2] - np.array(c.center)) ** 2) - c.radius ** 2)
                for c in at(k))
        assert h > 0 or (bool(r["crashed"]) and k == len(X) - 1)
    assert at(10) != at(0)

"""The sampling-safety study: config errors name the field, every method runs on the common
random numbers of its realisation, the summary has the fields a reader needs and its numbers
are the tidy data's, and the claim table is printed."""

from __future__ import annotations

import json

import casadi as ca
import numpy as np
import pytest

from studies.navigation.scene import MapSpec
from studies.sampling_safety import STUDY
from studies.sampling_safety.findings import verdicts
from studies.sampling_safety.summary import mean_interval
from studies.sampling_safety.tasks import setup
from workbench.scenarios.methods import names
from workbench.study import Rate, RunStore
from workbench.study.runner import profile_config, resolve_config
from workbench.study.runner import run as run_study

CELL_FIELDS = {"controller", "variance", "safety", "ci_low", "ci_high", "n", "mean_step_ms",
               "collision_free_sample_fraction", "ess_mean"}


def tiny(**overrides):
    return profile_config(STUDY, "tiny", **overrides)


@pytest.mark.parametrize("overrides, field", [
    ({"controllers": ("bas_mppi", "lqr")}, "controllers"),
    ({"controllers": ()}, "controllers"),
    ({"variances": (-1.0,)}, r"variances\[0\]"),
    ({"realisations": 0}, "realisations"),
    ({"steps": 0}, "steps"),
    ({"scene": MapSpec(goal=(6.4, 5.2))}, r"scene\.goal"),
    ({"methods": "fast"}, "methods"),
])
def test_bad_config_names_the_field(overrides, field):
    with pytest.raises(ValueError, match=rf"^{field}"):
        tiny(**overrides)


def test_profiles_cover_every_method():
    for profile in ("tiny", "quick", "paper"):
        assert resolve_config(STUDY, profile).controllers == names()
    assert len(names()) >= 7


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("sampling_safety")
    cfg = tiny()
    return cfg, out, run_study(STUDY, cfg, out, workers=0, progress=False)


def test_every_method_meets_the_same_disturbances(tiny_run):
    """w_k = x_{k+1} - F(x_k, u_k) from every stored path is one sequence per realisation."""
    cfg, out, _ = tiny_run
    store, plant = RunStore(out), setup(cfg.resolved()).plant
    f = ca.Function("f", [plant.x, plant.u], [plant.x_next])
    ep = store.table("episodes")
    seqs: dict[int, list[np.ndarray]] = {}
    for tid, j in zip(ep["task_id"], ep["realisation"], strict=True):
        a = store.arrays(tid)
        X, U = a["X"], a["U"]
        seqs.setdefault(int(j), []).append(
            np.array([X[k + 1] - np.asarray(f(X[k], U[k])).ravel() for k in range(len(U))]))
    for ws in seqs.values():
        assert len(ws) == len(cfg.controllers)
        n = min(len(w) for w in ws)
        for w in ws[1:]:
            np.testing.assert_allclose(w[:n], ws[0][:n], rtol=0, atol=1e-12)
    assert not np.allclose(seqs[0][0][:3], seqs[1][0][:3])


def test_summary_fields_and_numbers_are_the_data(tiny_run):
    _cfg, out, outcome = tiny_run
    store = RunStore(out)
    ep, timing = store.table("episodes"), store.table("timing")
    data = json.loads((out / "summary.json").read_text())
    cells = data["cells"]
    assert len({c["controller"] for c in cells}) == len(names())
    for c in cells:
        assert CELL_FIELDS <= set(c)
        rows = ep[(ep["controller"] == c["controller"]) & (ep["variance"] == c["variance"])]
        rate = Rate.of(~rows["crashed"].to_numpy(bool))
        assert (c["n"], c["safety"], c["ci_low"], c["ci_high"]) == (
            rate.n, rate.value, rate.low, rate.high)
        cf = mean_interval(rows["collision_free_fraction"], 0.0, 1.0)
        assert c["collision_free_sample_fraction"] == pytest.approx(cf[0], rel=1e-12)
        assert 0.0 <= c["collision_free_sample_fraction"] <= 1.0
        assert c["ess_mean"] == pytest.approx(rows["ess_mean"].mean(), rel=1e-12)
        t = timing[timing["task_id"].isin(rows["task_id"])]
        assert c["mean_step_ms"] == pytest.approx(t["mean_step_ms"].mean(), rel=1e-12)
    # every method reports its mechanism's activity (a method that never acts shows 0)
    act = {c["controller"]: c["activity"] for c in cells}
    assert "projected" in act["cbf_projection"] and "shield_acted" in act["shield_mppi"]
    assert "backup_used" in act["gatekeeper"] and "nominal_reset" in act["tube_mppi"]
    assert "al_active" in act["sais_al"] and "ecbf_active" in act["sais_ecbf"]
    text = outcome.report.read_text()
    for v in verdicts(outcome.summary.value):
        assert v.claim in text
    assert (out / "frontier.png").stat().st_size > 10_000
    assert "SPEC" not in text

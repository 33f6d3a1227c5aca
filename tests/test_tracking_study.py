"""The tracking comparison study: config validation, statistics, seeding, the vectorised
rollouts against the CasADi model, and a small end-to-end run (resume, worker count)."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from scipy.stats import binomtest

from studies.tracking_comparison.config import StudyConfig, Variant
from studies.tracking_comparison.methods import Setup, solve_nominal
from studies.tracking_comparison.report import write_report
from studies.tracking_comparison.rollouts import (
    LinearDynamics,
    ecbf_rollouts,
    feedback_rollouts,
    lift_function,
    noise_generator,
)
from studies.tracking_comparison.run import run
from workbench.barrier import BarrierOptions, embed_barrier
from workbench.ecbf import ECBFFilter
from workbench.problem import Problem
from workbench.stats import wilson_interval
from workbench.tracking import tracking_problem

TINY = dict(n_rollouts=6, n_seeds=2, sweep_rollouts=4, sweep_seeds=1, sweep_q_beta=(1e-2, 1.0),
            sweep_pole=(5.0,), sweep_q_scale=(1.0,), sweep_ecbf_noise=("before",), workers=1)


@pytest.mark.parametrize("overrides, field", [
    ({"methods": ("ecbf", "mpc")}, "methods"),
    ({"methods": ()}, "methods"),
    ({"noise_std": -1.0}, "noise_std"),
    ({"n_rollouts": 0}, "n_rollouts"),
    ({"n_seeds": 0}, "n_seeds"),
    ({"workers": 0}, "workers"),
    ({"target_radius": 0.0}, "target_radius"),
    ({"sweep_pole": (5.0, -2.0)}, "sweep_pole"),
    ({"sweep_ecbf_noise": ("during",)}, "sweep_ecbf_noise"),
])
def test_bad_config_fails_at_construction_naming_the_field(overrides, field):
    with pytest.raises(ValueError, match=rf"^{field}"):
        StudyConfig.for_profile("quick", **overrides)


def test_bad_profile_and_variant_name_the_field():
    with pytest.raises(ValueError, match=r"^profile"):
        StudyConfig.for_profile("huge")
    with pytest.raises(ValueError, match=r"^ecbf_noise"):
        Variant(ecbf_noise="sometimes")
    cfg = StudyConfig.for_profile("quick", methods=("bas", "ecbf"))
    assert cfg.methods == ("ecbf", "bas") and cfg.n_rollouts == 100
    assert StudyConfig.for_profile("full").n_rollouts * StudyConfig().n_seeds == 5000


@pytest.mark.parametrize("k, n", [(0, 500), (1, 500), (135, 500), (300, 500), (500, 500),
                                  (3, 7), (1, 1)])
def test_wilson_interval_matches_scipy(k, n):
    ref = binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
    lo, hi = wilson_interval(k, n)
    assert lo == pytest.approx(ref.low, abs=1e-12)
    assert hi == pytest.approx(ref.high, abs=1e-12)


def test_wilson_interval_known_value_and_validation():
    # 27 of 100, by hand: centre (0.27 + z^2/200) / (1 + z^2/100) = 0.278509, half-width
    # z / (1 + z^2/100) * sqrt(0.27 * 0.73 / 100 + z^2 / 40000) = 0.085813
    lo, hi = wilson_interval(27, 100)
    assert (round(lo, 4), round(hi, 4)) == (0.1927, 0.3643)
    with pytest.raises(ValueError, match=r"successes"):
        wilson_interval(11, 10)


def test_noise_generators_are_per_method_and_seed():
    a = noise_generator(7, "bas", 3).standard_normal(5)
    np.testing.assert_array_equal(a, noise_generator(7, "bas", 3).standard_normal(5))
    # the same stream as SeedSequence(7).spawn(3)[2].spawn(4)[3], whatever else was drawn
    direct = np.random.default_rng(np.random.SeedSequence(7, spawn_key=(2, 3)))
    np.testing.assert_array_equal(a, direct.standard_normal(5))
    others = [noise_generator(7, m, s).standard_normal(5)
              for m, s in (("bas", 2), ("al", 3), ("ecbf", 3))] + [
        noise_generator(8, "bas", 3).standard_normal(5)]
    assert all(not np.allclose(a, o) for o in others)


@pytest.fixture(scope="module")
def setup_and_nominals():
    """Nominals of the study's setup, except a relaxed barrier (gamma = 0.5) so that the BaS
    gains on the barrier state are not zero and the actual beta matters in the feedback."""
    setup = Setup(barrier=BarrierOptions(gamma=0.5))
    return setup, {m: solve_nominal(m, Variant(), setup) for m in ("ecbf", "al", "bas")}


def test_numpy_rollouts_equal_the_casadi_model(setup_and_nominals, rng):
    """Vectorised NumPy closed loops (AL, BaS with the actual barrier state) against a step-by-
    step loop through the CasADi model's own map (for BaS the embedded map, whose beta must stay
    equal to B(h(x)))."""
    setup, nominals = setup_and_nominals
    model = setup.model()
    dyn = LinearDynamics.from_model(model)
    x0 = np.array(setup.scene.start)
    noise = 10 * rng.standard_normal((3, setup.scene.horizon, 2))
    embedded = embed_barrier(model, setup.barrier)
    assert np.max(np.abs(nominals["bas"].K[:, :, 4])) > 1e-6
    for method, m in (("al", model), ("bas", embedded)):
        nom = nominals[method]
        lift = lift_function(embedded) if method == "bas" else None
        X = feedback_rollouts(dyn, x0, nom.X, nom.U, nom.K, noise, model.u_min, model.u_max,
                              lift)
        F = Problem.build(m, tracking_problem(m).cost).functions["dyn"]
        for i in range(noise.shape[0]):
            x = m.lift(x0)
            for k in range(setup.scene.horizon):
                u = np.clip(nom.U[k] + nom.K[k] @ (x - nom.X[k]) + noise[i, k], -15, 15)
                x = np.asarray(F(x, u)).ravel()
                np.testing.assert_allclose(x[:4], X[i, k + 1], rtol=0, atol=1e-12)
                if method == "bas":
                    np.testing.assert_allclose(x[4], m.lift(X[i, k + 1])[4], rtol=1e-12)


def test_ecbf_rollouts_equal_a_stepwise_filter_loop(setup_and_nominals, rng):
    setup, nominals = setup_and_nominals
    model = setup.model()
    nom = nominals["ecbf"]
    noise = 10 * rng.standard_normal((4, setup.scene.horizon, 2))
    x0 = np.array(setup.scene.start)
    r = ecbf_rollouts(LinearDynamics.from_model(model), x0, nom.X, nom.U, nom.K, noise,
                      ECBFFilter(model, setup.ecbf))
    F = Problem.build(model, tracking_problem(model).cost).functions["dyn"]
    for i in range(noise.shape[0]):
        filt, x, infeasible = ECBFFilter(model, setup.ecbf), x0.copy(), 0
        for k in range(setup.scene.horizon):
            res = filt(x, nom.U[k] + nom.K[k] @ (x - nom.X[k]) + noise[i, k])
            infeasible += res.infeasible
            x = np.asarray(F(x, res.u)).ravel()
            np.testing.assert_allclose(x, r.X[i, k + 1], rtol=0, atol=1e-6)
        assert infeasible == r.infeasible_steps[i]
    assert r.qp_steps.sum() > 0


def test_study_smoke_run_writes_outputs_and_resumes(tmp_path):
    out = tmp_path / "tc"
    cfg = StudyConfig.for_profile("quick", **TINY)
    summary = run(cfg, out, progress=False)
    report = write_report(out)
    data = json.loads((out / "summary.json").read_text())
    for m in ("ecbf", "al", "bas"):
        s = data["methods"][m]
        for key in ("unsafe_rate", "unsafe_ci_low", "unsafe_ci_high", "failure_rate",
                    "failure_ci_low", "failure_ci_high", "n_rollouts", "mean_final_distance",
                    "infeasible_qp_steps"):
            assert key in s, (m, key)
        assert s["n_rollouts"] == 12
        assert s["unsafe_ci_low"] <= s["unsafe_rate"] <= s["unsafe_ci_high"]
        assert s["failure_rate"] >= s["unsafe_rate"]
    rows = pd.read_csv(out / "rollouts.csv")
    assert len(rows[rows["study"] == "main"]) == 3 * 12
    sweep = rows[rows["study"] == "sweep"]
    # the base point (3 methods) and q_beta = 1 (BaS only: it changes no other method's task)
    assert len(sweep) == 4 * 4 and set(sweep["q_beta"]) == {1e-2, 1.0}
    assert set(sweep.loc[sweep["q_beta"] == 1.0, "method"]) == {"bas"}
    assert {r["parameter"] for r in data["sweep"]} == {"q_beta", "pole", "q_scale",
                                                       "ecbf_noise"}
    for name in ("trajectories_ecbf.png", "trajectories_al.png", "trajectories_bas.png",
                 "min_h_hist.png", "final_distance_hist.png", "sweep.png"):
        assert (out / name).stat().st_size > 1000, name
    text = report.read_text()
    assert "27%" in text and "60%" in text and "Assumed" in text
    assert data["tasks"]["computed"] == data["tasks"]["total"] == 6 + 4

    again = run(cfg, out, progress=False)  # everything resumed from the task files
    assert again["tasks"]["computed"] == 0
    assert again["methods"] == summary["methods"]
    task_files = sorted((out / ".cache" / "tasks").glob("al-s1-*.npz"))
    task_files[0].unlink()  # an interrupted run lost one task; another one is corrupt
    sorted((out / ".cache" / "tasks").glob("bas-s0-*.npz"))[0].write_bytes(b"not a npz")
    third = run(cfg, out, progress=False)
    assert third["tasks"]["computed"] == 2
    assert third["methods"] == summary["methods"]


def test_results_do_not_depend_on_the_worker_count(tmp_path):
    base = dict(TINY, sweep=False, methods=("ecbf", "bas"))
    run(StudyConfig.for_profile("quick", **base), tmp_path / "one", progress=False)
    run(StudyConfig.for_profile("quick", **{**base, "workers": 2}), tmp_path / "two",
        progress=False)
    one = (tmp_path / "one" / "rollouts.csv").read_text()
    assert one == (tmp_path / "two" / "rollouts.csv").read_text()
    assert len(one.splitlines()) == 1 + 2 * 12

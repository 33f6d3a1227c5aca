"""The tracking comparison study: config validation, statistics, seeding, the vectorised
rollouts against the CasADi model, and small end-to-end runs on the study framework (report
numbers recomputed from the tidy data, claims, resume, in-process / 2 workers / Dask)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from scipy.stats import binomtest

from studies.tracking_comparison import STUDY
from studies.tracking_comparison.config import StudyConfig, Variant
from studies.tracking_comparison.findings import all_claims
from studies.tracking_comparison.methods import Setup, solve_nominal
from studies.tracking_comparison.rollouts import (
    LinearDynamics,
    ecbf_rollouts,
    feedback_rollouts,
    lift_function,
    noise_generator,
)
from studies.tracking_comparison.tasks import plan
from studies.tracking_comparison.wording import NAMES
from workbench.filters.ecbf import ECBFFilter
from workbench.ilqg.bas import tracking_problem
from workbench.problem.barrier import BarrierOptions, embed_barrier
from workbench.problem.problem import Problem
from workbench.study import Rate, RunStore, fmt_rate
from workbench.study.config_io import ConfigError
from workbench.study.runner import profile_config, resolve_config
from workbench.study.runner import run as run_study
from workbench.study.stats import wilson_interval


def run(cfg, out, **kw):
    return run_study(STUDY, cfg, out, **kw)


def quick(**overrides):
    return profile_config(STUDY, "quick", **overrides)

TINY = dict(n_rollouts=6, n_seeds=2, sweep_rollouts=4, sweep_seeds=1, sweep_q_beta=(1e-2, 1.0),
            sweep_pole=(5.0,), sweep_q_scale=(1.0,), sweep_ecbf_noise=("before", "after"),
            sweep_noise_std=(10.0,), radii=(0.3, 0.5, 1.0))


@pytest.mark.parametrize("overrides, field", [
    ({"methods": ("ecbf", "mpc")}, "methods"),
    ({"methods": ()}, "methods"),
    ({"radii": (0.5, -1.0)}, "radii"),
    ({"sweep_noise_std": (float("nan"),)}, "sweep_noise_std"),
    ({"n_rollouts": 0}, "n_rollouts"),
    ({"n_seeds": 0}, "n_seeds"),
    ({"target_radius": 0.0}, "target_radius"),
    ({"sweep_pole": (5.0, -2.0)}, "sweep_pole"),
    ({"sweep_ecbf_noise": ("during",)}, "sweep_ecbf_noise"),
])
def test_bad_config_fails_at_construction_naming_the_field(overrides, field):
    with pytest.raises(ValueError, match=rf"^{field}"):
        quick(**overrides)


def test_bad_profile_and_variant_name_the_field():
    with pytest.raises(ConfigError, match=r"^--profile 'huge' is invalid"):
        resolve_config(STUDY, "huge")
    with pytest.raises(ValueError, match=r"^ecbf_noise"):
        Variant(ecbf_noise="sometimes")
    with pytest.raises(ValueError, match=r"^noise_std"):
        Variant(noise_std=-1.0)
    cfg = quick(methods=("bas", "ecbf"))
    assert cfg.methods == ("ecbf", "bas") and cfg.n_rollouts == 100
    assert resolve_config(STUDY, "full").n_rollouts * StudyConfig().n_seeds == 5000


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
                x = np.asarray(F(x, u, m.scene_value)).ravel()
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
            x = np.asarray(F(x, res.u, model.scene_value)).ravel()
            np.testing.assert_allclose(x, r.X[i, k + 1], rtol=0, atol=1e-6)
        assert infeasible == r.infeasible_steps[i]
    assert r.qp_steps.sum() > 0


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A tiny run in this process (workers = 0), its config and outcome."""
    out = tmp_path_factory.mktemp("tc")
    cfg = quick(**TINY)
    return cfg, out, run(cfg, out, workers=0, progress=False)


def test_tiny_run_writes_the_tidy_data_figures_and_report(tiny_run):
    cfg, out, outcome = tiny_run
    rows = RunStore(out).table("rollouts")
    p = plan(cfg)
    # main: 3 methods x 2 seeds x 6; sweep: q_beta = 1 (BaS only), ECBF noise after (ECBF only),
    # the base point's 4-rollout batches (shared by every point that changes nothing)
    assert len(rows) == 3 * 12 + 3 * 4 + 4 + 4
    assert len(p.tasks) == 3 + 6 + 3 + 2 and outcome.run.computed == len(p.tasks)
    assert set(rows.loc[rows["q_beta"] == 1.0, "method"]) == {"bas"}
    assert set(rows.loc[rows["ecbf_noise"] == "after", "method"]) == {"ecbf"}
    for name in ("trajectories_ecbf.png", "trajectories_al.png", "trajectories_bas.png",
                 "min_h_hist.png", "final_distance_hist.png", "sweep.png", "radius.png"):
        assert (out / name).stat().st_size > 1000, name
    assert (out / "rollouts.csv").read_text().count("\n") == len(rows) + 1
    data = json.loads((out / "summary.json").read_text())
    assert {o["method"] for o in data["methods"]} == {"ecbf", "al", "bas"}
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["config"]["n_rollouts"] == 6 and manifest["git_revision"]


def test_report_gives_each_methods_online_step_tail(tiny_run):
    """One timing row per step of each method's nominal loop (the online control step), and
    the report's p50 / max per method from those rows."""
    _, out, outcome = tiny_run
    st = RunStore(out).table("step_times")
    text = outcome.report.read_text()
    assert "## What a step costs: CPU time and the wall-clock tail" in text
    for m in ("ecbf", "al", "bas"):
        w = st.loc[st["method"] == m, "wall_ms"].to_numpy()
        assert w.size == Setup().scene.horizon and (w > 0).all()
        row = next(ln for ln in text.splitlines() if ln.startswith(f"| {NAMES[m]} | ")
                   and ln.count("|") == 9)
        cells = [c.strip() for c in row.split("|")[1:-1]]
        assert cells[3] == f"{np.percentile(w, 50):.2f}" and cells[6] == f"{w.max():.2f}"
    ecbf, bas = (st.loc[st["method"] == m, "cpu_ms"].mean() for m in ("ecbf", "bas"))
    assert ecbf > bas  # the QP costs more than the affine law


def _independent_rates(cfg, out):
    """Unsafe and failure counts of the main rollouts, recomputed from the Parquet table."""
    rows = RunStore(out).table("rollouts")
    main = rows[(rows["n_rollouts"] == cfg.n_rollouts) & (rows["q_beta"] == cfg.base.q_beta)
                & (rows["ecbf_noise"] == "before") & (rows["noise_std"] == cfg.noise_std)]
    out_ = {}
    for m, g in main.groupby("method"):
        unsafe = g["min_h"].to_numpy() < 0
        radii = {r: int((unsafe | (g["final_distance"].to_numpy() > r)).sum())
                 for r in cfg.radii}
        out_[m] = (len(g), int(unsafe.sum()), radii)
    return out_


def test_report_numbers_are_the_data(tiny_run):
    """Every rate in the headline table and the radius table equals the rate recomputed here
    from the tidy data; each method shows both unsafe and failure."""
    cfg, out, outcome = tiny_run
    text = outcome.report.read_text()
    for m, (n, k_unsafe, radii) in _independent_rates(cfg, out).items():
        assert n == cfg.n_seeds * cfg.n_rollouts
        line = next(ln for ln in text.splitlines() if ln.startswith(f"| {NAMES[m]} | "))
        cells = line.split(" | ")
        assert cells[1] == fmt_rate(Rate(k_unsafe, n))
        assert cells[3] == fmt_rate(Rate(radii[cfg.target_radius], n))
        for r, k in radii.items():
            row = next(ln for ln in text.splitlines() if ln.startswith(f"| {r:g} | "))
            assert fmt_rate(Rate(k, n)) in row, (m, r)
    assert re.search(r"\| AL-iLQG \| .* \| 60% \| .* \| not given \|", text)


def test_report_prints_exactly_the_claims_that_hold(tiny_run):
    outcome = tiny_run[2]
    text = outcome.report.read_text()
    claims = [c for cs in all_claims(outcome.summary.value).values() for c in cs]
    assert any(c.holds for c in claims) and any(not c.holds for c in claims)
    for c in claims:
        assert (f"- {c.text}" in text) == c.holds, c.text
    # mutually exclusive alternatives: exactly one ranking sentence is printed
    ranking = [c for c in all_claims(outcome.summary.value)["ranking"][:3] if c.holds]
    assert len(ranking) == 1


def test_rerun_resumes_and_recomputes_only_lost_tasks(tiny_run, tmp_path):
    cfg, out, first = tiny_run
    again = run(cfg, out, workers=0, progress=False)
    assert again.run.computed == 0 and again.summary == first.summary
    tasks = sorted((out / "tasks").glob("*.npz"))
    tasks[0].unlink()  # a task lost; another one corrupt
    tasks[1].write_bytes(b"not a npz")
    parquet = (out / "rollouts.parquet").read_bytes()
    third = run(cfg, out, workers=0, progress=False)
    assert third.run.computed == 2 and third.summary == first.summary
    assert (out / "rollouts.parquet").read_bytes() == parquet


def test_same_bytes_in_process_with_two_workers_and_on_a_dask_cluster(tiny_run, tmp_path):
    from distributed import LocalCluster

    cfg, out, _ = tiny_run
    run(cfg, tmp_path / "two", workers=2, progress=False)
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, protocol="tcp",
                      host="127.0.0.1", dashboard_address=None) as cluster:
        run(cfg, tmp_path / "dask", scheduler=cluster.scheduler_address, progress=False)
    for name in ("rollouts.parquet", "rollouts.csv", "summary.json"):
        ref = (out / name).read_bytes()
        assert (tmp_path / "two" / name).read_bytes() == ref, name
        assert (tmp_path / "dask" / name).read_bytes() == ref, name


def test_sigint_during_ecbf_tasks_then_rerun_equals_an_uninterrupted_run(tmp_path):
    """A real SIGINT while ECBF tasks run in the study's own process (where
    the QP solver may swallow the interrupt) stops the run within seconds; the rerun gives the
    same bytes as an uninterrupted run, so no silently altered task was recorded."""
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    overrides = dict(methods=("ecbf",), n_rollouts=40, n_seeds=4, sweep=False, radii=(0.5,))
    cfg = quick(**overrides)
    run(cfg, tmp_path / "ref", workers=0, progress=False)
    out = tmp_path / "run"
    code = ("import sys; from pathlib import Path\n"
            "from studies.tracking_comparison import STUDY\n"
            "from workbench.study import StudyInterrupted\n"
            "from workbench.study.runner import profile_config, run\n"
            f"cfg = profile_config(STUDY, 'quick', **{overrides!r})\n"
            f"try:\n    run(STUDY, cfg, Path({str(out)!r}), workers=0, progress=False)\n"
            "except StudyInterrupted:\n    sys.exit(130)\n")
    proc = subprocess.Popen([sys.executable, "-c", code], stderr=subprocess.PIPE,
                            cwd=Path(__file__).parents[2])
    t_end = time.monotonic() + 60
    while len(list((out / "tasks").glob("*.npz")) if (out / "tasks").exists() else []) < 2:
        assert time.monotonic() < t_end and proc.poll() is None
        time.sleep(0.01)
    time.sleep(0.05)  # inside the next ECBF batch
    t0 = time.monotonic()
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 130, err.decode()
    assert time.monotonic() - t0 < 3.0
    done = len(list((out / "tasks").glob("*.npz")))
    rerun = run(cfg, out, workers=0, progress=False)
    assert rerun.run.loaded == done and rerun.run.computed == 5 - done
    for name in ("rollouts.parquet", "summary.json"):
        assert (out / name).read_bytes() == (tmp_path / "ref" / name).read_bytes(), name

"""The navigation study: config validation naming the field, common random numbers
across controllers, report numbers recomputed from the tidy data, and the tiny profile on the
study framework (interrupt + resume, 1 / 2 workers / Dask byte-identical tidy data)."""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
import time
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from studies.navigation import STUDY
from studies.navigation.findings import all_claims
from studies.navigation.scene import MapSpec
from studies.navigation.tasks import Controllers, setup
from workbench.study import Rate, RunStore, fmt_rate
from workbench.study.config_io import ConfigError
from workbench.study.runner import declare, profile_config, resolve_config
from workbench.study.runner import run as run_study


def run(cfg, out, **kw):
    return run_study(STUDY, cfg, out, **kw)


def tiny(**overrides):
    return profile_config(STUDY, "tiny", **overrides)

TABLES = ("episodes.parquet", "episodes.csv", "velocity.parquet", "velocity.csv")


@pytest.mark.parametrize("overrides, field", [
    ({"controllers": ("bas_mppi", "lqr")}, "controllers"),
    ({"controllers": ()}, "controllers"),
    ({"variances": (0.0, -5.0)}, r"variances\[1\]"),
    ({"sweep_variances": (float("nan"),)}, r"sweep_variances\[0\]"),
    ({"realisations": 0}, "realisations"),
    ({"steps": 0}, "steps"),
    ({"sweep_controller": "bas_mppi"}, "sweep_controller"),
    ({"scene": MapSpec(start=(3.6, 5.0))}, r"scene\.start"),  # inside the left gate circle
    ({"scene": MapSpec(goal=(6.4, 5.2))}, r"scene\.goal"),  # inside the right gate circle
    ({"scene": MapSpec(circles=((9.0, 9.0, 1.0),))}, r"scene\.goal"),
])
def test_bad_config_fails_at_start_naming_the_field(overrides, field):
    with pytest.raises(ValueError, match=rf"^{field}"):
        tiny(**overrides)


def test_bad_map_values_and_profile_name_the_field():
    with pytest.raises(ValueError, match=r"^scene\.circles\[0\]"):
        MapSpec(circles=((1.0, 1.0, -0.5),))
    with pytest.raises(ConfigError, match=r"^--profile 'huge' is invalid"):
        resolve_config(STUDY, "huge")
    cfg = resolve_config(STUDY, "quick")
    assert cfg.variances == (0.0, 10.0, 100.0) and cfg.realisations == 20
    assert resolve_config(STUDY, "paper").realisations == 100


def test_streams_are_keyed_by_variance_and_realisation_only():
    cfg = tiny()
    decl, p = declare(STUDY, cfg)
    keys: dict = {}
    for t in p.tasks:
        keys.setdefault((t.variance, t.realisation), set()).add(decl.context(t).key)
    assert all(len(k) == 1 for k in keys.values())  # one stream per realisation
    assert len({next(iter(k)) for k in keys.values()}) == len(keys)  # distinct realisations


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("nav")
    cfg = tiny()
    return cfg, out, run(cfg, out, workers=0, progress=False)  # later runs reuse its set-up


def test_common_random_numbers_same_disturbance_for_every_controller(tiny_run):
    """The plant disturbance w_k = x_{k+1} - F(x_k, u_k), recovered from every stored
    trajectory, is the same sequence for every controller and alpha rule of realisation j."""
    cfg, out, _ = tiny_run
    store, plant = RunStore(out), setup(Controllers.of(cfg)).plant
    f = ca.Function("f", [plant.x, plant.u], [plant.x_next])
    ep = store.table("episodes")
    seqs: dict[int, list[np.ndarray]] = {}
    for tid, j in zip(ep["task_id"], ep["realisation"], strict=True):
        a = store.arrays(tid)
        X, U = a["X"], a["U"]
        w = np.array([X[k + 1] - np.asarray(f(X[k], U[k])).ravel() for k in range(len(U))])
        np.testing.assert_allclose(w[:, :2], 0.0, atol=1e-12)  # velocity disturbance only
        seqs.setdefault(int(j), []).append(w[:, 2:])
    assert len(seqs) == cfg.realisations
    for ws in seqs.values():
        assert len(ws) == len(cfg.controllers) + len(cfg.sweep_rules)
        n = min(len(w) for w in ws)
        for w in ws[1:]:
            np.testing.assert_allclose(w[:n], ws[0][:n], rtol=0, atol=1e-12)
    assert not np.allclose(seqs[0][0][:5], seqs[1][0][:5])  # realisations differ
    assert np.std(seqs[0][0]) == pytest.approx(plant.dt * math.sqrt(50.0), rel=0.5)


def test_report_numbers_are_the_data(tiny_run):
    _cfg, out, outcome = tiny_run
    ep = RunStore(out).table("episodes")
    cells = json.loads((out / "summary.json").read_text())["cells"]
    assert {"controller", "variance", "safety", "ci_low", "ci_high", "rmse", "n", "rule",
            "mean_step_ms", "nominal_differs_fraction", "ksafe_fallback_rate"} <= set(cells[0])
    text = outcome.report.read_text()
    for c in cells:
        rows = ep[(ep["controller"] == c["controller"]) & (ep["rule"] == c["rule"])
                  & (ep["variance"] == c["variance"])]
        safe = ~rows["crashed"].to_numpy(bool)
        rate = Rate.of(safe)
        assert (c["n"], c["safety"], c["ci_low"]) == (rate.n, rate.value, rate.low)
        err = rows["final_error"].to_numpy()[safe]
        rmse = math.sqrt(np.mean(err ** 2)) if err.size else math.nan
        assert c["rmse"] == pytest.approx(rmse, rel=1e-12, nan_ok=True)
        differs = rows["nominal_differs_steps"].sum() / rows["steps"].sum()
        assert c["nominal_differs_fraction"] == pytest.approx(differs)
    line = next(ln for ln in text.splitlines() if ln.startswith("| 50 | "))
    sa = next(c for c in cells if c["controller"] == "sa_rmppi" and c["main"])
    assert fmt_rate(Rate(sa["safe"]["k"], sa["n"]), 0) in line
    assert f"{sa['rmse']:.4f}" in line or math.isnan(sa["rmse"])
    claims = all_claims(outcome.summary.value)
    # the tiny profile's 20-step episodes are not the paper's set-up: no Table I comparison
    assert "Custom run: not comparable with the paper's Table I" in text
    assert "## Table I beside ours" not in text
    for claim in claims.pop("magnitude"):
        assert claim.text not in text
    for cs in claims.values():  # every other claim of the paper is printed
        for claim in cs:
            assert f"- {claim.text}" in text


def _strip_timing(path: Path) -> dict:
    data = json.loads(path.read_text())
    for c in data["cells"]:
        del c["mean_step_ms"], c["median_step_ms"], c["cpu_ms"]
    return data


def test_same_bytes_with_two_workers_and_on_a_dask_cluster(tiny_run, tmp_path):
    from distributed import LocalCluster

    cfg, out, _ = tiny_run
    run(cfg, tmp_path / "two", workers=2, progress=False)
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, protocol="tcp",
                      host="127.0.0.1", dashboard_address=None) as cluster:
        run(cfg, tmp_path / "dask", scheduler=cluster.scheduler_address, progress=False)
    for other in ("two", "dask"):
        for name in TABLES:
            assert (tmp_path / other / name).read_bytes() == (out / name).read_bytes(), name
        assert _strip_timing(tmp_path / other / "summary.json") == _strip_timing(
            out / "summary.json")


def test_interrupt_then_rerun_equals_an_uninterrupted_run(tiny_run, tmp_path):
    cfg, ref, _ = tiny_run
    out = tmp_path / "run"
    code = ("import sys; from pathlib import Path\n"
            "from studies.navigation import STUDY\n"
            "from workbench.study import StudyInterrupted\n"
            "from workbench.study.runner import profile_config, run\n"
            "try:\n    run(STUDY, profile_config(STUDY, 'tiny'), Path(sys.argv[1]), workers=1, "
            "progress=False)\nexcept StudyInterrupted:\n    sys.exit(130)\n")
    proc = subprocess.Popen([sys.executable, "-c", code, str(out)], stderr=subprocess.PIPE,
                            cwd=Path(__file__).parents[2])
    t_end = time.monotonic() + 90
    while len(list(out.glob("tasks/*.npz"))) < 3:
        assert time.monotonic() < t_end and proc.poll() is None
        time.sleep(0.02)
    t0 = time.monotonic()
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 130, err.decode()
    assert time.monotonic() - t0 < 5.0
    done = len(list(out.glob("tasks/*.npz")))
    rerun = run(cfg, out, workers=0, progress=False)
    assert rerun.run.loaded == done and rerun.run.computed == rerun.run.n_tasks - done > 0
    for name in TABLES:
        assert (out / name).read_bytes() == (ref / name).read_bytes(), name
    again = run(cfg, out, workers=0, progress=False)  # complete: nothing recomputed
    assert again.run.computed == 0


def test_fig4_illustration_task_runs_and_keeps_both_sample_sets():
    """The Fig. 4 task (limits +-50, velocity variance 5000) on a few steps: it ran in no
    other test (the tiny profile skips it) and broke once on an API change."""
    from dataclasses import replace

    from studies.navigation.tasks import Illustration, prepare, run_task
    from workbench.sampling.threshold import AlphaRule
    from workbench.study import TaskContext

    rule = AlphaRule(kappa=0.1, calibration_steps=30)
    config = replace(tiny(rule=rule), illustration=True, illustration_steps=8)
    task = Illustration(rule, steps=8)
    out = run_task(task, TaskContext("fig4", 1, (7,), 1), config, prepare(config))
    assert out.arrays["path"].shape[1] == 2 and len(out.arrays["path"]) >= 2
    assert np.all(np.isfinite(out.arrays["path"]))
    assert len(out.arrays) >= 3  # the path, the nominal path and the rolled-out samples

"""The free-energy bound study on its tiny profile: runs end to end, every
summary number recomputed here from the tidy per-step table, the table's checks recomputed from
its own estimator columns, claims printed iff they hold, resume, bad config fails at start."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from studies.free_energy_bound import STUDY
from studies.free_energy_bound.config import TESTS
from workbench.cli import main
from workbench.study.config_io import ConfigError
from workbench.study.runner import profile_config, resolve_config
from workbench.study.runner import run as run_study
from workbench.study.stats import wilson_interval


def run(cfg, out, **kw):
    return run_study(STUDY, cfg, out, **kw)

# kappa = 0: alpha is the undisturbed free energy itself, so the nominal state differs on some
# of the few steps and R > 0 (with the default 0.1 the tiny episodes never leave the real state)
TINY = dict(kappa=0.0, steps=10)
STRATA = {"all": None, "all_real_safe": ("all_real_safe", True),
          "some_real_crashed": ("all_real_safe", False), "admissible": ("fallback_used", False),
          "fallback": ("fallback_used", True), "nominal_differs": ("nominal_differs", True),
          "nominal_is_real": ("nominal_differs", False)}


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    out = tmp_path_factory.mktemp("bound_tiny")
    cfg = profile_config(STUDY, "tiny", **TINY)
    outcome = run(cfg, out, workers=0, progress=False)
    return cfg, out, outcome


@pytest.mark.parametrize("overrides, field", [
    ({"variances": (0.0, -5.0)}, "variances"), ({"variances": ()}, "variances"),
    ({"episodes": 0}, "episodes"), ({"tests": ("T1", "T4")}, "tests"),
    ({"steps": 1}, "steps"), ({"kappa": float("nan")}, "kappa"), ({"n_q": "T+1"}, "n_q"),
    ({"space": "polar"}, "space"),
])
def test_bad_config_fails_at_construction_naming_the_field(overrides, field):
    with pytest.raises(ValueError, match=rf"^{field}"):
        profile_config(STUDY, "tiny", **overrides)
    with pytest.raises(ConfigError, match=r"^--profile 'huge' is invalid"):
        resolve_config(STUDY, "huge")


def test_bad_cli_value_fails_before_any_work(tmp_path, capsys):
    assert main(["run", "free-energy-bound", "--profile", "tiny", "--set", "episodes=0",
                 "--out", str(tmp_path / "x")]) == 2
    assert "episodes = 0 is invalid" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_tiny_runs_and_table_is_per_step(tiny):
    cfg, out, _ = tiny
    df = pd.read_parquet(out / "steps.parquet")
    ep = pd.read_parquet(out / "episodes.parquet")
    assert len(ep) == len(cfg.variances) * cfg.episodes
    assert len(df) == ep["n_steps"].sum()
    for _, g in df.groupby(["variance", "episode"]):
        assert list(g["step"]) == list(range(len(g)))
        last = g.iloc[-1]  # no t+1: the transition checks are not evaluated
        assert all(np.isnan(last[f"{t}_{c}_holds"]) for t in ("T3", "T3b", "T3c", "T3d")
                   for c in ("local", "global"))
    for t in TESTS:
        for c in ("local", "global"):
            assert set(np.unique(df[f"{t}_{c}_holds"].dropna())) <= {0.0, 1.0}
    assert df["nominal_differs"].any() and (df["R"] > 0).any(), "tiny run exercises no tube"
    for name in ("summary.json", "report.md", "slack_over_time.png", "rhs_local_vs_global.png",
                 "tube_radius.png", "steps.csv"):
        assert (out / name).stat().st_size > 0


def test_report_gives_the_controller_step_tail_per_variance(tiny):
    """One timing row per step of the controller alone (CPU <= wall on one thread), and the
    report's p50 / p95 / p99 / max per variance from those rows."""
    cfg, out, _ = tiny
    st = pd.read_parquet(out / "step_times.parquet")
    ep = pd.read_parquet(out / "episodes.parquet")
    assert len(st) == ep["n_steps"].sum() and (st["wall_ms"] > 0).all()
    text = (out / "report.md").read_text()
    assert "## What a step costs: CPU time and the wall-clock tail" in text
    for v in cfg.variances:
        w = st.loc[st["variance"] == v, "wall_ms"].to_numpy()
        row = next(line for line in text.splitlines()
                   if line.startswith(f"| SA-RMPPI, variance {v:g} |"))
        cells = [c.strip() for c in row.split("|")[1:-1]]
        assert cells[3] == f"{np.percentile(w, 50):.2f}" and cells[6] == f"{w.max():.2f}"
        assert cells[7] == str(w.size)


def test_checks_recomputed_from_the_table_columns(tiny):
    _, out, _ = tiny
    df = pd.read_parquet(out / "steps.parquet")
    for c in ("local", "global"):
        d = df[f"delta_{c}"]
        L_q, L_phi = (df["L_q"], df["L_phi"]) if c == "local" else (df["L_q_global"],
                                                                    df["L_phi_global"])
        np.testing.assert_allclose(d, (L_phi + df["n_q"] * L_q) * df["R"], rtol=1e-12)
        np.testing.assert_allclose(df[f"T2_{c}_rhs"], df["F_nom"] + d, rtol=1e-12)
        np.testing.assert_array_equal(df[f"T2_{c}_lhs"], df["F_real"])
        for t in TESTS:
            ok = df[f"{t}_{c}_holds"].notna()
            slack = df.loc[ok, f"{t}_{c}_rhs"] - df.loc[ok, f"{t}_{c}_lhs"]
            np.testing.assert_allclose(df.loc[ok, f"{t}_{c}_slack"], slack, rtol=1e-9, atol=1e-9)
            np.testing.assert_array_equal(df.loc[ok, f"{t}_{c}_holds"] == 1.0,
                                          df.loc[ok, f"{t}_{c}_lhs"] <= df.loc[ok, f"{t}_{c}_rhs"])
        for (_, _), g in df.groupby(["variance", "episode"]):
            g = g.reset_index(drop=True)
            dF = g["F_real"].shift(-1) - g["F_real"]
            ok = g[f"T3_{c}_holds"].notna()
            np.testing.assert_allclose(g.loc[ok, f"T3_{c}_lhs"], dF[ok], rtol=1e-12)
            E2 = 2 * np.maximum(g["E"], g["E"].shift(-1))
            rhs = g["alpha"] - g["F_nom"] + E2 + g[f"delta_{c}"] * g["D_F"]
            np.testing.assert_allclose(g.loc[ok, f"T3_{c}_rhs"], rhs[ok], rtol=1e-12)


def test_summary_rows_recomputed_from_the_table(tiny):
    cfg, out, _ = tiny
    df = pd.read_parquet(out / "steps.parquet")
    s = json.loads((out / "summary.json").read_text())
    seen = 0
    for r in s["rows"]:
        d = df[df["variance"] == r["variance"]]
        col, val = STRATA[r["stratum"]] or (None, None)
        if col:
            d = d[d[col] == val]
        p = f"{r['test']}_{r['constants']}_"
        d = d[d[p + "holds"].notna()]
        k = int((d[p + "holds"] == 1.0).sum())
        assert (r["n_steps"], r["n_holding"]) == (len(d), k)
        assert r["fraction_holding"] == pytest.approx(k / len(d))
        assert r["interval"] == pytest.approx(list(wilson_interval(k, len(d))))
        q = np.quantile(d[p + "slack"], [0.05, 0.5, 0.95])
        assert [r["slack_q05"], r["slack_q50"], r["slack_q95"]] == pytest.approx(list(q))
        loc, glo = d[f"{r['test']}_local_rhs"], d[f"{r['test']}_global_rhs"]
        ratio = (glo[loc > 0] / loc[loc > 0]).median() if (loc > 0).any() else np.nan
        # summary.json is strict JSON: a non-finite ratio is written as null
        got = np.nan if r["rhs_ratio"] is None else r["rhs_ratio"]
        assert got == pytest.approx(ratio, nan_ok=True)
        seen += 1
    n_tests = len(cfg.tests) * 3 * len(cfg.variances)  # local, global, sampled
    assert sum(r["stratum"] == "all" for r in s["rows"]) == n_tests and seen > n_tests
    for v in s["variances"]:
        d = df[df["variance"] == v["variance"]]
        assert v["n_steps"] == len(d)
        assert v["n_nominal_differs"] == int(d["nominal_differs"].sum())
        assert v["n_all_real_safe"] == int(d["all_real_safe"].sum())
        assert v["n_fallback"] == int(d["fallback_used"].sum())


def test_sampled_checks_and_tightness_recomputed_from_the_table(tiny):
    """The sampled-tube bound's columns (δ_λ <= max_n δ_n <= δ_local), its checks, the
    tightness rows (ratios over steps with R > 0 and LHS > 0), the comparisons' counts, and
    the report's opening (one sentence per test) and new outputs."""
    cfg, out, _ = tiny
    df = pd.read_parquet(out / "steps.parquet")
    tol = 1e-12
    assert np.all(df["delta_sampled"] <= df["delta_sampled_max"] * (1 + tol))
    assert np.all(df["delta_sampled_max"] <= df["delta_local"] * (1 + tol))
    assert np.all(df.loc[df["R"] == 0, "delta_sampled_max"] == 0.0)
    np.testing.assert_allclose(df["T2_sampled_rhs"], df["F_nom"] + df["delta_sampled"],
                               rtol=1e-12)
    np.testing.assert_allclose(df["T1_sampled_rhs"], df["delta_sampled_max"], rtol=1e-12)
    assert np.all(np.isfinite(df["clearance"]))
    s = json.loads((out / "summary.json").read_text())
    assert len(s["tightness"]) == len(cfg.tests) * 3 * (len(cfg.variances) + 1)
    for r in s["tightness"]:
        d = df if r["variance"] is None else df[df["variance"] == r["variance"]]
        p = f"{r['test']}_{r['constants']}_"
        d = d[(d["R"] > 0) & d[p + "lhs"].notna() & d[p + "rhs"].notna()]
        lhs, rhs = d[p + "lhs"].to_numpy(), d[p + "rhs"].to_numpy()
        assert (r["n"], r["n_lhs_nonpositive"], r["n_holding"]) == (
            len(d), int(np.sum(lhs <= 0)), int(np.sum(lhs <= rhs)))
        ratio = rhs[lhs > 0] / lhs[lhs > 0]
        want = [np.quantile(ratio, q) for q in (0.05, 0.25, 0.5, 0.75, 0.95)] if ratio.size \
            else [None] * 5
        got = r["ratio_quantiles"]
        assert [np.nan if g is None else g for g in got] == pytest.approx(
            [np.nan if w is None else w for w in want], rel=1e-12, nan_ok=True)
        assert r["n_informative"] == [int(np.sum((ratio >= 1) & (ratio <= c)))
                                      for c in (2.0, 10.0, 100.0)]
    assert s["comparisons"], "no comparison on the tiny run"
    for c in s["comparisons"]:
        assert c["verdict"] in ("better", "worse", "equivalent", "undecided")
        assert c["low"] <= c["difference"] <= c["high"]
    report = (out / "report.md").read_text()
    opening = report.split("\n\n")[1].splitlines()
    assert [line.split("**")[1] for line in opening] == list(cfg.tests)
    for name in ("tightness.csv", "ratio_over_episode.png"):
        assert (out / name).stat().st_size > 0
    assert "Lemma 1' (the sampled-tube bound)" in report


def test_claims_printed_iff_they_hold(tiny):
    _, out, _ = tiny
    s = json.loads((out / "summary.json").read_text())
    report = (out / "report.md").read_text()
    claims = [c for cs in s["claims"].values() for c in cs]
    assert any(c["holds"] for c in claims) and any(not c["holds"] for c in claims)
    for c in claims:
        assert (c["text"] in report) == c["holds"], c["text"]
    assert "Lemma 1 as printed" in report and "(T-1)L_q" in report


def test_resume_computes_only_what_is_missing(tiny):
    cfg, out, _ = tiny
    before = (out / "summary.json").read_bytes()
    again = run(cfg, out, workers=0, progress=False)
    assert again.run.computed == 0 and (out / "summary.json").read_bytes() == before
    tasks = sorted((out / "tasks").glob("*.npz"))
    tasks[0].unlink()
    third = run(cfg, out, workers=0, progress=False)
    assert third.run.computed == 1 and (out / "summary.json").read_bytes() == before


def test_failures_are_classified_from_the_table():
    from studies.free_energy_bound.failures import TransitionFailures, t1_failures_when_safe

    base = {f"{t}_{c}_{p}": 1.0 for t in ("T1", "T1s", "T3") for c in ("local", "global")
            for p in ("holds", "slack", "lhs", "rhs")}
    rows = []
    for i, (secant_ok, crashed_nom, safe) in enumerate(
            [(False, 0, True), (True, 3, True), (True, 0, True), (True, 0, False)]):
        rows.append({**base, "T1_local_holds": 0.0, "T1_local_slack": -1.0, "variance": 10.0,
                     "episode": 0, "step": i, "all_real_safe": safe, "secant_ok": secant_ok,
                     "n_crashed_nom": crashed_nom, "R": 0.1, "L_q": 5.0, "secant_q": 6.0})
    df = pd.DataFrame(rows)
    got = [(f.step, f.cause) for f in t1_failures_when_safe(df)]
    # the step with a crashed real sample is not in the safe stratum
    assert got == [(0, "secant_exceeds"), (1, "nominal_crashed"), (2, "unexplained")]
    df = pd.DataFrame({"T3_local_holds": [0.0, 0.0, 1.0, np.nan], "step": [0, 1, 2, 3],
                       "nominal_admissible": [False, True, True, True],
                       "nominal_admissible_next": [True, True, True, False],
                       "fallback_used": [True, False, False, False],
                       "fallback_next": [False, False, False, False]})
    f = TransitionFailures.of(df, "T3", "local", 10.0)
    assert (f.n_evaluated, f.n_failed, f.n_premise_fails, f.n_fallback, f.n_first_step) == \
        (3, 2, 1, 1, 1)
    assert f.last_step == 1

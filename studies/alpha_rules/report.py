"""Summary table (Wilson intervals) and report of the alpha-rule activation study."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from studies.alpha_rules.run import DEFAULT_RULE, RULES
from workbench.study.io import atomic_write_json, atomic_write_text
from workbench.study.stats import mcnemar_exact, paired_difference_interval, wilson_interval


def summarise(df: pd.DataFrame) -> pd.DataFrame:
    rows = []
    for (ctrl, rule, var), g in df.groupby(["controller", "rule", "variance"], sort=False):
        n, crashes = len(g), int(g.crashed.sum())
        lo, hi = wilson_interval(crashes, n)
        steps = int(g.n_steps.sum())
        safe = g[~g.crashed]
        rows.append({
            "controller": ctrl, "rule": rule, "variance": var, "n": n,
            "crash_rate": crashes / n, "crash_ci_low": lo, "crash_ci_high": hi,
            "nominal_differs_fraction": g.nominal_differs.sum() / steps,
            "alpha_fallback_fraction": g.alpha_fallback.sum() / steps,
            "ksafe_fallback_rate": g.ksafe_fallback.sum() / steps,
            "ksafe_fallback_reasons": ",".join(sorted({r for s in g.ksafe_reasons for r in
                                                       s.split(",") if r})) or "-",
            "nominal_unsafe_fraction": g.nominal_unsafe.sum() / steps,
            "rmse_safe": float((safe.final_error ** 2).mean() ** 0.5) if len(safe) else None,
            "n_steps": steps, "mean_step_ms": float(g.step_ms.mean()),
        })
    return pd.DataFrame(rows)


def _fmt(x, p=3):
    return "-" if x is None or x != x else f"{x:.{p}f}"


def distinct_paths(df: pd.DataFrame, store) -> list[str]:
    """Per variance: on how many realisations SA-RMPPI (default rule), RMPPI and BaS-MPPI
    followed different trajectories (the robust machinery changed what the robot did)."""
    lines = []
    base = df[(df.rule == DEFAULT_RULE) | (df.controller == "bas_mppi")]
    for var, g in base.groupby("variance"):
        paths = {(r.controller, r.episode): store.arrays(r.task_id)["path"]
                 for r in g.itertuples()}
        n = g.episode.nunique()

        def differ(a, b, paths=paths, n=n):
            return sum(not np.array_equal(paths[(a, j)], paths[(b, j)])
                       for j in range(n) if (a, j) in paths and (b, j) in paths)

        lines.append(f"- variance {var:g}: SA-RMPPI ≠ BaS-MPPI on {differ('sa_rmppi', 'bas_mppi')}"
                     f" of {n}, SA-RMPPI ≠ RMPPI on {differ('sa_rmppi', 'rmppi')} of {n}, "
                     f"RMPPI ≠ BaS-MPPI on {differ('rmppi', 'bas_mppi')} of {n} realisations")
    return lines


def write_report(df: pd.DataFrame, out: Path, config: dict, store=None) -> None:
    out = Path(out)
    s = summarise(df)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out / "summary.json", {"config": config,
                                             "rules": {k: repr(v) for k, v in RULES.items()},
                                             "cells": s.to_dict(orient="records")})
    lines = ["# SA-RMPPI alpha rules: does the robust machinery act?", "",
             f"{config['episodes']} episodes per cell, {config['steps']} steps, seed "
             f"{config['seed']}, common random numbers across controllers; tidy data in "
             f"`episodes.parquet`, manifest in `manifest.json`; wall {config['wall_s']:.0f} s. "
             f"Default rule: `{DEFAULT_RULE}` = "
             f"{RULES[DEFAULT_RULE].label()}.", "",
             "| controller | rule | variance | n | crash rate [95% CI] | nominal ≠ real | "
             "alpha fallback | K_safe fallback (reasons) | nominal rollout unsafe | "
             "RMSE safe [m] | step [ms] |", "|" + "---|" * 11]
    for r in s.itertuples():
        lines.append(
            f"| {r.controller} | {r.rule} | {r.variance:g} | {r.n} | {_fmt(r.crash_rate, 2)} "
            f"[{_fmt(r.crash_ci_low, 2)}, {_fmt(r.crash_ci_high, 2)}] | "
            f"{_fmt(r.nominal_differs_fraction)} | {_fmt(r.alpha_fallback_fraction)} | "
            f"{_fmt(r.ksafe_fallback_rate, 4)} ({r.ksafe_fallback_reasons}) | "
            f"{_fmt(r.nominal_unsafe_fraction)} | {_fmt(r.rmse_safe)} | {r.mean_step_ms:.1f} |")
    lines += ["", "## Criterion for the default (issue 8, SPEC 10.3)", "",
              "A rule qualifies when the nominal state differs from the real state on 10–90% "
              "of steps at every variance >= 10, and K_safe falls back on < 1% of steps.", ""]
    for rule, g in s[s.controller == "sa_rmppi"].groupby("rule", sort=False):
        band = g[g.variance >= 10]
        ok = bool(((band.nominal_differs_fraction >= 0.1)
                   & (band.nominal_differs_fraction <= 0.9)).all()
                  and (g.ksafe_fallback_rate < 0.01).all())
        frac = ", ".join(f"{v:g}: {f:.2f}" for v, f in zip(band.variance,
                                                             band.nominal_differs_fraction,
                                                             strict=True))
        lines.append(f"- `{rule}`: {'qualifies' if ok else 'does not qualify'} "
                     f"(nominal ≠ real by variance: {frac})")
    lines += ["", "## Paired comparison with BaS-MPPI (same realisations)", "",
              "| rule | variance | both safe | only SA-RMPPI safe | only BaS-MPPI safe | both "
              "crashed | safety difference [95% CI] | exact McNemar p |", "|" + "---|" * 8]
    for (rule, var), g in df[df.controller == "sa_rmppi"].groupby(["rule", "variance"],
                                                                  sort=False):
        base = df[(df.controller == "bas_mppi") & (df.variance == var)]
        pair = g.merge(base, on="episode", suffixes=("", "_b"))
        sa, ba = ~pair.crashed.astype(bool), ~pair.crashed_b.astype(bool)
        a, b = int((sa & ba).sum()), int((sa & ~ba).sum())
        c, d = int((~sa & ba).sum()), int((~sa & ~ba).sum())
        diff, lo, hi = paired_difference_interval(a, b, c, d)
        lines.append(f"| {rule} | {var:g} | {a} | {b} | {c} | {d} | {diff:+.2f} "
                     f"[{lo:+.2f}, {hi:+.2f}] | {mcnemar_exact(b, c):.3f} |")
    if store is not None:
        lines += ["", "## Do the controllers act differently? (same realisations)", ""]
        lines += distinct_paths(df, store)
    lines += ["", "Rates of steps are pooled over all steps of all episodes of a cell. "
              "'nominal ≠ real': the nominal state after selection differs from the measured "
              "state. 'alpha fallback': no candidate was below alpha. 'K_safe fallback': the "
              "gains were the previous ones shifted (never zeros unless there were none). "
              "'nominal rollout unsafe': the nominal trajectory used for K_safe left the safe "
              "set; its gains come from the barrier's crash-safe evaluation."]
    atomic_write_text(out / "report.md", "\n".join(lines) + "\n")

"""Figures and report.md from a run's summary and tidy table (formatting only: numbers come from
the summary, sentences that interpret them from ``findings``)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from studies.free_energy_bound import tightness
from studies.free_energy_bound.findings import all_claims
from studies.free_energy_bound.paper import LEMMA, READING, VARIANT, assumed_values
from studies.free_energy_bound.summary import STRATA, BoundSummary, summarise
from workbench.study import md_table, png_bytes, supported, to_jsonable
from workbench.study.io import atomic_write_bytes, atomic_write_text
from workbench.study.latency import tail_lines
from workbench.study.report import num
from workbench.study.spec import Summary

TITLES = {"holds": "Where each test holds", "safe_steps": "T1 where all real samples stayed safe",
          "looseness": "How tight: magnitudes of the local and global constants",
          "transitions": "The T3 family: what the failures share",
          "strata": "Strata, variance and the secant check"}


def slack_figure(df: pd.DataFrame, tests=("T2", "T3", "T3b")) -> bytes:
    vs = sorted(df["variance"].unique())
    fig, axes = plt.subplots(len(tests), len(vs), figsize=(4 * len(vs), 2.6 * len(tests)),
                             squeeze=False, sharex=True)
    for i, t in enumerate(tests):
        for j, v in enumerate(vs):
            ax = axes[i][j]
            for e, g in df[df["variance"] == v].groupby("episode"):
                for c, ls in (("local", "-"), ("global", ":")):
                    ax.plot(g["step"], g[f"{t}_{c}_slack"], ls, lw=0.8,
                            label=f"ep {e} {c}" if i == j == 0 else None)
            ax.set_yscale("symlog", linthresh=1.0)
            lo, hi = ax.get_ylim()
            ax.set_yticks([t for t in (-1e4, -1e2, 0, 1e2, 1e4, 1e8, 1e12, 1e16)
                           if lo <= t <= hi])
            ax.axhline(0, color="k", lw=0.6)
            ax.set_title(f"{t} slack (RHS − LHS), variance {v:g}", fontsize=9)
            ax.set_ylabel("slack [cost units] (symlog)", fontsize=8)
            ax.set_xlabel("plant step (of 0.02 s)", fontsize=8)
    axes[0][0].legend(fontsize=6)
    return png_bytes(fig)


def rhs_figure(df: pd.DataFrame, test: str = "T2") -> bytes:
    fig, ax = plt.subplots(figsize=(5.5, 4.5))
    for v, g in df.groupby("variance"):
        ok = (g[f"{test}_local_rhs"] > 0) & (g[f"{test}_global_rhs"] > 0)
        ax.loglog(g.loc[ok, f"{test}_local_rhs"], g.loc[ok, f"{test}_global_rhs"], ".", ms=3,
                  label=f"variance {v:g}")
    lim = ax.get_xlim()
    ax.plot(lim, lim, "k--", lw=0.8, label="global = local")
    ax.set_xlabel(f"{test} right-hand side, local constants [cost units]")
    ax.set_ylabel(f"{test} right-hand side, global constants [cost units]")
    ax.legend(fontsize=7)
    return png_bytes(fig)


def radius_figure(df: pd.DataFrame) -> bytes:
    vs = sorted(df["variance"].unique())
    fig, ax = plt.subplots(figsize=(5.5, 4))
    data = [df.loc[(df["variance"] == v) & (df["R"] > 0), "R"].to_numpy() for v in vs]
    ax.boxplot([d if d.size else [np.nan] for d in data], tick_labels=[f"{v:g}" for v in vs])
    ax.plot(range(1, len(vs) + 1), [df.loc[(df["variance"] == v) & (df["R"] > 0), "R99"].median()
                                    for v in vs], "rs", label="median R99 (same steps)")
    ax.set_xlabel("velocity-disturbance variance [m²/s⁴]")
    ax.set_ylabel("tube radius R, norm of (p [m], v [m/s]) (steps with R > 0)", fontsize=8)
    ax.set_title("steps with R > 0: " + ", ".join(
        f"{(df.loc[df['variance'] == v, 'R'] > 0).sum()} of {(df['variance'] == v).sum()}"
        for v in vs), fontsize=8)
    ax.legend(fontsize=7)
    return png_bytes(fig)


NO_R = "no step with R > 0"
NO_RHS = "local right-hand side <= 0 at every step"
NO_TERM = "R = 0 at every step: no Lipschitz term"


def _pct(r) -> str:
    return "–" if r is None else (f"{100 * r.fraction_holding:.1f}% [{100 * r.interval[0]:.1f}, "
                                  f"{100 * r.interval[1]:.1f}] (n={r.n_steps})")


def _spread(x) -> str:
    if x.n == 0:
        return f"n/a ({NO_R})"
    return f"{num(x.median)} [{num(x.min)}, {num(x.max)}]"


def tables(s: BoundSummary) -> list[str]:
    tests = s.config["tests"]
    head = md_table(["variance", "episodes (crashed)", "steps", "nominal ≠ real", "all real safe",
                     "fallback", *(f"{t} local" for t in tests), "global/local L-term (T2)"],
                    [[f"{v.variance:g}", f"{v.n_episodes} ({v.n_crashed})", v.n_steps,
                      v.n_nominal_differs, v.n_all_real_safe, v.n_fallback,
                      *(_pct(s.row(t, "local", v.variance)) for t in tests),
                      num(s.row("T2", "local", v.variance).term_ratio, ".3g", NO_TERM)
                      if s.row("T2", "local", v.variance) else "–"] for v in s.variances])
    full = md_table(["variance", "test", "constants", "holds [95%]", "slack q05 / q50 / q95",
                     "global/local RHS", "global/local L-term"],
                    [[f"{r.variance:g}", r.test, r.constants, _pct(r),
                      f"{num(r.slack_q05)} / {num(r.slack_q50)} / {num(r.slack_q95)}",
                      num(r.rhs_ratio, ".3g", NO_RHS), num(r.term_ratio, ".3g", NO_TERM)]
                     for r in s.rows if r.stratum == "all"])
    strata = md_table(["variance", "test (local)", *STRATA],
                      [[f"{v.variance:g}", t, *(_pct(s.row(t, "local", v.variance, k))
                                                for k in STRATA)]
                       for v in s.variances for t in tests])
    mags = md_table(["variance", "R median (max)", "R99 median", "local L_q median [min, max]",
                     "local L_phi median", "global L_q", "global L_phi", "δ local median",
                     "Ê median", "D_F median"],
                    [[f"{v.variance:g}", f"{num(v.R.median)} ({num(v.R.max)})",
                      num(v.R99_median), _spread(v.L_q_local), num(v.L_phi_local.median, why=NO_R),
                      num(v.L_q_global), num(v.L_phi_global),
                      num(v.delta_local.median, why=NO_R), num(v.E_median), num(v.D_F_median)]
                     for v in s.variances])
    return ["## Headline (stratum: all steps)", "", *head, "",
            "## Every test, local and global constants", "", *full, "",
            "## Stratified (assumptions §11.3 (a), (b); nominal differs from real), local "
            "constants", "",
            *strata, "", "## Magnitudes", "", *mags, ""]


def step_cost(steps) -> list[str]:
    """The section on what a controller step costs (SA-RMPPI alone, the bound's evaluation
    left out), per variance; empty for runs stored before step times were kept."""
    lines = tail_lines(steps, ["variance"], label=lambda k: f"SA-RMPPI, variance {k[0]:g}")
    if lines:
        lines.insert(2, "Times of the controller's step alone; evaluating the bound's terms "
                        "after each step is not included.")
        lines.insert(3, "")
    return lines


def write_report(s: BoundSummary, df: pd.DataFrame, out: Path, assumed, no_barrier_L_q: float,
                 run_line: str, steps=None) -> Path:
    out = Path(out)
    for name, fig in (("slack_over_time.png", slack_figure(df)), ("rhs_local_vs_global.png",
                      rhs_figure(df)), ("tube_radius.png", radius_figure(df)),
                      ("ratio_over_episode.png", tightness.ratio_figure(df))):
        atomic_write_bytes(out / name, fig)
    atomic_write_text(out / "tightness.csv", tightness.csv(s))
    claims = all_claims(s, no_barrier_L_q)
    lines = ["# Free-energy bound (Lemma 1): numerical check on the navigation map", "",
             *tightness.opening(s), "", f"{run_line}", "",
             *tightness.tables(s),
             "![ratio over an episode next to the distance to the nearest obstacle]"
             "(ratio_over_episode.png)", "",
             "## A variant that informs: the sampled-tube bound", "", VARIANT, "",
             *(tightness.supported_variant(s) or ["- (no claim of this kind is supported)"]), "",
             "## Lemma 1 as printed", "", LEMMA, "", "## Reading used (assumptions §11, §13)", "",
             *(f"- {r}" for r in READING), "", "## Assumed values", "",
             *md_table(["what", "value", "source"],
                       [[a["name"], a["value"], a["source"]] for a in assumed]), "",
             *tables(s)]
    for key, title in TITLES.items():
        said = supported(claims[key])
        lines += [f"## {title}", "", *(said or ["- (no claim of this kind is supported)"]), ""]
    lines += step_cost(steps)
    lines += ["## Figures", "", "![slack over time](slack_over_time.png)", "",
              "![local vs global right-hand side](rhs_local_vs_global.png)", "",
              "![tube radius vs variance](tube_radius.png)", ""]
    path = out / "report.md"
    atomic_write_text(path, "\n".join(lines))
    return path


def summary(finished) -> Summary:
    """summary.json: the summary, the global constants, the assumed values and the claims."""
    shared = finished.prepared
    s = summarise(finished.config, finished.store.table("steps"),
                  finished.store.table("episodes"))
    claims = all_claims(s, shared.no_barrier.L_q)
    claims["variant"] = tightness.variant_claims(s)
    data = {**to_jsonable(s), "global_constant": to_jsonable(shared.global_),
            "no_barrier_constant": to_jsonable(shared.no_barrier),
            "assumed": assumed_values(finished.config, shared),
            "claims": {k: [to_jsonable(c) for c in v] for k, v in claims.items()}}
    return Summary(data, s)


def report(finished, summary) -> Path:
    """The framework's report step: figures and report.md from a finished run."""
    store = finished.store
    steps = (store.table("step_times") if (store.root / "step_times.parquet").exists()
             else None)
    return write_report(summary.value, store.table("steps"), finished.out,
                        summary.data["assumed"], finished.prepared.no_barrier.L_q,
                        finished.run_line, steps)

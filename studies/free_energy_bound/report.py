"""Figures and report.md from a run's summary and tidy table (formatting only: numbers come from
the summary, sentences that interpret them from ``findings``)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from studies.free_energy_bound.findings import all_claims
from studies.free_energy_bound.paper import LEMMA, READING
from studies.free_energy_bound.summary import STRATA, BoundSummary
from workbench.study import md_table, png_bytes, supported
from workbench.study.io import atomic_write_bytes, atomic_write_text

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
            ax.set_yticks([-1e4, -1e2, 0, 1e2, 1e4, 1e8, 1e12, 1e16])
            ax.axhline(0, color="k", lw=0.6)
            ax.set_title(f"{t} slack (RHS − LHS), variance {v:g}", fontsize=9)
    axes[-1][0].set_xlabel("step")
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
    ax.set_xlabel(f"{test} right-hand side, local constants")
    ax.set_ylabel(f"{test} right-hand side, global constants")
    ax.legend(fontsize=7)
    return png_bytes(fig)


def radius_figure(df: pd.DataFrame) -> bytes:
    vs = sorted(df["variance"].unique())
    fig, ax = plt.subplots(figsize=(5.5, 4))
    data = [df.loc[(df["variance"] == v) & (df["R"] > 0), "R"].to_numpy() for v in vs]
    ax.boxplot([d if d.size else [np.nan] for d in data], tick_labels=[f"{v:g}" for v in vs])
    ax.plot(range(1, len(vs) + 1), [df.loc[(df["variance"] == v) & (df["R"] > 0), "R99"].median()
                                    for v in vs], "rs", label="median R99 (same steps)")
    ax.set_xlabel("velocity variance")
    ax.set_ylabel("tube radius R (steps with R > 0)")
    ax.set_title("steps with R > 0: " + ", ".join(
        f"{(df.loc[df['variance'] == v, 'R'] > 0).sum()} of {(df['variance'] == v).sum()}"
        for v in vs), fontsize=8)
    ax.legend(fontsize=7)
    return png_bytes(fig)


def _pct(r) -> str:
    return "–" if r is None else (f"{100 * r.fraction_holding:.1f}% [{100 * r.interval[0]:.1f}, "
                                  f"{100 * r.interval[1]:.1f}] (n={r.n_steps})")


def tables(s: BoundSummary) -> list[str]:
    tests = s.config["tests"]
    head = md_table(["variance", "episodes (crashed)", "steps", "nominal ≠ real", "all real safe",
                     "fallback", *(f"{t} local" for t in tests), "global/local L-term (T2)"],
                    [[f"{v.variance:g}", f"{v.n_episodes} ({v.n_crashed})", v.n_steps,
                      v.n_nominal_differs, v.n_all_real_safe, v.n_fallback,
                      *(_pct(s.row(t, "local", v.variance)) for t in tests),
                      f"{s.row('T2', 'local', v.variance).term_ratio:.3g}"
                      if s.row("T2", "local", v.variance) else "–"] for v in s.variances])
    full = md_table(["variance", "test", "constants", "holds [95%]", "slack q05 / q50 / q95",
                     "global/local RHS", "global/local L-term"],
                    [[f"{r.variance:g}", r.test, r.constants, _pct(r),
                      f"{r.slack_q05:.3g} / {r.slack_q50:.3g} / {r.slack_q95:.3g}",
                      f"{r.rhs_ratio:.3g}", f"{r.term_ratio:.3g}"]
                     for r in s.rows if r.stratum == "all"])
    strata = md_table(["variance", "test (local)", *STRATA],
                      [[f"{v.variance:g}", t, *(_pct(s.row(t, "local", v.variance, k))
                                                for k in STRATA)]
                       for v in s.variances for t in tests])
    mags = md_table(["variance", "R median (max)", "R99 median", "local L_q median [min, max]",
                     "local L_phi median", "global L_q", "global L_phi", "δ local median",
                     "Ê median", "D_F median"],
                    [[f"{v.variance:g}", f"{v.R.median:.3g} ({v.R.max:.3g})",
                      f"{v.R99_median:.3g}", f"{v.L_q_local.median:.3g} [{v.L_q_local.min:.3g}, "
                      f"{v.L_q_local.max:.3g}]", f"{v.L_phi_local.median:.3g}",
                      f"{v.L_q_global:.3g}", f"{v.L_phi_global:.3g}",
                      f"{v.delta_local.median:.3g}", f"{v.E_median:.3g}", f"{v.D_F_median:.3g}"]
                     for v in s.variances])
    return ["## Headline (stratum: all steps)", "", *head, "",
            "## Every test, local and global constants", "", *full, "",
            "## Stratified (SPEC 11.3 (a), (b); nominal differs from real), local constants", "",
            *strata, "", "## Magnitudes", "", *mags, ""]


def write_report(s: BoundSummary, df: pd.DataFrame, out: Path, assumed, no_barrier_L_q: float,
                 run_line: str) -> Path:
    out = Path(out)
    for name, fig in (("slack_over_time.png", slack_figure(df)), ("rhs_local_vs_global.png",
                      rhs_figure(df)), ("tube_radius.png", radius_figure(df))):
        atomic_write_bytes(out / name, fig)
    claims = all_claims(s, no_barrier_L_q)
    lines = ["# Free-energy bound (Lemma 1): numerical check on the navigation map", "",
             f"{run_line}", "",
             "## Lemma 1 as printed", "", LEMMA, "", "## Reading used (SPEC 11, 13)", "",
             *(f"- {r}" for r in READING), "", "## Assumed values", "",
             *md_table(["what", "value", "source"],
                       [[a["name"], a["value"], a["source"]] for a in assumed]), "",
             *tables(s)]
    for key, title in TITLES.items():
        said = supported(claims[key])
        lines += [f"## {title}", "", *(said or ["- (no claim of this kind is supported)"]), ""]
    lines += ["## Figures", "", "![slack over time](slack_over_time.png)", "",
              "![local vs global right-hand side](rhs_local_vs_global.png)", "",
              "![tube radius vs variance](tube_radius.png)", ""]
    path = out / "report.md"
    atomic_write_text(path, "\n".join(lines))
    return path


def report(finished, summary) -> Path:
    """The framework's report step: figures and report.md from a finished run."""
    return write_report(summary.value, finished.store.table("steps"), finished.out,
                        summary.data["assumed"], finished.prepared.no_barrier.L_q,
                        finished.run_line)

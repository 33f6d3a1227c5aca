"""The report's tightness part: one opening sentence per test, the tightness and comparison
tables, the claims about the sampled-tube bound, and the figure of the ratio over an episode
next to the distance to the nearest obstacle (numbers from the summary and the tidy table)."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from studies.free_energy_bound.config import CONSTANTS
from studies.free_energy_bound.summary import MARGIN, THRESHOLD, BoundSummary, Decided, TightRow
from workbench.bound.tightness import QUANTILES, THRESHOLDS, ratios
from workbench.study import Claim, md_table, png_bytes, supported
from workbench.study.report import num

SIDE = {"T1": "the largest per-sample cost gap", "T1s": "that gap over the safe pairs",
        "T2": "F̂_real", "T2E": "F̂_real (against an independent batch)",
        "T3": "the free-energy growth", "T3b": "the free-energy growth",
        "T3c": "the free-energy growth", "T3d": "F̂_real(t+1)"}
HOLDS_AT_LEAST = 0.99  # the sampled-tube bound "holds" when on >= 99 % of informative steps


def _pct(x: float) -> str:
    return "n/a" if not np.isfinite(x) else f"{100 * x:.1f} %"


def _verdict(d: Decided | None, what: str) -> str:
    if d is None:
        return f"{what}: not compared (no informative step)"
    return (f"{what}: {d.verdict} (informative at {d.threshold:g}: {_pct(d.share_a)} against "
            f"{_pct(d.share_b)}, difference {100 * d.difference:+.1f} points "
            f"[{100 * d.low:+.1f}, {100 * d.high:+.1f}]; median right-hand side "
            f"{d.second}/{d.first} {num(d.rhs_ratio)} [{num(d.rhs_ratio_low)}, "
            f"{num(d.rhs_ratio_high)}])")


def _part(r: TightRow) -> str:
    return (f"holds on {_pct(r.n_holding / r.n)} of the {r.n} informative steps, its "
            f"right-hand side is typically {num(r.ratio_median)} times {SIDE[r.test]} "
            f"(median over the {r.n - r.n_lhs_nonpositive} steps where that is > 0), and it is "
            f"informative (within a factor {THRESHOLD:g}) on {_pct(r.share(THRESHOLD))}")


def opening(s: BoundSummary) -> list[str]:
    """One sentence per test, all variances pooled."""
    out = []
    for t in s.config["tests"]:
        loc, glo, smp = (s.tight(t, c) for c in CONSTANTS)
        if loc is None or loc.n == 0:
            out.append(f"- **{t}**: no informative step (R > 0 at no step where it was "
                       "evaluated), so its tightness is not measured.")
            continue
        out.append(f"- **{t}** with local constants {_part(loc)}; with global constants "
                   f"informative on {_pct(glo.share(THRESHOLD)) if glo else 'n/a'} — "
                   f"{_verdict(s.decided(t, 'local', 'global'), 'local against global')}. "
                   f"The sampled-tube bound {_part(smp)} — "
                   f"{_verdict(s.decided(t, 'sampled', 'local'), 'against the local form')}.")
    return out


def tables(s: BoundSummary) -> list[str]:
    def label(v: float) -> str:
        return 'all' if np.isnan(v) else f"{v:g}"

    tight = md_table(
        ["variance", "test", "constants", "informative steps", "LHS <= 0", "holds",
         "RHS/LHS q05 / q50 / q95", *(f"informative at {c:g} [95%]" for c in THRESHOLDS)],
        [[label(r.variance), r.test, r.constants, r.n, r.n_lhs_nonpositive,
          _pct(r.n_holding / r.n) if r.n else "n/a",
          " / ".join(num(r.ratio_quantiles[QUANTILES.index(q)]) for q in (0.05, 0.5, 0.95)),
          *(f"{_pct(r.share(c))} [{_pct(lo)}, {_pct(hi)}]"
            for c, (lo, hi) in zip(THRESHOLDS, r.informative_interval, strict=True))]
         for r in s.tightness])
    comp = md_table(
        ["test", "A", "B", "steps", f"A informative at {THRESHOLD:g}", "B informative",
         "A − B [interval]", "verdict", "median RHS_B / RHS_A [interval]"],
        [[d.test, d.first, d.second, d.n, _pct(d.share_a), _pct(d.share_b),
          f"{100 * d.difference:+.1f} [{100 * d.low:+.1f}, {100 * d.high:+.1f}] points",
          d.verdict, f"{num(d.rhs_ratio)} [{num(d.rhs_ratio_low)}, {num(d.rhs_ratio_high)}]"]
         for d in s.comparisons])
    m = len(s.comparisons)
    return ["## How tight: right-hand side over left-hand side", "",
            "Informative steps: R > 0 (nominal and real samples differ, so the Lipschitz term "
            "is not zero). The ratio RHS/LHS is taken where LHS > 0; steps with LHS <= 0 are "
            "counted apart. A bound is 'informative at c' on a step when LHS > 0 and "
            "LHS <= RHS <= c LHS; shares are of all informative steps, with Wilson 95 % "
            "intervals. Variance 'all': every variance pooled.", "", *tight, "",
            "## Local against global constants, and the sampled-tube bound against the "
            "local form (decided)", "",
            f"Paired by step over the informative steps, every variance pooled: the share "
            f"informative at {THRESHOLD:g} with A minus that with B, Tango's score interval; "
            f"the median of RHS_B / RHS_A with the sign test's interval. The {m} comparisons "
            f"share a family-wise level of 0.05 (Bonferroni). Verdict: 'better' (interval "
            f"above 0), 'worse' (below 0), 'equivalent' (inside ±{100 * MARGIN:g} points), "
            "else 'undecided'. The intervals treat steps as independent; consecutive steps "
            "of an episode are not, so they are narrower than a clustered interval would be.",
            "", *comp, ""]


def variant_claims(s: BoundSummary) -> list[Claim]:
    out = []
    for t in s.config["tests"]:
        r = s.tight(t, "sampled")
        if r is None or r.n == 0:
            continue
        share = r.n_holding / r.n
        out.append(Claim(f"{t}: the sampled-tube bound holds on {_pct(share)} of the {r.n} "
                         "informative steps (at least 99 %).", share >= HOLDS_AT_LEAST))
        fails = [(v.variance, x) for v in s.variances
                 if (x := s.tight(t, "sampled", v.variance)) is not None and x.n
                 and x.n_holding < x.n]
        where = "; ".join(f"variance {v:g}: {x.n - x.n_holding} of {x.n}" for v, x in fails)
        f = next((x for x in s.variant_failures if x.test == t), None)
        if f is None:
            continue
        premise = (f" {f.n_failed_premise} of them also have a nominal state that is not "
                   "admissible (F̂_nom > alpha), the premise of the transition checks."
                   if t.startswith("T3") else "")
        out.append(Claim(f"{t}: the sampled-tube bound fails on {f.n_failed} of the {f.n} "
                         f"informative steps ({where}), below 99 %; every failure is at a step "
                         "where some real sample crashed, outside the lemma's premise that "
                         "the safe set is forward invariant: a crashed sample's cost carries "
                         "β_max, and its segment crosses an obstacle where no gradient is "
                         "evaluated, so S_n <= S*_n + δ_n fails for it." + premise + " On the "
                         f"{f.n_safe} informative steps where every real sample stayed safe it "
                         f"holds on {f.n_safe_holding}.",
                         share < HOLDS_AT_LEAST and f.n_failed == f.n_failed_crashed))
        out.append(Claim(f"{t}: the sampled-tube bound fails on {f.n_failed} of the {f.n} "
                         f"informative steps ({where}), {f.n_failed - f.n_failed_crashed} of "
                         "them at steps where every real sample stayed safe.",
                         share < HOLDS_AT_LEAST and f.n_failed > f.n_failed_crashed))
        d = s.decided(t, "sampled", "local")
        if d is not None and np.isfinite(d.rhs_ratio):
            out.append(Claim(f"{t}: the sampled-tube bound's right-hand side is smaller than "
                             f"the local form's by a median factor {num(d.rhs_ratio)} "
                             f"[{num(d.rhs_ratio_low)}, {num(d.rhs_ratio_high)}] over "
                             f"{d.n_ratio} informative steps.", d.rhs_ratio_low > 1.0))
    return out


def supported_variant(s: BoundSummary) -> list[str]:
    return supported(variant_claims(s))


def episode_with_most_informative(df: pd.DataFrame) -> tuple[float, int] | None:
    n = df[df["R"] > 0].groupby(["variance", "episode"]).size()
    if n.empty:
        return None
    v, e = n.idxmax()
    return float(v), int(e)


def ratio_figure(df: pd.DataFrame, tests=("T1", "T2", "T3b")) -> bytes:
    """RHS/LHS per step of the episode with the most informative steps (nan where R = 0 or
    LHS <= 0), per set of constants, above the distance to the nearest obstacle."""
    pick = episode_with_most_informative(df)
    if pick is None:
        fig, ax = plt.subplots(figsize=(5, 2.5))
        ax.set_title("no step with R > 0: no ratio to show", fontsize=9)
        ax.set_xlabel("plant step (of 0.02 s)", fontsize=8)
        ax.set_ylabel("RHS / LHS", fontsize=8)
        return png_bytes(fig)
    fig, axes = plt.subplots(len(tests) + 1, 1, figsize=(7, 2.2 * (len(tests) + 1)),
                             sharex=True)
    g = df[(df["variance"] == pick[0]) & (df["episode"] == pick[1])].sort_values("step")
    active = g["R"].to_numpy(float) > 0
    for ax, t in zip(axes, tests, strict=False):
        for c, style in (("local", "-"), ("global", ":"), ("sampled", "--")):
            r = ratios(g[f"{t}_{c}_lhs"], g[f"{t}_{c}_rhs"])
            r[~active] = np.nan
            ax.semilogy(g["step"], r, style, lw=0.9, marker=".", ms=2, label=c)
        for c in (1.0, THRESHOLD):
            ax.axhline(c, color="k", lw=0.5, ls="-" if c == 1.0 else "-.")
        ax.set_ylabel(f"{t} RHS / LHS", fontsize=8)
        ax.set_xlabel("plant step (of 0.02 s)", fontsize=8)
        ax.legend(fontsize=6, ncol=3)
    ax = axes[-1]
    ax.plot(g["step"], g["clearance"], "k-", lw=0.9)
    ax.set_ylabel("distance to the nearest\nobstacle's edge [m]", fontsize=8)
    ax.set_xlabel("plant step (of 0.02 s)", fontsize=8)
    axes[0].set_title(f"variance {pick[0]:g}, episode {pick[1]}: {int(active.sum())} of "
                      f"{len(g)} steps with R > 0 (gaps: R = 0 or LHS <= 0)", fontsize=9)
    return png_bytes(fig)


def csv(s: BoundSummary) -> str:
    """The tightness table as CSV (variance empty: all variances pooled)."""
    rows = []
    for r in s.tightness:
        d = {"variance": "" if np.isnan(r.variance) else r.variance, "test": r.test,
             "constants": r.constants, "informative_steps": r.n,
             "lhs_nonpositive": r.n_lhs_nonpositive, "holding": r.n_holding}
        d.update({f"ratio_q{round(100 * q):02d}": x
                  for q, x in zip(QUANTILES, r.ratio_quantiles, strict=True)})
        d.update({f"informative_at_{c:g}": k
                  for c, k in zip(THRESHOLDS, r.n_informative, strict=True)})
        rows.append(d)
    return pd.DataFrame(rows).to_csv(index=False)

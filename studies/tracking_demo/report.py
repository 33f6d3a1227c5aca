"""Summary and report of the BaS-iLQG tracking demo: a table per barrier weight, the paths."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from workbench.ilqg.bas import TrackingWeights
from workbench.scenarios.scenes import TrackingScene
from workbench.study import png_bytes
from workbench.study.io import atomic_write_bytes, atomic_write_text
from workbench.study.spec import Finished, PaperRow, Summary


def summary(finished: Finished) -> Summary:
    """One row per barrier weight (results only; solve times stay in the task records)."""
    table = finished.store.table("solves")
    rows = [{"q_beta": float(r.q_beta), "cost": float(r.cost), "ipopt_cost": float(r.ipopt_cost),
             "rel_cost_gap": float(r.rel_cost_gap), "min_h": float(r.min_h),
             "final_distance": float(r.final_distance), "iterations": int(r.iterations),
             "converged": bool(r.converged)} for r in table.itertuples()]
    weights = TrackingWeights()
    assumed = {**TrackingScene().assumed_values(), "Q": weights.Q, "R": weights.R,
               "S": weights.S, "s_beta": weights.s_beta,
               "q_beta_values": finished.config.q_betas,
               "barrier": "inverse 1/h, one summed state, gamma=0", "integrator": "euler"}
    lines = tuple(f"q_beta={r['q_beta']:g}: cost {r['cost']:.4f} (IPOPT {r['ipopt_cost']:.4f}), "
                  f"min h {r['min_h']:.4f}, final distance {r['final_distance']:.4f} m"
                  for r in rows)
    return Summary({"rows": rows, "assumed": assumed}, rows, lines)


def report(finished: Finished, summary: Summary) -> Path:
    out = finished.out
    scene = TrackingScene()
    trajs = {t.q_beta: finished.store.arrays(finished.ids[t])["X"] for t in finished.plan}
    times = {t.q_beta: finished.store.meta(finished.ids[t]) for t in finished.plan}
    atomic_write_bytes(out / "trajectories.png", _figure(scene, scene.reference(), trajs))
    path = out / "report.md"
    atomic_write_text(path, _report(summary.value, times, summary.data["assumed"],
                                    finished.run_line))
    return path


def paper_rows(out: Path) -> list[PaperRow]:
    import json

    rows = json.loads((Path(out) / "summary.json").read_text())["rows"]
    return [PaperRow(
        f"BaS-iLQG, q_beta = {r['q_beta']:g}",
        "tracks the unsafe reference safely and reaches the target (Sec. III, Fig. 3; no "
        "numbers)",
        f"min h {r['min_h']:.4f} m², final distance {r['final_distance']:.4f} m, cost "
        f"{r['cost']:.4f} vs IPOPT {r['ipopt_cost']:.4f}",
        "safe" if r["min_h"] > 0 else "UNSAFE") for r in rows]


def _figure(scene, ref, trajs) -> bytes:
    fig, ax = plt.subplots(figsize=(9, 3.5))
    c = scene.obstacle
    ax.add_patch(plt.Circle(c.center, c.radius, color="0.7", label="obstacle"))
    ax.plot(ref[:, 0], ref[:, 1], "k--", lw=1, label="reference (unsafe)")
    for q_beta, X in trajs.items():
        ax.plot(X[:, 0], X[:, 1], lw=1.5, label=f"BaS-iLQG, q_beta={q_beta:g}")
    ax.plot(*scene.start[:2], "kx", ms=8)
    ax.plot(*scene.target[:2], "k*", ms=10)
    ax.set_aspect("equal")
    ax.set_xlabel("p_x [m]")
    ax.set_ylabel("p_y [m]")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    return png_bytes(fig, dpi=120)


def _report(rows: list[dict], times: dict, assumed: dict, run_line: str) -> str:
    lines = [
        "# BaS-iLQG on the tracking scene (assumptions §3.3, §6.1)", "",
        "The paper reports (Sec. III) that BaS-iLQG tracks the unsafe reference safely and "
        "reaches the target; it gives no cost figures. Our measured numbers below; the full "
        f"Monte Carlo comparison (ECBF, AL, BaS) is the tracking-comparison study. {run_line}",
        "",
        "| q_beta | cost | IPOPT cost | rel. gap | min h [m²] | final dist. [m] | iters | "
        "iLQG [ms] | IPOPT [ms] |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        t = times[r["q_beta"]]
        lines.append(f"| {r['q_beta']:g} | {r['cost']:.4f} | {r['ipopt_cost']:.4f} | "
                     f"{r['rel_cost_gap']:.1e} | {r['min_h']:.4f} | {r['final_distance']:.4f} | "
                     f"{r['iterations']} | {1e3 * t['ilqg_time_s']:.1f} | "
                     f"{1e3 * t['ipopt_time_s']:.1f} |")
    lines += ["", "Times include the first, cached-library call; see `make bench` for timing.", "",
              "## Assumed values [A]", ""]
    lines += [f"- `{k}`: {v}" for k, v in assumed.items()]
    lines += ["", "![trajectories](trajectories.png)", ""]
    return "\n".join(lines)

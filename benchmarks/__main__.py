"""``python -m benchmarks --out reports/bench/bench.json`` (``make bench``), also writes
``report.md`` beside it.

Each record: name, value, unit, baseline, baseline_value, ratio (= baseline_value / value),
params. Times are medians of repeats; every ratio compares two things measured in this process,
so noisy machines still give comparable figures. Baselines: a vectorised NumPy implementation
(sampler kernels), IPOPT and FATROP on the same multiple-shooting NLP (iLQG variants), a fresh
qpsolvers call (ECBF step), pytorch_mppi (optional ``bench`` extra), the NumPy iLQG twin (per
iteration). A record without a measured baseline has ratio None.
"""

from __future__ import annotations

import argparse
import importlib
import os
import statistics
import time
from pathlib import Path

import numpy as np

from workbench.ilqg import ILQGOptions, ilqg, make_passes
from workbench.ilqg.bas import TrackingWeights, tracking_params, tracking_problem
from workbench.problem.barrier import BarrierOptions
from workbench.problem.models import double_integrator
from workbench.scenarios.scenes import TrackingScene
from workbench.study.io import atomic_write_json, manifest


def _median_time(fn, repeats: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def record(name, value, unit, baseline, baseline_value, params):
    ratio = baseline_value / value if value else None
    return {"name": name, "value": value, "unit": unit, "baseline": baseline,
            "baseline_value": baseline_value, "ratio": ratio, "params": params}


def bench_ilqg_iteration(repeats: int) -> dict:
    """Per-iteration time of BaS-iLQG at T=100 (nx=5, nu=2), compiled vs NumPy twin."""
    scene = TrackingScene(horizon=100)
    model = double_integrator(obstacles=(scene.obstacle,), u_limit=scene.u_limit)
    problem = tracking_problem(model, TrackingWeights(), barrier=BarrierOptions())
    P = tracking_params(problem, scene.reference(), scene.target)
    U0 = np.zeros((100, 2))
    opts = ILQGOptions(max_iter=20)
    fast = make_passes(problem, 100, "compiled")
    slow = make_passes(problem, 100, "numpy")
    t_fast, r_fast = _median_time(lambda: ilqg(problem, scene.start, U0, P, opts, fast), repeats)
    t_slow, r_slow = _median_time(lambda: ilqg(problem, scene.start, U0, P, opts, slow), 1)
    per_fast = 1e3 * t_fast / r_fast.iterations
    per_slow = 1e3 * t_slow / r_slow.iterations
    return record("ilqg_iteration_T100", per_fast, "ms/iteration", "numpy_twin_ms_per_iteration",
                  per_slow, {"T": 100, "nx": 5, "nu": 2, "iterations": r_fast.iterations,
                             "includes": "derivatives + backward pass + line search + Python "
                             "outer loop", "goal_ms": 1.0})


def _fmt(v, spec: str = ".3g") -> str:
    return "—" if v is None else format(v, spec)


def report_markdown(records: list[dict], man: dict) -> str:
    """The benchmark table: every ratio is baseline_value / value, both measured in this run."""
    lines = ["# Benchmarks (`make bench`)", "",
             "Medians of repeats in one process; every ratio = baseline / value, both measured "
             "in this run (alternating where both are timed in a loop). Machine: "
             f"{man.get('platform', '?')}, {os.cpu_count()} CPUs; "
             f"git {str(man.get('git_revision', '?'))[:10]}.", "",
             "| benchmark | value | unit | baseline | baseline value | ratio | notes |",
             "|---|---:|---|---|---:|---:|---|"]
    for r in records:
        p = r.get("params", {})
        notes = []
        if r.get("skipped"):
            notes.append(f"skipped: {r['skipped']}")
        for key in ("goal_ratio", "goal_ms"):
            if p.get(key) is not None:
                notes.append(f"{key} {p[key]}")
        if isinstance(p.get("iterations"), dict):
            notes.append("iterations " + ", ".join(f"{k} {v}" for k, v in p["iterations"].items()))
        if p.get("threads") is not None:
            notes.append(f"threads {p['threads']}")
        if "max_rel_cost_difference" in p:
            notes.append(f"objectives agree to {p['max_rel_cost_difference']:.1e}")
        if "max_rel_err_vs_kernel_on_kernel_noise" in p:
            notes.append(f"baseline = kernel to {p['max_rel_err_vs_kernel_on_kernel_noise']:.0e}")
        if "nlp_max_rel_cost_difference" in p:
            notes.append(f"IPOPT/FATROP objectives agree to {p['nlp_max_rel_cost_difference']:.1e}")
        if "slowdown_vs_di" in p:
            notes.append(f"slowdown {p['slowdown_vs_di']:.2f}x (goal <= {p['goal_slowdown']}x"
                         f"{', met' if p['goal_met'] else ', not met'}); same kernel with cubic "
                         f"polynomials for sin/cos: {p['floor_polynomial_unicycle_vs_di']:.2f}x")
        if "vector_vs_scalar_max_rel_diff" in p and "slowdown_vs_di" not in p:
            notes.append(f"{p['vector_math']}, <= {p['max_ulp_tested']} ulp; vector = scalar to "
                         f"{p['vector_vs_scalar_max_rel_diff']:.0e}")
        if "al_rel_cost_gap_vs_fatrop" in p:
            notes.append(f"AL cost gap {p['al_rel_cost_gap_vs_fatrop']:.1e}")
        lines.append(f"| {r['name']} | {_fmt(r['value'])} | {r['unit']} | "
                     f"{r['baseline'] or '—'} | {_fmt(r['baseline_value'])} | "
                     f"{_fmt(r['ratio'], '.1f')} | {'; '.join(notes)} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", type=Path, default=Path("reports/bench/bench.json"))
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args(argv)
    records = []
    for module in ("benchmarks.tracking", "benchmarks.sampling", "benchmarks.trig",
                   "benchmarks.torch_mppi"):
        records += importlib.import_module(module).records(args.repeats)
    records.append(bench_ilqg_iteration(args.repeats))
    for r in records:
        print(f"{r['name']:44s} {_fmt(r['value'], '10.4f')} {r['unit']:12s} baseline "
              f"{r['baseline']} = {_fmt(r['baseline_value'], '.4f')}  ratio "
              f"{_fmt(r['ratio'], '.1f')}x" + (f"  [skipped: {r['skipped']}]"
                                             if r.get("skipped") else ""))
    man = manifest()
    atomic_write_json(args.out, {"records": records, "manifest": man})
    report = args.out.with_name("report.md")
    report.write_text(report_markdown(records, man))
    print(f"wrote {args.out} and {report}")


if __name__ == "__main__":
    main()

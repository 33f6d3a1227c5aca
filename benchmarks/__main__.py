"""``python -m benchmarks --out reports/bench/bench.json`` (``make bench``).

Each record: name, value, unit, baseline, baseline_value, ratio, params. Times are medians of
repeats; every ratio compares two things measured in this process, so noisy machines still give
comparable figures.
"""

from __future__ import annotations

import argparse
import importlib
import statistics
import time
from pathlib import Path

import numpy as np

from workbench.barrier import BarrierOptions
from workbench.ilqg import ILQGOptions, ilqg, make_passes
from workbench.io import atomic_write_json, manifest
from workbench.ipopt_oracle import solve_ipopt
from workbench.models import double_integrator
from workbench.scenes import TrackingScene
from workbench.tracking import TrackingWeights, tracking_params, tracking_problem


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


def bench_bas_ilqg_vs_ipopt(repeats: int) -> dict:
    scene = TrackingScene()
    model = double_integrator(obstacles=(scene.obstacle,), u_limit=scene.u_limit)
    problem = tracking_problem(model, TrackingWeights(), barrier=BarrierOptions())
    P = tracking_params(problem, scene.reference(), scene.target)
    U0 = np.zeros((scene.horizon, 2))
    ilqg(problem, scene.start, U0, P)  # load the cached library once
    runs = [ilqg(problem, scene.start, U0, P) for _ in range(repeats)]
    t_ilqg, res = statistics.median(r.solve_time_s for r in runs), runs[-1]
    t_build, ora = _median_time(lambda: solve_ipopt(problem, scene.start, U0, P), 3)
    oracle_runs = [solve_ipopt(problem, scene.start, U0, P) for _ in range(2)] + [ora]
    t_ipopt = statistics.median(o.solve_time_s for o in oracle_runs)
    return record("bas_ilqg_vs_ipopt_tracking", 1e3 * t_ilqg, "ms", "ipopt_solve_ms",
                  1e3 * t_ipopt, {
                      "T": scene.horizon, "ilqg_iterations": res.iterations,
                      "ipopt_iterations": ora.iterations, "ilqg_cost": res.cost,
                      "ipopt_cost": ora.cost,
                      "rel_cost_difference": (res.cost - ora.cost) / abs(ora.cost),
                      "ipopt_time": "solve call only (IPOPT, exact Hessian, tol 1e-10)",
                      "ipopt_nlp_construction_plus_solve_ms": 1e3 * t_build,
                      "goal_ratio": 10.0})


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


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", type=Path, default=Path("reports/bench/bench.json"))
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args(argv)
    records = [bench_bas_ilqg_vs_ipopt(args.repeats), bench_ilqg_iteration(args.repeats)]
    for module in ("benchmarks.tracking", "benchmarks.sampling"):
        try:
            mod = importlib.import_module(module)
        except ModuleNotFoundError:
            continue
        records += mod.records(args.repeats)
    for r in records:
        print(f"{r['name']:32s} {r['value']:10.4f} {r['unit']:14s} baseline "
              f"{r['baseline']} = {r['baseline_value']:.4f}  ratio {r['ratio']:.1f}x")
    atomic_write_json(args.out, {"records": records, "manifest": manifest()})
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

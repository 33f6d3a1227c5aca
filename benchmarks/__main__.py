"""``python -m benchmarks --out reports/bench/bench.json`` (``make bench``), also writes
``report.md`` beside it, and the growth curves ``growth.json`` / ``growth.png``.

Flags: ``--quick`` (fewer repeats, no growth curves, no jit-compiled NLP baselines),
``--growth`` (only the growth curves; ``report.md`` is re-rendered with the records already in
``bench.json``), ``--max-circles`` (largest circle count of the growth curves).

Each record: name, value, unit, baseline, baseline_value, ratio (= baseline_value / value),
params. Times are medians of repeats; every ratio compares two things measured in this process,
so noisy machines still give comparable figures. Baselines: a vectorised NumPy implementation
(sampler kernels), IPOPT and FATROP on the same multiple-shooting NLP (iLQG variants), a fresh
qpsolvers call (ECBF step), pytorch_mppi (optional ``bench`` extra), the NumPy iLQG twin (per
iteration), the hand-written C floor of the sampler rollouts (``benchmarks/floor``; the
split of each batch into noise, rollout, Python call, weights and update is a ratio to it). A
record without a measured baseline has ratio None.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import json
import logging
import os
import statistics
import time
import traceback
from pathlib import Path

import numpy as np

from benchmarks.floor import cpu_flags, cpu_model
from benchmarks.report import report_markdown
from workbench.ilqg import ILQGOptions, ilqg, make_passes
from workbench.ilqg.bas import TrackingWeights, tracking_params, tracking_problem
from workbench.problem.barrier import BarrierOptions
from workbench.problem.models import double_integrator
from workbench.scenarios.scenes import TrackingScene
from workbench.study.io import atomic_write_json, manifest

log = logging.getLogger("benchmarks")


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


def optional_records(repeats: int) -> list[dict]:
    """Records of the optional benchmark modules (precision, threads, the robust step, the
    sequential comparison's operating characteristics, the scene kinds' margins) when
    they exist; a module that fails leaves a record naming the error (and its traceback on
    stderr)."""
    out = []
    for module, fn in (("benchmarks.precision", "bench_precision"),
                       ("benchmarks.threads", "bench_threads"),
                       ("benchmarks.robust_step", "records"),
                       ("benchmarks.sequential_operating", "records"),
                       ("benchmarks.latency", "records"),
                       ("benchmarks.scene_margins", "records")):
        if importlib.util.find_spec(module) is None:
            print(f"{module}: not present, skipped")
            continue
        try:
            out += list(getattr(importlib.import_module(module), fn)(repeats))
        except Exception as exc:  # one failing module must not lose the other records
            traceback.print_exc()
            out.append({"name": module, "value": None, "unit": "", "baseline": None,
                        "baseline_value": None, "ratio": None, "params": {},
                        "skipped": f"failed: {type(exc).__name__}: {exc}"})
    return out


def _fmt(v, spec: str = ".3g") -> str:
    return "—" if v is None else format(v, spec)


def _tail(r: dict) -> str:
    """`` p50/p95/p99/max a/b/c/d ms`` for a record with step-time percentiles, else ""."""
    p = r.get("params") or {}
    keys = ("p50_ms", "p95_ms", "p99_ms", "max_ms")
    if not all(isinstance(p.get(k), int | float) for k in keys):
        return ""
    return "  p50/p95/p99/max " + "/".join(f"{p[k]:.2f}" for k in keys) + " ms"


def _growth_markdown(out_dir: Path) -> str | None:
    from benchmarks.growth import markdown

    try:
        return markdown(json.loads((out_dir / "growth.json").read_text()))
    except (OSError, ValueError, KeyError):
        return None


def _run_growth(args, out_dir: Path) -> None:
    from benchmarks.growth import GrowthConfig, growth

    cfg = GrowthConfig(circles=tuple(n for n in GrowthConfig().circles if n <= args.max_circles)
                       or (args.max_circles,))
    growth(cfg, out_dir)
    print(f"wrote {out_dir / 'growth.json'} and {out_dir / 'growth.png'}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("reports/bench/bench.json"))
    ap.add_argument("--repeats", type=int, default=None,
                    help="repeats per timing (default 7; 3 with --quick)")
    ap.add_argument("--quick", action="store_true",
                    help="fewer repeats, no growth curves, no jit-compiled NLP baselines")
    ap.add_argument("--growth", action="store_true",
                    help="only the growth curves (report.md re-rendered with bench.json)")
    ap.add_argument("--max-circles", type=int, default=1000,
                    help="largest circle count of the growth curves (default 1000; the first "
                    "build of the 1000-slot kernels takes about a minute)")
    args = ap.parse_args(argv)
    if args.quick and args.growth:
        ap.error("--quick and --growth exclude each other")
    if args.repeats is not None and args.repeats < 1:
        ap.error(f"--repeats {args.repeats}: must be at least 1")
    if args.max_circles < 1:
        ap.error(f"--max-circles {args.max_circles}: must be at least 1")
    repeats = args.repeats or (3 if args.quick else 7)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    out_dir = args.out.parent
    if args.growth:
        _run_growth(args, out_dir)
        try:
            data = json.loads(args.out.read_text())
            records, man = data["records"], data["manifest"]
        except (OSError, ValueError, KeyError):
            records, man = [], manifest()
        report = out_dir / "report.md"
        report.write_text(report_markdown(records, man, _growth_markdown(out_dir)))
        print(f"wrote {report}")
        return
    records = []
    records += importlib.import_module("benchmarks.tracking").records(repeats,
                                                                      jit=not args.quick)
    for module in ("benchmarks.split", "benchmarks.sampling", "benchmarks.trig",
                   "benchmarks.torch_mppi"):
        records += importlib.import_module(module).records(repeats)
    records.append(bench_ilqg_iteration(repeats))
    records += optional_records(repeats)
    for r in records:
        print(f"{r['name']:52s} {_fmt(r['value'], '10.4f')} {r['unit']:12s} baseline "
              f"{r['baseline']} = {_fmt(r['baseline_value'], '.4f')}  ratio "
              f"{_fmt(r['ratio'], '.1f')}x" + (f"  [skipped: {r['skipped']}]"
                                             if r.get("skipped") else "") + _tail(r))
    man = manifest()
    man["machine"] = {"cpu": cpu_model(), "cpu_flags": cpu_flags(), "cpus": os.cpu_count()}
    atomic_write_json(args.out, {"records": records, "manifest": man})
    if not args.quick:
        _run_growth(args, out_dir)
    report = out_dir / "report.md"
    report.write_text(report_markdown(records, man, _growth_markdown(out_dir)))
    print(f"wrote {args.out} and {report}")


if __name__ == "__main__":
    main()

"""Do float32 sampler kernels change outcomes? Paired navigation episodes, float32 vs float64.

``python -m benchmarks.precision_evidence --out reports/bench/precision_evidence.json``

Each realisation j at a disturbance variance runs the same controller twice, once with float64
and once with float32 sampler kernels (:class:`~workbench.sampling.sampler.Sampler`
``precision``), on the same controller and plant random streams (seeded by (seed, variance,
j)) and the same calibrated selection threshold (one calibration, float64). The float32
kernels draw the float64 kernels' normals rounded to float, so the two episodes differ only by
precision until their states part (closed loops amplify differences: the first step where the
states differ by more than 1e-6 and the largest position difference are recorded).

A control arm measures what any rounding-level change does to a closed loop: float64 again,
with the start moved by :data:`MOVE` (1e-7 m, the float32 resolution of a position of order 1)
along x. Under strong disturbances the loop is chaotic near the obstacles: once the states
part, the two episodes are different realisations, and crash outcomes agree no more than those
of the control pair.

Per (controller, variance): crash agreement (the fraction of realisations whose crash outcome
is the same) of float32 and of the control with float64, the safety rates with Wilson 95%
intervals, the paired difference (Newcombe interval) and McNemar's exact p, the float32 guards'
activity (samples recomputed in float64 near the crash margin, whole batches recomputed because
no sample was crash-free) and median step times. The verdict: crash agreement >= 97% and each
safety rate inside the other's interval.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np

from workbench.sampling.sampler import Sampler
from workbench.scenarios.navigation import navigation_setup
from workbench.sim import Disturbance, closed_loop
from workbench.study.io import atomic_write_json, manifest
from workbench.study.stats import (
    mcnemar_exact,
    paired_counts,
    paired_difference_interval,
    wilson_interval,
)

AGREEMENT_GOAL = 0.97
PRECISIONS = ("float64", "float32")
MOVE = 1e-7  # m: the control arm's start shift
ARMS = ("float64", "float32", "float64_moved")


def with_precision(ctrl, precision: str):
    """``ctrl`` sampling with ``precision`` kernels: its sampler (and its inner MPPI's, for
    RobustMPPI, which shares it) replaced by one of that precision."""
    old = ctrl.sampler
    new = Sampler(old.sp, old.backend, precision)
    ctrl.sampler = new
    inner = getattr(ctrl, "mppi", None)
    if inner is not None and getattr(inner, "sampler", None) is old:
        inner.sampler = new
    return ctrl


def _streams(seed: int, variance: float, j: int):
    key = [int(seed), round(variance * 1000), int(j)]
    return np.random.default_rng([*key, 0]), np.random.default_rng([*key, 1])


def _episode(nav, ctrl, variance: float, j: int, seed: int, steps: int, goal_radius: float,
             move: float = 0.0):
    g = ctrl.sampler.guard
    before = (g.batches, g.samples, g.rechecked, g.reruns)
    rc, rp = _streams(seed, variance, j)
    x0 = np.array(nav.x0, dtype=float)
    x0[nav.plant.position[0]] += move
    t0 = time.perf_counter()
    ep = closed_loop(ctrl, nav.plant, x0, steps, rc, rp, Disturbance(variance),
                     keep_infos=False, stop_at_goal=goal_radius, goal=nav.goal)
    wall = time.perf_counter() - t0
    after = (g.batches, g.samples, g.rechecked, g.reruns)
    d = [a - b for a, b in zip(after, before, strict=True)]
    return ep, {"crashed": bool(ep.crashed), "crash_step": ep.crash_step,
                "reached": bool(ep.reached_goal), "goal_step": ep.goal_step,
                "steps": len(ep.U), "min_margin": float(ep.min_margin),
                "median_step_ms": 1e3 * float(np.median(ep.step_time_s)),
                "wall_s": wall, "guard_batches": d[0], "guard_samples": d[1],
                "guard_rechecked": d[2], "guard_reruns": d[3]}


def _divergence(X64: np.ndarray, X32: np.ndarray, position=(0, 1)) -> dict:
    n = min(len(X64), len(X32))
    d = np.max(np.abs(X64[:n] - X32[:n]), axis=1)
    part = np.flatnonzero(d > 1e-6)
    pos = np.linalg.norm(X64[:n][:, list(position)] - X32[:n][:, list(position)], axis=1)
    return {"first_step_apart_1e-6": int(part[0]) if part.size else None,
            "max_position_difference": float(pos.max()),
            "final_position_difference": float(pos[-1])}


def _summary(pairs: list[dict]) -> dict:
    arms = [p for p in ARMS if p in pairs[0]]
    safe = {p: [not r[p]["crashed"] for r in pairs] for p in arms}
    n = len(pairs)
    a, b, c, d = paired_counts(safe["float64"], safe["float32"])
    rates = {}
    for p in arms:
        k = int(sum(safe[p]))
        lo, hi = wilson_interval(k, n)
        rates[p] = {"safe": k, "n": n, "rate": k / n, "low": lo, "high": hi}
    theta, lo, hi = paired_difference_interval(a, b, c, d)
    r64, r32 = rates["float64"], rates["float32"]
    agree = (a + d) / n
    within = (r64["low"] <= r32["rate"] <= r64["high"]) and (r32["low"] <= r64["rate"]
                                                            <= r32["high"])
    samples = sum(r["float32"]["guard_samples"] for r in pairs)
    batches = sum(r["float32"]["guard_batches"] for r in pairs)
    control = None
    if "float64_moved" in arms:
        ca, cb, cc, cd = paired_counts(safe["float64"], safe["float64_moved"])
        control = {"crash_agreement": (ca + cd) / n, "disagreements": cb + cc,
                   "move_m": MOVE}
    return {
        "n": n, "crash_agreement": agree, "disagreements": b + c,
        "control_float64_moved": control,
        "safety": rates, "paired_counts_a_b_c_d": [a, b, c, d],
        "safety_difference_64_minus_32": {"value": theta, "low": lo, "high": hi},
        "mcnemar_p": mcnemar_exact(b, c),
        "reached_agreement": float(np.mean([r["float64"]["reached"] == r["float32"]["reached"]
                                            for r in pairs])),
        "guard": {"rechecked_fraction": (sum(r["float32"]["guard_rechecked"] for r in pairs)
                                         / samples if samples else 0.0),
                  "rerun_batches_fraction": (sum(r["float32"]["guard_reruns"] for r in pairs)
                                             / batches if batches else 0.0),
                  "batches": batches, "samples": samples},
        "median_step_ms": {p: statistics.median(r[p]["median_step_ms"] for r in pairs)
                           for p in arms},
        "median_first_step_apart": (statistics.median(s) if (s := [
            r["divergence"]["first_step_apart_1e-6"] for r in pairs
            if r["divergence"]["first_step_apart_1e-6"] is not None]) else None),
        "verdict": {"crash_agreement_ok": agree >= AGREEMENT_GOAL,
                    "safety_rates_within_intervals": within},
    }


def run(controllers=("sa_rmppi",), variances=(10.0, 100.0), realisations: int = 50,
        steps: int = 1000, seed: int = 2026, goal_radius: float = 1.0, threads: int = 1,
        control: bool = True, log=print) -> dict:
    """The paired episodes and their summary (see module docstring)."""
    from workbench.sampling.kernels.library import set_threads

    set_threads(threads, adaptive=False)
    nav = navigation_setup()
    out: dict = {"config": {"controllers": list(controllers), "variances": list(variances),
                            "realisations": realisations, "steps": steps, "seed": seed,
                            "goal_radius": goal_radius, "threads": threads,
                            "mppi": {"n_samples": nav.mppi.n_samples,
                                     "horizon": nav.mppi.horizon, "sigma": list(nav.mppi.sigma),
                                     "lam": nav.mppi.lam}},
                 "cells": [], "pairs": []}
    for name in controllers:
        threshold = nav.threshold() if name in ("sa_rmppi", "rmppi") else None
        kw = {"threshold": threshold} if threshold is not None else {}
        ctrls = {p: with_precision(nav.controller(name, **kw), p) for p in PRECISIONS}
        assert ctrls["float32"].sampler.precision == "float32"
        arms = ARMS if control else PRECISIONS
        for var in variances:
            pairs = []
            for j in range(realisations):
                eps, rec = {}, {"controller": name, "variance": var, "realisation": j}
                for arm in arms:
                    p = "float64" if arm == "float64_moved" else arm
                    eps[arm], rec[arm] = _episode(nav, ctrls[p], var, j, seed, steps,
                                                  goal_radius, MOVE if arm != p else 0.0)
                rec["divergence"] = _divergence(eps["float64"].X, eps["float32"].X,
                                                nav.plant.position)
                if "float64_moved" in eps:
                    rec["divergence_control"] = _divergence(
                        eps["float64"].X, eps["float64_moved"].X, nav.plant.position)
                pairs.append(rec)
                log(f"{name} var {var:g} j {j}: crashed "
                    + "/".join(str(rec[a]["crashed"]) for a in arms) + ", steps "
                    + "/".join(str(rec[a]["steps"]) for a in arms)
                    + f", rechecked {rec['float32']['guard_rechecked']}")
            cell = {"controller": name, "variance": var, **_summary(pairs)}
            out["cells"].append(cell)
            out["pairs"] += pairs
            rates = cell["safety"]
            log(f"{name} var {var:g}: agreement {cell['crash_agreement']:.3f}, safety "
                f"{rates['float64']['rate']:.3f} / {rates['float32']['rate']:.3f}")
    every = list(out["pairs"])
    out["overall"] = _summary(every) if every else None
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("reports/bench/precision_evidence.json"))
    ap.add_argument("--controllers", nargs="+", default=["sa_rmppi"])
    ap.add_argument("--variances", nargs="+", type=float, default=[10.0, 100.0])
    ap.add_argument("--realisations", type=int, default=50)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--no-control", action="store_true",
                    help="skip the control arm (float64 with the start moved by 1e-7 m)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    res = run(args.controllers, args.variances, args.realisations, args.steps, args.seed,
              control=not args.no_control)
    res["wall_s"] = time.perf_counter() - t0
    res["manifest"] = manifest()
    atomic_write_json(args.out, res)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

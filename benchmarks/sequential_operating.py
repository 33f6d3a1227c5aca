"""Operating characteristics of the group-sequential paired comparison
(:mod:`workbench.study.sequential`) by seeded simulation.

``python -m benchmarks.sequential_operating --out reports/bench/sequential_operating.json``
(``make bench`` adds one record per cell to ``bench.json``).

Per cell (discordance psi, comparisons m), the design :func:`plan_pairs` gives for margin 0.10
in 4 looks is simulated at five truths, ``reps`` comparisons each: d = 0 (p_b = p_c = psi/2),
d = +-margin, and a clear effect d = 2 margin (d = psi when psi < 2 margin). Reported: the
type I error P(superior or inferior | d = 0), the powers P(superior | d = margin) and
P(inferior | d = -margin), the equivalence power P(equivalent | d = 0), the wrong-equivalence
rates at d = +-margin, each with its Wilson 95% interval, and the mean (and quantiles) of the
pairs used against the maximum. The same truths are run with Agresti-Min intervals
(``interval="agresti-min"``) at the same size, for comparison. A cell's promises are ``kept``
unless an error rate is significantly above alpha / m (Wilson lower limit above it) or a power
significantly below the planned 0.8 (Wilson upper limit below it).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from workbench.study.io import atomic_write_json, manifest
from workbench.study.sequential import (
    Operating,
    SequentialDesign,
    detectable,
    plan_pairs,
    simulate,
)
from workbench.study.summary import Rate

MARGIN, ALPHA, POWER, LOOKS = 0.10, 0.05, 0.8, 4
DISCORDANCES = (0.2, 0.35, 0.5)
COMPARISONS = (1, 4)
REPS = 100_000
SEED = 2026


def _rate(r: Rate) -> dict:
    return {"rate": r.value, "low": r.low, "high": r.high, "k": r.k, "n": r.n}


def _truths(psi: float) -> dict[str, tuple[float, float]]:
    clear = min(2 * MARGIN, psi)
    return {"null": (psi / 2, psi / 2), "plus": ((psi + MARGIN) / 2, (psi - MARGIN) / 2),
            "minus": ((psi - MARGIN) / 2, (psi + MARGIN) / 2),
            "clear": ((psi + clear) / 2, (psi - clear) / 2)}


def _errors(op: dict[str, Operating]) -> tuple[Rate, Rate, Rate]:
    """Type I (either direction at d = 0), wrong equivalence at d = +margin and -margin."""
    null = op["null"]
    return (Rate(null.superior.k + null.inferior.k, null.reps), op["plus"].equivalent,
            op["minus"].equivalent)


def cell(psi: float, m: int, reps: int, seed: int) -> dict:
    """One (discordance, comparisons) cell: the plan and its simulated characteristics."""
    n = plan_pairs(MARGIN, psi, ALPHA, POWER, LOOKS, m)
    design = SequentialDesign(LOOKS, n // LOOKS, MARGIN, ALPHA, m, POWER)
    rng = np.random.default_rng([seed, round(psi * 1000), m])
    op = {k: simulate(design, pb, pc, reps, rng) for k, (pb, pc) in _truths(psi).items()}
    am = SequentialDesign(LOOKS, n // LOOKS, MARGIN, ALPHA, m, POWER, interval="agresti-min")
    op_am = {k: simulate(am, pb, pc, reps, rng) for k, (pb, pc) in _truths(psi).items()
             if k != "clear"}
    level = ALPHA / m
    type1, wrong_plus, wrong_minus = _errors(op)
    am_type1, am_plus, am_minus = _errors(op_am)
    powers = (op["plus"].superior, op["minus"].inferior, op["null"].equivalent)
    kept = (all(r.low <= level for r in (type1, wrong_plus, wrong_minus))
            and all(r.high >= POWER for r in powers))
    return {
        "discordance": psi, "comparisons": m, "level": level, "margin": MARGIN, "looks": LOOKS,
        "max_pairs": n, "pairs_per_look": n // LOOKS, "reps": reps,
        "bounds": design.bounds().tolist(),
        "equivalence_bounds": design.equivalence_bounds().tolist(),
        "type1": _rate(type1), "power_superior": _rate(powers[0]),
        "power_inferior": _rate(powers[1]), "equivalence_power": _rate(powers[2]),
        "wrong_equivalence": {"plus": _rate(wrong_plus), "minus": _rate(wrong_minus)},
        "undecided_null": _rate(op["null"].undecided),
        "expected_pairs": {k: o.mean_pairs for k, o in op.items()},
        "pairs_quantiles_null": list(op["null"].pairs_quantiles),
        "clear_difference": op["clear"].difference,
        "detectable_at_max_pairs": detectable(n, psi, ALPHA, POWER, LOOKS, m),
        "kept": kept,
        "agresti_min": {"type1": _rate(am_type1),
                        "wrong_equivalence": {"plus": _rate(am_plus), "minus": _rate(am_minus)},
                        "power_superior": _rate(op_am["plus"].superior),
                        "equivalence_power": _rate(op_am["null"].equivalent)},
    }


def run(discordances=DISCORDANCES, comparisons=COMPARISONS, reps: int = REPS,
        seed: int = SEED) -> dict:
    t0 = time.perf_counter()
    cells = [cell(psi, m, reps, seed) for psi in discordances for m in comparisons]
    for c in cells:
        print(line(c))
    return {"cells": cells, "alpha": ALPHA, "power": POWER, "seed": seed,
            "wall_s": time.perf_counter() - t0}


def _fmt(r: dict) -> str:
    return f"{r['rate']:.4f} [{r['low']:.4f}, {r['high']:.4f}]"


def line(c: dict) -> str:
    """One printed line per cell."""
    e = c["expected_pairs"]
    return (f"psi {c['discordance']:.2f} m {c['comparisons']}: max pairs {c['max_pairs']}, "
            f"type I {_fmt(c['type1'])} (<= {c['level']:.4f}), power "
            f"{c['power_superior']['rate']:.3f}, equivalence power "
            f"{c['equivalence_power']['rate']:.3f}, wrong equivalence "
            f"{c['wrong_equivalence']['plus']['rate']:.4f}/"
            f"{c['wrong_equivalence']['minus']['rate']:.4f}, expected pairs "
            f"{e['null']:.0f} (d=0) {e['plus']:.0f} (d=margin) {e['clear']:.0f} "
            f"(d={c['clear_difference']:.2f}); Agresti-Min: type I "
            f"{c['agresti_min']['type1']['rate']:.4f}, wrong equivalence "
            f"{c['agresti_min']['wrong_equivalence']['plus']['rate']:.4f}"
            f"{'' if c['kept'] else '  ** NOT KEPT **'}")


def records(repeats: int) -> list[dict]:
    """``make bench`` records (``repeats`` is unused: one simulation per cell): value = the
    simulated type I error, baseline = alpha / m, ratio = alpha / m over it; the other figures
    in ``params``, ``goal_met`` = the cell's promises kept."""
    res = run()
    out = []
    for c in res["cells"]:
        value = c["type1"]["rate"]
        params = {k: v for k, v in c.items() if k not in ("type1", "bounds",
                                                          "equivalence_bounds")}
        params.update(type1_low=c["type1"]["low"], type1_high=c["type1"]["high"],
                      goal_met=c["kept"], wall_s_all_cells=res["wall_s"])
        out.append({"name": f"sequential_type1_psi{c['discordance']:g}_m{c['comparisons']}",
                    "value": value, "unit": "rate", "baseline": "alpha/m",
                    "baseline_value": c["level"],
                    "ratio": c["level"] / value if value else None, "params": params})
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("reports/bench/sequential_operating.json"))
    ap.add_argument("--reps", type=int, default=REPS, help="comparisons per truth")
    ap.add_argument("--seed", type=int, default=SEED)
    ap.add_argument("--discordance", nargs="+", type=float, default=list(DISCORDANCES))
    ap.add_argument("--comparisons", nargs="+", type=int, default=list(COMPARISONS))
    args = ap.parse_args(argv)
    res = run(args.discordance, args.comparisons, args.reps, args.seed)
    res["manifest"] = manifest()
    atomic_write_json(args.out, res)
    print(f"wrote {args.out} ({res['wall_s']:.1f} s)")


if __name__ == "__main__":
    main()

"""``python -m studies.free_energy_bound --profile tiny|quick|paper --out DIR [--workers N |
--scheduler ADDRESS]``.

Checks Lemma 1 (the free-energy bound) numerically on SA-RMPPI episodes on the navigation map
and writes the tidy data (steps.parquet/.csv, episodes.parquet/.csv), summary.json, figures and
report.md to DIR. Ctrl-C stops within seconds; rerun the same command to continue.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from studies.free_energy_bound.config import PROFILES, StudyConfig
from studies.free_energy_bound.run import run
from workbench.study import StudyInterrupted
from workbench.validation import writable_dir


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--profile", default="quick", choices=PROFILES)
    ap.add_argument("--out", type=Path, default=Path("reports/free_energy_bound"))
    ap.add_argument("--workers", type=int, default=2,
                    help="local worker processes (0: run in this process; default 2)")
    ap.add_argument("--scheduler", default=None, help="Dask scheduler address instead")
    ap.add_argument("--seed", type=int, default=None, help="root seed")
    ap.add_argument("--episodes", type=int, default=None, help="episodes per variance")
    ap.add_argument("--steps", type=int, default=None, help="steps per episode (at most)")
    args = ap.parse_args(argv)
    overrides = {k: v for k, v in (("seed", args.seed), ("episodes", args.episodes),
                                   ("steps", args.steps)) if v is not None}
    config = StudyConfig.for_profile(args.profile, **overrides)  # fails fast on bad values
    try:
        writable_dir("--out", args.out)
    except ValueError as exc:
        ap.error(str(exc))
    try:
        outcome = run(config, args.out, workers=args.workers, scheduler=args.scheduler)
    except StudyInterrupted:
        sys.exit(130)
    s = outcome.summary
    for v in s.variances:
        cells = []
        for t in config.tests:
            r = s.row(t, "local", v.variance)
            if r is not None:
                cells.append(f"{t} {100 * r.fraction_holding:.0f}%")
        print(f"variance {v.variance:g}: {v.n_steps} steps, " + ", ".join(cells))
    print(f"wall time {outcome.wall_s:.1f} s; wrote {outcome.report}")


if __name__ == "__main__":
    main()

"""``python -m studies.tracking_comparison --profile quick|full --out DIR [--workers N |
--scheduler ADDRESS]``.

Runs (or continues) the tracking comparison of the paper's Sec. III and writes the tidy data
(rollouts.parquet, rollouts.csv), summary.json, the figures and report.md to DIR. Progress goes
to stderr. Ctrl-C stops within seconds; rerun the same command to continue.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from studies.tracking_comparison.config import METHODS, PROFILES, StudyConfig
from studies.tracking_comparison.findings import NAMES
from studies.tracking_comparison.run import run
from workbench.study import StudyInterrupted, fmt_rate


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--profile", default="quick", choices=PROFILES)
    ap.add_argument("--out", type=Path, default=Path("reports/tracking_comparison"))
    ap.add_argument("--workers", type=int, default=2,
                    help="local worker processes (0: run in this process; default 2)")
    ap.add_argument("--scheduler", default=None,
                    help="Dask scheduler address (e.g. tcp://host:8786) instead of local workers")
    ap.add_argument("--seed", type=int, default=None, help="root seed")
    ap.add_argument("--methods", nargs="+", default=None, help=f"subset of {METHODS}")
    ap.add_argument("--no-sweep", action="store_true", help="skip the sensitivity sweep")
    args = ap.parse_args(argv)
    overrides = {k: v for k, v in (("seed", args.seed),
                                   ("methods", tuple(args.methods) if args.methods else None))
                 if v is not None}
    if args.no_sweep:
        overrides["sweep"] = False
    config = StudyConfig.for_profile(args.profile, **overrides)  # fails fast on bad values
    try:
        outcome = run(config, args.out, workers=args.workers, scheduler=args.scheduler)
    except StudyInterrupted:
        sys.exit(130)
    for o in outcome.summary.methods:
        print(f"{NAMES[o.method]:20s} unsafe {fmt_rate(o.unsafe):22s} failure "
              f"{fmt_rate(o.failure):22s} n={o.n}")
    print(f"wall time {outcome.run.wall_time_s:.1f} s; wrote {outcome.report}")


if __name__ == "__main__":
    main()

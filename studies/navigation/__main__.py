"""``python -m studies.navigation --profile tiny|quick|paper --out DIR [--workers N |
--scheduler ADDRESS]``.

Runs (or continues) the navigation study of the paper's Sec. V and writes the tidy data
(episodes, velocity, timing as Parquet and CSV), summary.json, map.json, the figures and
report.md to DIR. Ctrl-C stops within seconds; rerun the same command to continue.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from studies.navigation.config import PROFILES, StudyConfig
from studies.navigation.findings import NAMES
from studies.navigation.run import run
from workbench.study import StudyInterrupted, fmt_rate


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--profile", default="quick", choices=PROFILES)
    ap.add_argument("--out", type=Path, default=Path("reports/navigation"))
    ap.add_argument("--workers", type=int, default=2,
                    help="local worker processes (0: run in this process; default 2)")
    ap.add_argument("--scheduler", default=None,
                    help="Dask scheduler address (e.g. tcp://host:8786) instead of local workers")
    ap.add_argument("--seed", type=int, default=None, help="root seed")
    args = ap.parse_args(argv)
    overrides = {"seed": args.seed} if args.seed is not None else {}
    config = StudyConfig.for_profile(args.profile, **overrides)  # fails fast on bad values
    try:
        outcome = run(config, args.out, workers=args.workers, scheduler=args.scheduler)
    except StudyInterrupted:
        sys.exit(130)
    for c in outcome.summary.cells:
        print(f"{NAMES[c.controller]:26s} {c.rule:22s} var {c.variance:6g}  safety "
              f"{fmt_rate(c.safe, 0):16s} RMSE {c.rmse:.4f}  {c.mean_step_ms:.1f} ms/step")
    print(f"wall time {outcome.run.wall_time_s:.1f} s; wrote {outcome.report}")


if __name__ == "__main__":
    main()

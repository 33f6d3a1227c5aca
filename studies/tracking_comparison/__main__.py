"""``python -m studies.tracking_comparison --profile quick|full --out DIR [--workers N]``.

Runs (or resumes) the tracking comparison of the paper's Sec. III and writes summary.json,
rollouts.csv, sweep.csv, the figures and report.md to DIR. Progress goes to stderr.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from studies.tracking_comparison.config import METHODS, PROFILES, StudyConfig
from studies.tracking_comparison.report import write_report
from studies.tracking_comparison.run import run
from workbench.validation import writable_dir


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--profile", default="quick", choices=PROFILES)
    ap.add_argument("--out", type=Path, default=Path("reports/tracking_comparison"))
    ap.add_argument("--workers", type=int, default=None, help="worker processes (default 2)")
    ap.add_argument("--seed", type=int, default=None, help="root seed")
    ap.add_argument("--methods", nargs="+", default=None, help=f"subset of {METHODS}")
    ap.add_argument("--no-sweep", action="store_true", help="skip the sensitivity sweep")
    args = ap.parse_args(argv)
    overrides = {k: v for k, v in (("workers", args.workers), ("seed", args.seed),
                                   ("methods", tuple(args.methods) if args.methods else None))
                 if v is not None}
    if args.no_sweep:
        overrides["sweep"] = False
    config = StudyConfig.for_profile(args.profile, **overrides)  # fails fast on bad values
    try:
        writable_dir("--out", args.out)
    except ValueError as exc:
        ap.error(str(exc))  # exits with status 2 and the message
    summary = run(config, args.out)
    path = write_report(args.out)
    for m, s in summary["methods"].items():
        print(f"{m:5s} unsafe {100 * s['unsafe_rate']:5.1f}% "
              f"[{100 * s['unsafe_ci_low']:.1f}, {100 * s['unsafe_ci_high']:.1f}]  "
              f"failure {100 * s['failure_rate']:5.1f}% "
              f"[{100 * s['failure_ci_low']:.1f}, {100 * s['failure_ci_high']:.1f}]  "
              f"n={s['n_rollouts']}")
    print(f"wall time {summary['wall_time_s']:.1f} s; wrote {path}")


if __name__ == "__main__":
    main()

"""python -m studies.alpha_rules --episodes 20 --out reports/alpha_rules"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import pandas as pd

from studies.alpha_rules.report import write_report
from studies.alpha_rules.run import run


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--episodes", type=int, default=20)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--variances", type=float, nargs="+", default=[10.0, 100.0])
    ap.add_argument("--out", type=Path, default=Path("reports/alpha_rules"))
    a = ap.parse_args(argv)
    if a.episodes < 1 or a.steps < 1 or a.workers < 1:
        ap.error("--episodes, --steps and --workers must be >= 1")
    t0 = time.time()
    rows = pd.DataFrame(run(a.episodes, a.seed, a.steps, a.workers, tuple(a.variances)))
    config = {k: str(v) if isinstance(v, Path) else v for k, v in vars(a).items()}
    write_report(rows.drop(columns=["path"]), a.out, config | {"wall_s": time.time() - t0})


if __name__ == "__main__":
    main()

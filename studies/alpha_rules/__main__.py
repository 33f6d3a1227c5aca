"""python -m studies.alpha_rules --episodes 20 --out reports/alpha_rules"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from studies.alpha_rules.report import write_report
from studies.alpha_rules.run import study
from workbench.study import RunStore, run_study


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--episodes", type=int, default=20)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--scheduler", default=None, help="Dask scheduler address")
    ap.add_argument("--variances", type=float, nargs="+", default=[10.0, 100.0])
    ap.add_argument("--out", type=Path, default=Path("reports/alpha_rules"))
    a = ap.parse_args(argv)
    if a.episodes < 1 or a.steps < 1 or a.workers < 0 or min(a.variances) < 0:
        ap.error("--episodes and --steps must be >= 1, --workers >= 0, variances >= 0")
    t0 = time.time()
    decl = study(a.episodes, a.steps, a.seed, tuple(a.variances))
    run_study(decl, a.out, workers=a.workers, scheduler=a.scheduler).raise_for_errors()
    config = {"episodes": a.episodes, "steps": a.steps, "seed": a.seed,
              "wall_s": time.time() - t0}
    store = RunStore(a.out)
    write_report(store.table("episodes"), a.out, config, store)


if __name__ == "__main__":
    main()

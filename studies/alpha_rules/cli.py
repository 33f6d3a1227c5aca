"""Command-line entry of the alpha-rule study (``workbench run alpha-rules``)."""

from __future__ import annotations

import json
import time
from pathlib import Path

from studies.alpha_rules.config import AlphaRulesConfig
from workbench.study.entry import StudyEntry, profiles_in


def _declare(config: AlphaRulesConfig):
    from studies.alpha_rules.run import study

    return study(config.episodes, config.steps, config.seed, config.variances)


def _report_from(out: Path) -> Path:
    """report.md from the stored episodes (wall time from run.json, written by a run)."""
    from studies.alpha_rules.report import write_report
    from workbench.study import RunStore

    store = RunStore(out)
    manifest = store.manifest()
    run_file = Path(out) / "run.json"
    wall = json.loads(run_file.read_text())["wall_s"] if run_file.exists() else float("nan")
    config = {"episodes": manifest["config"]["episodes"], "steps": manifest["config"]["steps"],
              "seed": manifest["seed"], "wall_s": wall}
    write_report(store.table("episodes"), Path(out), config, store)
    return Path(out) / "report.md"


def _run(config: AlphaRulesConfig, out: Path, workers: int, scheduler: str | None) -> Path:
    from workbench.study import run_study
    from workbench.study.io import atomic_write_json

    t0 = time.time()
    run_study(_declare(config), out, workers=workers, scheduler=scheduler).raise_for_errors()
    atomic_write_json(Path(out) / "run.json", {"wall_s": time.time() - t0})
    return _report_from(out)


ENTRY = StudyEntry(
    name="alpha-rules",
    description="SA-RMPPI on the navigation map: how often the robust part acts, per alpha rule "
                "(issue 8, SPEC 10.3)",
    config_type=AlphaRulesConfig,
    profiles=profiles_in(Path(__file__).parent),
    run=_run,
    default_out=Path("reports/alpha_rules"),
    report=_report_from,
    declare=_declare,
)

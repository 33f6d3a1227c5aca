"""Command-line entry of the navigation study (``workbench run navigation``)."""

from __future__ import annotations

import json
from pathlib import Path

from studies.navigation.config import StudyConfig
from workbench.study.entry import PaperRow, StudyEntry, profiles_in


def _declare(config: StudyConfig):
    from studies.navigation.run import study

    return study(config)[0]


def _run(config: StudyConfig, out: Path, workers: int, scheduler: str | None) -> Path:
    from studies.navigation.run import run

    return run(config, out, workers=workers, scheduler=scheduler).report


def _paper(out: Path) -> list[PaperRow]:
    from studies.navigation.paper import TABLE_I

    cells = json.loads((Path(out) / "summary.json").read_text())["cells"]
    rows = []
    for c in cells:
        paper = TABLE_I.get(float(c["variance"]), {}).get(c["controller"])
        if paper is None:
            continue
        rows.append(PaperRow(
            f"{c['controller']} safety, variance {c['variance']:g}", f"{paper[0]}%",
            f"{100 * c['safety']:.0f}% [{100 * c['ci_low']:.0f}, {100 * c['ci_high']:.0f}], "
            f"n = {c['n']}",
            f"RMSE paper {paper[1]:g} m, ours "
            f"{'-' if c['rmse'] is None else format(c['rmse'], '.3f')} m"))
    return rows


ENTRY = StudyEntry(
    name="navigation",
    description="paper Sec. V / Table I: SA-RMPPI vs BaS-MPPI (+ RMPPI and crash-cost MPPI "
                "ablations) in the 30-obstacle field under velocity disturbances",
    config_type=StudyConfig,
    profiles=profiles_in(Path(__file__).parent),
    run=_run,
    default_out=Path("reports/navigation"),
    declare=_declare,
    paper=_paper,
)

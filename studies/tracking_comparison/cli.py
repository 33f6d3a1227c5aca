"""Command-line entry of the tracking comparison (``workbench run tracking``)."""

from __future__ import annotations

from pathlib import Path

from studies.tracking_comparison.config import StudyConfig
from workbench.study.entry import PaperRow, StudyEntry, profiles_in


def _run(config: StudyConfig, out: Path, workers: int, scheduler: str | None) -> Path:
    from studies.tracking_comparison.findings import NAMES
    from studies.tracking_comparison.run import run
    from workbench.study import fmt_rate

    outcome = run(config, out, workers=workers, scheduler=scheduler)
    for o in outcome.summary.methods:
        print(f"{NAMES[o.method]:20s} unsafe {fmt_rate(o.unsafe):22s} failure "
              f"{fmt_rate(o.failure):22s} n={o.n}")
    return outcome.report


def _declare(config: StudyConfig):
    from studies.tracking_comparison.methods import Setup
    from studies.tracking_comparison.run import study

    return study(config, Setup())[0]


def _report(out: Path) -> Path:
    """Rebuild report.md from a finished run (every task loaded, nothing computed)."""
    from studies.tracking_comparison.run import run
    from workbench.study import RunStore
    from workbench.study.config_io import load

    store = RunStore(out)
    config = load(StudyConfig, store.manifest()["config"])
    decl = _declare(config)
    missing = len(decl.tasks) - len(store.finished(decl.task_ids()))
    if missing:
        raise RuntimeError(f"{out}: {missing} of {len(decl.tasks)} tasks are not finished; "
                           "`workbench run tracking` with the same config completes them")
    return run(config, out, workers=0, progress=False).report


def _paper(out: Path) -> list[PaperRow]:
    import json

    from studies.tracking_comparison.findings import NAMES
    from studies.tracking_comparison.paper import PAPER

    summary = json.loads((Path(out) / "summary.json").read_text())
    ours = {m["method"]: m for m in summary["methods"]}
    rows = []
    for p in PAPER:
        if p.method not in ours:
            continue
        r = ours[p.method][p.metric]
        inside = p.band[0] <= r["value"] <= p.band[1]
        rows.append(PaperRow(
            f"{NAMES[p.method]}: {p.metric} rate", f"{p.value:.0%} ({p.text})",
            f"{r['value']:.1%} [{r['low']:.1%}, {r['high']:.1%}], n = {r['n']}",
            f"SPEC 14.4 band {p.band[0]:.0%}-{p.band[1]:.0%}: "
            f"{'inside' if inside else 'outside'}"))
    return rows


ENTRY = StudyEntry(
    name="tracking",
    description="paper Sec. III: ECBF-filtered iLQG, AL-iLQG and BaS-iLQG under control noise "
                "(unsafe and failure rates, radius and sensitivity sweeps)",
    config_type=StudyConfig,
    profiles=profiles_in(Path(__file__).parent),
    run=_run,
    default_out=Path("reports/tracking_comparison"),
    report=_report,
    declare=_declare,
    paper=_paper,
    aliases={k: f"base.{k}" for k in ("q_beta", "pole", "q_scale", "ecbf_noise", "noise_std")},
    figure="trajectories_bas.png",
)

"""Command-line entry of the free-energy bound study (``workbench run free-energy-bound``)."""

from __future__ import annotations

from pathlib import Path

from studies.free_energy_bound.config import StudyConfig
from workbench.study.entry import StudyEntry, profiles_in


def _run(config: StudyConfig, out: Path, workers: int, scheduler: str | None) -> Path:
    from studies.free_energy_bound.run import run

    return run(config, out, workers=workers, scheduler=scheduler).report


ENTRY = StudyEntry(
    name="free-energy-bound",
    description="Lemma 1 checked at every step of SA-RMPPI episodes: T1-T3d, local vs global "
                "Lipschitz constants",
    config_type=StudyConfig,
    profiles=profiles_in(Path(__file__).parent),
    run=_run,
    default_out=Path("reports/free_energy_bound"),
)

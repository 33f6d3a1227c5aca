"""Lemma 1 (the free-energy bound) checked at every step of SA-RMPPI episodes on the navigation
map: T1-T3d with local and global Lipschitz constants, stratified, with Wilson intervals."""

from pathlib import Path

from studies.free_energy_bound.config import StudyConfig
from workbench.study.spec import StudySpec

STUDY = StudySpec(
    name="free-energy-bound",
    description="Lemma 1 checked at every step of SA-RMPPI episodes: T1-T3d, local vs global "
                "Lipschitz constants",
    config_type=StudyConfig,
    directory=Path(__file__).parent,
    prepare="studies.free_energy_bound.shared:load_or_compute",
    tasks="studies.free_energy_bound.tasks:declare",
    summarise="studies.free_energy_bound.report:summary",
    report="studies.free_energy_bound.report:report",
)

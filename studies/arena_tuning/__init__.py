"""Fair tuning for the arena: the same optuna budget per (system, controller) on training maps
disjoint from the arena's test maps; ``make tune-arena`` ships the result as defaults."""

from pathlib import Path

from studies.arena.config import ArenaConfig
from workbench.study.spec import StudySpec

STUDY = StudySpec(
    name="arena-tuning",
    description="equal-budget optuna tuning of each arena controller on training maps",
    config_type=ArenaConfig,
    directory=Path(__file__).parent,
    tasks="studies.arena.tuning:declare",
    summarise="studies.arena.tuning:summary",
    report="studies.arena.tuning:report",
)

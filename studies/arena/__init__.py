"""The arena: safe-sampling controllers x systems x generated maps x disturbances, with
hand-tuned and equally-budgeted automatic tuning, paired statistics pooled over maps, and the
verdict on the paper's claim (i)."""

from pathlib import Path

from studies.arena.config import ArenaConfig
from workbench.study.spec import StudySpec

STUDY = StudySpec(
    name="arena",
    description="controllers x systems x generated maps x disturbances, fairly tuned; pooled "
                "paired statistics and the verdict on the paper's claim (i)",
    config_type=ArenaConfig,
    directory=Path(__file__).parent,
    tasks="studies.arena.tasks:declare",
    summarise="studies.arena.report:summary",
    report="studies.arena.report:report",
    figure="frontier.png",
)

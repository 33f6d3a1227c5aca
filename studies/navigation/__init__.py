"""Navigation (paper Sec. V, Table I): SA-RMPPI against BaS-MPPI and two ablations in the
30-obstacle field under velocity disturbances, with an alpha-rule sweep and the Fig. 4 batch."""

from pathlib import Path

from studies.navigation.config import StudyConfig
from workbench.study.spec import StudySpec

STUDY = StudySpec(
    name="navigation",
    description="paper Sec. V / Table I: SA-RMPPI vs BaS-MPPI (+ RMPPI and crash-cost MPPI "
                "ablations) in the 30-obstacle field under velocity disturbances; alpha-rule "
                "sweep",
    config_type=StudyConfig,
    directory=Path(__file__).parent,
    prepare="studies.navigation.tasks:prepare",
    tasks="studies.navigation.tasks:declare",
    summarise="studies.navigation.summary:summary",
    report="studies.navigation.report:report",
    paper="studies.navigation.paper:paper_rows",
)

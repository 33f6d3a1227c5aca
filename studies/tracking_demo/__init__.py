"""BaS-iLQG on the tracking scene for each barrier weight, each solution checked against IPOPT."""

from pathlib import Path

from studies.tracking_demo.config import DemoConfig
from workbench.study.spec import StudySpec

STUDY = StudySpec(
    name="tracking-demo",
    description="BaS-iLQG on the tracking scene against IPOPT on the same embedded problem",
    config_type=DemoConfig,
    directory=Path(__file__).parent,
    tasks="studies.tracking_demo.tasks:declare",
    summarise="studies.tracking_demo.report:summary",
    report="studies.tracking_demo.report:report",
    paper="studies.tracking_demo.report:paper_rows",
    figure="trajectories.png",
)

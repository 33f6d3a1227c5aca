"""Tracking comparison (paper Sec. III): ECBF-filtered iLQG, AL-iLQG and BaS-iLQG tracking an
unsafe reference under control noise; unsafe and failure rates, radius and sensitivity sweeps."""

from pathlib import Path

from studies.tracking_comparison.config import StudyConfig
from workbench.study.spec import StudySpec

STUDY = StudySpec(
    name="tracking",
    description="paper Sec. III: ECBF-filtered iLQG, AL-iLQG and BaS-iLQG under control noise "
                "(unsafe and failure rates, radius and sensitivity sweeps)",
    config_type=StudyConfig,
    directory=Path(__file__).parent,
    tasks="studies.tracking_comparison.tasks:declare",
    summarise="studies.tracking_comparison.report:summary",
    report="studies.tracking_comparison.report:report",
    paper="studies.tracking_comparison.paper:paper_rows",
    aliases={k: f"base.{k}" for k in ("q_beta", "pole", "q_scale", "ecbf_noise", "noise_std")},
    figure="trajectories_bas.png",
)

"""Sampling safety: the field's safe-sampling methods (BaS-MPPI, SA-RMPPI, Tube-MPPI, per-sample
CBF projection, Shield-MPPI, a gatekeeper, SAIS with AL and ECBF gains) on one sampler and one
map, under velocity disturbances, paired by realisation; decides the paper's claim (1)."""

from pathlib import Path

from studies.sampling_safety.config import StudyConfig
from workbench.study.spec import StudySpec

STUDY = StudySpec(
    name="sampling-safety",
    description="the field's safe-sampling methods on one sampler: collision-free samples, "
                "ESS, ms per step and closed-loop safety; decides the paper's claim (1)",
    config_type=StudyConfig,
    directory=Path(__file__).parent,
    prepare="studies.sampling_safety.tasks:prepare",
    tasks="studies.sampling_safety.tasks:declare",
    summarise="studies.sampling_safety.report:summary",
    report="studies.sampling_safety.report:report",
    cost="studies.sampling_safety.tasks:cost_plan",
    figure="frontier.png",
)

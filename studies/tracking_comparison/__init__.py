"""Tracking comparison (paper Sec. III, SPEC 6, 12.1): ECBF-filtered iLQG, AL-iLQG and BaS-iLQG
tracking an unsafe reference under control noise, Monte Carlo with Wilson intervals.

config (frozen, validated) -> methods (nominal solutions) -> rollouts (vectorised closed loops)
-> tasks (task descriptions, task function, plan) -> run (on workbench.study) -> summary (typed,
metrics defined once) -> findings (claims from the numbers) -> report (figures, report.md);
paper.py holds the paper's numbers and the assumed values.
"""

"""Tracking comparison (paper Sec. III, SPEC 6, 12.1): ECBF-filtered iLQG, AL-iLQG and BaS-iLQG
tracking an unsafe reference under control noise, Monte Carlo with Wilson intervals.

config (frozen, validated) -> methods (nominal solutions) -> rollouts (closed loops, metrics)
-> run (tasks, resume, workers, tidy data) -> report (figures, report.md, from the data only).
"""

"""Navigation study (paper Sec. V, Table I, Figs. 4-6; SPEC 3.2, 12.2, 14.2-14.4): SA-RMPPI vs
BaS-MPPI in the 30-obstacle field under velocity disturbances, with two ablations (RMPPI with
plain iLQG gains, MPPI with a crash cost only) and an alpha sweep.

config (frozen, validated; scene: the map) -> tasks (one realisation per task, common random
numbers; illustration: Fig. 4) -> metrics (per-episode rows) -> run (on workbench.study) ->
summary (typed cells, paired comparisons) -> findings (SPEC 14.4 claims) and evidence
(internals, ablations, alpha) -> figures, report; paper.py holds Table I and the assumed values.
"""

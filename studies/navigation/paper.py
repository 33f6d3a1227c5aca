"""What the paper reports for the navigation study (Table I, SPEC 14.2) and the reproduction
criteria (SPEC 14.4); every assumed value of the study is listed with its source."""

from __future__ import annotations

# Table I [P]: safety % and RMSE [m] over 100 realisations per variance
TABLE_I = {
    0.0: {"sa_rmppi": (97, 0.1815), "bas_mppi": (99, 0.002)},
    5.0: {"sa_rmppi": (91, 0.2021), "bas_mppi": (74, 0.018)},
    10.0: {"sa_rmppi": (87, 0.2117), "bas_mppi": (63, 0.0312)},
    50.0: {"sa_rmppi": (61, 0.3062), "bas_mppi": (47, 0.0536)},
    100.0: {"sa_rmppi": (49, 0.3634), "bas_mppi": (31, 0.0701)},
}

CLAIMS = {
    "safer": "SA-RMPPI is safer than BaS-MPPI at every variance > 0 (paired, 95% interval of "
             "the difference above 0)",
    "rmse": "BaS-MPPI has the lower RMSE (safe runs) at every variance",
    "monotone": "safety decreases with the variance, for both controllers",
    "magnitude": "each cell within 10 points of Table I in safety",
    "rmse_factor": "each RMSE within a factor of 2 of Table I",
    "reached": "safe runs end within 1 m of the goal",
}

ASSUMED = {
    "map": "SPEC 3.2 generator, fixed seed (workbench.scenes.NavigationScene) [A]",
    "episode": "20 s = 1000 steps from rest at the start, stop at the first crash [A]",
    "disturbance": "w = dt N(0, variance I) on the velocity (SPEC 2.3) [P/X]",
    "sampling": "N = 1024, T = 100, one iteration; sigma = 5, lambda = 10, q_beta = 0.01 "
                "(tuned, SPEC 8.2 values stall undisturbed, NOTES.md) [A]",
    "candidates": "9 candidates x 64 samples (MPPI-G) [X]",
    "K_safe": "Q_K = diag(500, 500, 100, 100), R_K = I, q_beta_K = 1, one derivative "
              "evaluation + backward pass about the nominal trajectory [A]",
    "alpha": "progress-indexed: (1 + kappa) x the free energy an undisturbed run has at the "
             "same distance to the goal, calibrated per controller (SPEC 10.3) [A]",
    "rmse": "over safe realisations, final position (SPEC 12.2) [A]",
    "reached": "final distance <= 1 m [P]",
}

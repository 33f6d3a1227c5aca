"""How the tracking comparison words its results: the methods' display names (full and short)
and the swept parameters' names, shared by the findings, the paper comparison and the report."""

NAMES = {"ecbf": "ECBF-filtered iLQG", "al": "AL-iLQG", "bas": "BaS-iLQG"}
SHORT = {"ecbf": "ECBF", "al": "AL", "bas": "BaS"}
PARAM_NAMES = {"q_beta": "q_beta (BaS)", "pole": "ECBF poles p1 = p2", "q_scale": "Q scale",
               "ecbf_noise": "ECBF noise vs filter", "noise_std": "noise std"}

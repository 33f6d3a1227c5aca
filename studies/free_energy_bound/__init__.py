"""Lemma 1 (free-energy bound) checked numerically on SA-RMPPI episodes (issue 12, part 3):
config -> shared -> tasks -> run -> summary (failures) -> findings -> report; paper.py."""

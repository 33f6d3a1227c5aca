"""Activation of SA-RMPPI's robust machinery under each alpha rule (issue: SA-RMPPI)."""

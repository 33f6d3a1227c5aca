"""iLQG and its variants: one core, two pass backends (compiled C and the NumPy twin)."""

from workbench.ilqg.solver import ILQGOptions, ILQGResult, Iteration, ilqg, make_passes

__all__ = ["ILQGOptions", "ILQGResult", "Iteration", "ilqg", "make_passes"]

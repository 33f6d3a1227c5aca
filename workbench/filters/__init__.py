"""Safety filters applied to a nominal control: the exponential-CBF quadratic program."""

from workbench.filters.ecbf import ECBFFilter, ECBFOptions

__all__ = ["ECBFFilter", "ECBFOptions"]

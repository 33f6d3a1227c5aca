"""ECBF filter options: OSQP's iteration limit is bounded and the poles are numbers, not
bools."""

from __future__ import annotations

import numpy as np
import pytest

from workbench.filters.ecbf import MAX_OSQP_ITER, ECBFOptions


def test_the_osqp_iteration_limit_is_bounded():
    """Before: max_iter = 10**12 was accepted and handed to OSQP."""
    with pytest.raises(ValueError, match=rf"^ECBFOptions\.max_iter = {10**12} is invalid: must "
                       rf"be an integer in \[1, {MAX_OSQP_ITER}\]$"):
        ECBFOptions(max_iter=10**12)
    assert ECBFOptions(max_iter=MAX_OSQP_ITER).max_iter == 10**6


@pytest.mark.parametrize("poles", [(True, 5.0), (5.0, np.True_)])
def test_a_bool_pole_is_refused(poles):
    """Before: (True, 5.0) became the poles (1.0, 5.0)."""
    with pytest.raises(ValueError, match=r"^ECBFOptions\.poles = \(.*True.*\) is invalid: need "
                       r"two finite poles p1, p2 > 0 \(numbers, not true/false\)$"):
        ECBFOptions(poles=poles)
    assert ECBFOptions(poles=(np.float64(2.0), 3)).poles == (2.0, 3.0)

"""The shared validators: bool is never a number, a number never a flag."""

from __future__ import annotations

import numpy as np
import pytest

from workbench.validation import positive, real_or_inf


@pytest.mark.parametrize("value", [1.5, -2, np.float32(3.0), np.inf])
def test_real_or_inf_accepts_numbers_and_plus_inf(value):
    assert real_or_inf("a", value) == float(value)


@pytest.mark.parametrize("value", [True, np.False_, np.nan, -np.inf, "1", None, np.ones(1)])
def test_real_or_inf_rejects_bool_nan_minus_inf_and_non_numbers(value):
    with pytest.raises(ValueError, match=r"^a = .* is invalid: must be a number or \+inf$"):
        real_or_inf("a", value)


@pytest.mark.parametrize(("value", "allow_zero"), [(True, False), (np.True_, True), (0.0, False),
                                                   (-1.0, True), (np.inf, True), ("2", True)])
def test_positive_is_real_above_zero(value, allow_zero):
    with pytest.raises(ValueError, match=r"^b = .* is invalid: must be a finite number >=? 0$"):
        positive("b", value, allow_zero=allow_zero)
    assert positive("b", 2) == 2.0 and positive("b", 0, allow_zero=True) == 0.0

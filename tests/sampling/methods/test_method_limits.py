"""The methods' counts have upper bounds and refuse bools: a typo fails when the config is
built, naming the field, the value and the range, instead of looping or allocating at run time."""

from __future__ import annotations

import re

import numpy as np
import pytest

from workbench.sampling.methods.gatekeeper import MAX_HORIZON, GatekeeperConfig
from workbench.sampling.methods.shield import MAX_REPAIR_STEPS, ShieldConfig

COUNTS = [(ShieldConfig, "repair_steps", MAX_REPAIR_STEPS),
          (GatekeeperConfig, "horizon", MAX_HORIZON)]


@pytest.mark.parametrize(("cls", "name", "limit"), COUNTS)
def test_counts_accept_their_range(cls, name, limit):
    for v in (1, limit, np.int64(limit)):
        assert getattr(cls(**{name: v}), name) == v


@pytest.mark.parametrize(("cls", "name", "limit"), COUNTS)
@pytest.mark.parametrize("bad", ["above", "huge", True, False, np.bool_(True), 0, -1, 2.0,
                                 "10", None])
def test_counts_refuse_bools_and_out_of_range(cls, name, limit, bad):
    value = {"above": limit + 1, "huge": 10**12}.get(bad, bad) if isinstance(bad, str) else bad
    field = f"{cls.__name__}.{name}"
    with pytest.raises(ValueError, match=re.escape(field)) as err:
        cls(**{name: value})
    assert f"in [1, {limit}]" in str(err.value)

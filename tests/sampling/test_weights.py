"""Importance weights: max-shift, shift invariance, free energy vs high precision, ESS."""

from __future__ import annotations

from decimal import Decimal, localcontext
from math import log

import numpy as np
import pytest

from workbench.sampling.weights import importance_weights


def test_weights_are_normalised_and_shift_invariant(rng):
    S = np.round(rng.normal(1e3, 30, 500) * 2**20) / 2**20  # dyadic: S + 1e6 is exact
    a, b = importance_weights(S, 2.0), importance_weights(S + 1e6, 2.0)
    assert a.w.sum() == pytest.approx(1.0, abs=1e-14)
    np.testing.assert_array_equal(a.w, b.w)  # only differences S - min S enter
    assert b.free_energy - a.free_energy == pytest.approx(1e6, rel=1e-12)
    assert a.rho == S.min()


def test_huge_costs_do_not_underflow_everything():
    S = np.array([1e9, 1e9 + 1.0, 1e9 + 2.0])
    w = importance_weights(S, 1.0).w
    np.testing.assert_allclose(w, np.exp(-np.arange(3)) / np.exp(-np.arange(3)).sum())


def test_free_energy_equals_high_precision(rng):
    S = rng.normal(50, 20, 64)
    lam = 0.7
    with localcontext() as ctx:
        ctx.prec = 50
        L = Decimal(lam)
        total = sum((-Decimal(float(s)) / L).exp() for s in S) / len(S)
        direct = -L * total.ln()
    assert importance_weights(S, lam).free_energy == pytest.approx(float(direct), rel=1e-13)


def test_ess_hand_cases():
    assert importance_weights(np.zeros(10), 1.0).ess == pytest.approx(10.0)
    assert importance_weights(np.array([0.0, 1e6, 1e6]), 1.0).ess == pytest.approx(1.0)
    S = np.array([0.0, log(3.0)])  # weights 3/4, 1/4 -> ESS = 1 / (9/16 + 1/16) = 1.6
    assert importance_weights(S, 1.0).ess == pytest.approx(1.6)


def test_non_finite_costs_never_reach_the_weights():
    S = np.array([1.0, np.nan, np.inf, 2.0, -np.inf])
    res = importance_weights(S, 1.0)
    assert np.all(np.isfinite(res.w)) and res.w[1] == res.w[2] == res.w[4] == 0.0
    assert res.n_finite == 2 and res.w.sum() == pytest.approx(1.0)
    none = importance_weights(np.array([np.nan, np.inf]), 1.0)
    assert not none.valid and np.all(none.w == 0)


@pytest.mark.parametrize("lam", [0.0, -1.0, np.inf, np.nan])
def test_bad_temperature_is_rejected(lam):
    with pytest.raises(ValueError, match="lambda"):
        importance_weights(np.zeros(3), lam)

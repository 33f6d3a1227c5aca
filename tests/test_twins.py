"""Every fast path equals its twin per element at relative tolerance (the registry in
``tests/twins.py``), and the harness's comparison fails on a deliberately broken twin."""

from __future__ import annotations

import functools

import numpy as np
import pytest
from twins import CASES, TwinCase, disagreements, element_error, mismatch

BY_NAME = {case.name: case for case in CASES}


@functools.cache
def inputs(name: str):
    return BY_NAME[name].inputs()


@functools.cache
def outputs(name: str):
    """(fast, twin) outputs of a case, computed once per session."""
    case = BY_NAME[name]
    i = inputs(name)
    return case.fast(i), case.twin(i)


@pytest.mark.parametrize("name", list(BY_NAME))
def test_fast_path_equals_its_twin_per_element(name):
    fast, twin = outputs(name)
    assert set(fast) == set(twin)
    assert any(np.size(v) > 1 for v in twin.values())  # the case compares whole arrays
    bad = disagreements(BY_NAME[name], fast, twin)
    assert not bad, bad


def broken(twin: dict, name: str, rtol: float) -> dict:
    """The twin's outputs with one element of output ``name`` moved by 100 rtol relative
    (booleans: flipped; integers: plus one; strings and None: replaced)."""
    out = dict(twin)
    v = twin[name]
    if v is None or isinstance(v, str):
        out[name] = "broken"
        return out
    a = np.array(v, copy=True, order="C")  # C order: ``flat`` below is a view of ``a``
    flat = a.reshape(-1)
    if a.dtype == bool:
        flat[0] = not flat[0]
    elif a.dtype.kind in "iu":
        flat[0] += 1
    else:
        j = int(np.argmax(np.where(np.isfinite(flat), np.abs(flat), -1.0)))
        flat[j] = flat[j] + 100.0 * rtol * max(abs(float(flat[j])), 1.0)
    out[name] = a if a.ndim else a.item()
    return out


@pytest.mark.parametrize("name", list(BY_NAME))
def test_harness_fails_on_a_broken_twin(name):
    """Each output of the twin, broken in one element, is reported as a mismatch (and only
    that output)."""
    case = BY_NAME[name]
    fast, twin = outputs(name)
    for out in twin:
        if np.size(twin[out]) == 0:
            continue
        bad = disagreements(case, fast, broken(twin, out, case.rtol))
        assert set(bad) == {out}, (out, bad)


def test_tolerance_is_relative_and_absolute_only_below_the_floor():
    assert element_error([1e6], [1e6 + 1.0], 1.0) == pytest.approx(1e-6)
    assert element_error([1e-3], [2e-3], 1.0) == pytest.approx(1e-3)  # absolute below 1
    assert element_error([np.nan, 2.0], [np.nan, 2.0], 1.0) == 0.0
    assert element_error([np.nan], [1.0], 1.0) == np.inf
    assert element_error(np.zeros(3), np.zeros(4), 1.0) == np.inf
    assert mismatch({"a": np.array([True])}, {"a": np.array([False])}, 1.0) == {"a": np.inf}
    assert mismatch({"a": 1.0}, {}, 1.0) == {"a": np.inf}
    with pytest.raises(ValueError, match=r"TwinCase\.rtol"):
        TwinCase("x", dict, dict, tuple, rtol=0.0)


def test_harness_fails_on_a_mutated_twin():
    """The MPPI twin run with lambda 1e-4 larger (the likelihood-ratio weight): the harness
    reports the costs, and only them."""
    from dataclasses import replace

    case = BY_NAME["mppi kernel / mppi_twin"]
    sk, model, sp, sampler, c, x0, U, sais = inputs(case.name)
    mutated = (sk, model, sp, sampler, replace(c, lam=c.lam * (1 + 1e-4)), x0, U, sais)
    fast, _ = outputs(case.name)
    bad = disagreements(case, fast, case.twin(mutated))
    assert set(bad) == {"S"} and bad["S"] > 1e3 * case.rtol, bad

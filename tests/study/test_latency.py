"""Step-time statistics: percentiles are numpy's on the given times, bad times are refused
naming the field, the cost order groups methods whose intervals overlap, and orders that
contradict each other are told apart from orders that differ only in ties."""

from __future__ import annotations

import math

import numpy as np
import pytest

from workbench.study.latency import (
    Latency,
    cost_order,
    latency_table,
    mean_interval,
    orders_agree,
    step_table,
)


def test_latency_is_the_percentiles_of_the_times():
    rng = np.random.default_rng(3)
    ms = rng.gamma(2.0, 1.5, size=1000)
    lat = Latency.of(ms)
    want = np.percentile(ms, [50, 95, 99])
    got = np.array([lat.p50_ms, lat.p95_ms, lat.p99_ms])
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=0)
    assert lat.max_ms == ms.max() and lat.n == 1000
    assert lat.mean_ms == pytest.approx(ms.mean(), rel=1e-12)
    assert lat.p50_ms <= lat.p95_ms <= lat.p99_ms <= lat.max_ms


def test_a_single_slow_step_is_the_tail_not_the_median():
    ms = np.r_[np.full(99, 2.0), 40.0]  # p99 at order statistic 98.01
    lat = Latency.of(ms)
    assert lat.p50_ms == 2.0 and lat.max_ms == 40.0
    assert lat.p99_ms == pytest.approx(2.0 + 0.01 * 38.0, rel=1e-12)


@pytest.mark.parametrize("values, match", [
    ([], r"^wall_ms = \[\] is invalid: need at least one step time"),
    ([1.0, -0.5], r"^wall_ms = .*-0\.5.* is invalid: step times must be finite and >= 0"),
    ([1.0, math.nan], r"^wall_ms = .*nan.* is invalid"),
])
def test_bad_times_are_refused_naming_the_field(values, match):
    with pytest.raises(ValueError, match=match):
        Latency.of(values, "wall_ms")


def test_step_table_needs_one_cpu_time_per_step():
    t = step_table([0.001, 0.002], [0.0005, 0.003])
    np.testing.assert_array_equal(t["step"], [0, 1])
    np.testing.assert_allclose(t["wall_ms"], [1.0, 2.0], rtol=1e-12)
    np.testing.assert_allclose(t["cpu_ms"], [0.5, 3.0], rtol=1e-12)
    with pytest.raises(ValueError, match=r"^cpu_s = \[0\.001\] is invalid: need one CPU "
                       r"time per step \(1 given for 2 steps\)"):
        step_table([0.001, 0.002], [0.001])


def test_cost_order_ties_overlapping_intervals():
    rng = np.random.default_rng(11)
    a = 1.0 + 0.01 * rng.standard_normal(50)
    b = 1.001 + 0.01 * rng.standard_normal(50)  # overlaps a
    c = 3.0 + 0.01 * rng.standard_normal(50)
    order = cost_order({"c": c, "b": b, "a": a})
    assert order[-1] == ("c",) and len(order) == 2
    assert set(order[0]) == {"a", "b"}
    (a_lo, a_hi), (b_lo, b_hi) = mean_interval(a)[1:], mean_interval(b)[1:]
    assert a_lo <= b_hi and b_lo <= a_hi


def test_orders_agree_up_to_ties_only():
    assert orders_agree((("a", "b"), ("c",)), (("a",), ("b",), ("c",)))
    assert orders_agree((("a",), ("b", "c")), (("a", "b", "c"),))
    assert not orders_agree((("a",), ("b",)), (("b",), ("a",)))
    assert not orders_agree((("a",), ("b", "c")), (("c",), ("a", "b")))


def test_latency_table_rows():
    rows = latency_table({"m": ([1.0, 2.0, 3.0], [0.5, 0.5, 0.5])})
    assert rows == [["m", "0.50", "2.00", "2.00", "2.90", "2.98", "3.00", "3"]]

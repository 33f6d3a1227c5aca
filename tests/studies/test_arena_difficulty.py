"""The arena's difficulty calibration: the log-scale bisection lands in the band for monotone
stand-in crash rates (and says so when it cannot), the bench's episodes are reproducible (one
stream per system, map and realisation) and feed the bisection, and the uninformative label
covers each case."""

from __future__ import annotations

import math

import numpy as np
import pytest

from studies.arena import STUDY
from studies.arena.difficulty import (
    BAND,
    TARGET,
    TOLERANCE,
    Bench,
    bisect_scale,
    calibrate,
    main,
    streams,
    uninformative,
)
from workbench.study.runner import profile_config


def log_ramp(lo: float, hi: float):
    """0 at ``lo``, 1 at ``hi``, linear in log(scale) between: a monotone crash rate."""
    def rate(scale: float) -> float:
        return float(np.clip(math.log(scale / lo) / math.log(hi / lo), 0.0, 1.0))
    return rate


def counted(rate, n: int):
    """The rate rounded down to whole episodes of ``n`` (a staircase, as measured)."""
    return lambda scale: math.floor(rate(scale) * n) / n


@pytest.mark.parametrize("oracle", [
    log_ramp(1e-3, 1.0),  # target at 10**-1.8
    log_ramp(0.2, 0.3),  # steep: the band is a sliver of the bracket
    counted(log_ramp(0.01, 5.0), 24),  # 24 episodes per probe
    lambda s: 1.0 - math.exp(-s / 0.05),  # saturating
])
def test_bisection_lands_in_the_band_for_monotone_rates(oracle):
    calls: list[float] = []

    def rate(scale):
        calls.append(scale)
        return oracle(scale)

    b = bisect_scale(rate, 1e-4, 10.0, evaluations=12)
    assert b.in_band and BAND[0] <= b.chosen.rate <= BAND[1]
    assert abs(b.chosen.rate - TARGET) <= TOLERANCE
    assert b.chosen == b.probes[-1]  # it stops at the first probe within tolerance
    assert [p.level_scale for p in b.probes] == calls  # each probe evaluated once
    assert calls[0] == pytest.approx(math.sqrt(1e-4 * 10.0))  # the geometric midpoint
    lo, hi = 1e-4, 10.0
    for p in b.probes:  # every probe halves the log bracket, moving towards the target
        assert p.level_scale == pytest.approx(math.sqrt(lo * hi))
        lo, hi = (p.level_scale, hi) if p.rate < TARGET else (lo, p.level_scale)


def test_bisection_probes_the_bracket_only_and_reports_a_missed_band():
    b = bisect_scale(lambda s: 0.0, 0.01, 1.0, evaluations=5)  # never crashes
    assert not b.in_band and len(b.probes) == 5
    scales = [p.level_scale for p in b.probes]
    assert scales == sorted(scales) and all(0.01 < s < 1.0 for s in scales)
    assert b.chosen == b.probes[0]  # equally far: the earliest
    b = bisect_scale(lambda s: 1.0, 0.01, 1.0, evaluations=3)  # always crashes
    assert not b.in_band and [p.level_scale for p in b.probes] == sorted(
        (p.level_scale for p in b.probes), reverse=True)
    # a rate that jumps over the tolerance window: the closest probe, still in the band
    b = bisect_scale(lambda s: 0.25 if s < 0.1 else 0.55, 0.01, 1.0, evaluations=4)
    assert b.in_band and abs(b.chosen.rate - TARGET) == pytest.approx(0.15)


@pytest.mark.parametrize("kwargs, field", [
    ({"low": 1.0, "high": 1.0}, "high"), ({"low": 0.0}, "low"),
    ({"target": 0.7}, "target"), ({"evaluations": 0}, "evaluations"),
    ({"band": (0.2, 1.5)}, r"band\[1\]"),
])
def test_bisection_checks_its_arguments(kwargs, field):
    args = {"low": 0.01, "high": 1.0, **kwargs}
    with pytest.raises(ValueError, match=rf"^{field}"):
        bisect_scale(lambda s: 0.4, args.pop("low"), args.pop("high"), **args)


def test_uninformative_names_each_case():
    assert "every controller's rate is 0 %" in uninformative({"a": 0.0, "b": 0.0}, 6)
    assert "every controller's rate is 100 %" in uninformative({"a": 1.0, "b": 1.0}, 6)
    assert "the only controller's rate is 0 %" in uninformative({"a": 0.0}, 6)
    assert "within one episode" in uninformative({"a": 0.5, "b": 4 / 6, "c": 0.5}, 6)
    assert "within one episode" in uninformative({"a": 0.0, "b": 1 / 6}, 6)
    assert uninformative({"a": 0.5, "b": 5 / 6}, 6) is None  # two episodes apart
    assert "within one episode" in uninformative({"a": 0.0, "b": 1.0}, 1)  # one episode each
    assert uninformative({"a": 0.0, "b": 1.0}, 2) is None
    assert uninformative({"a": 0.5}, 6) is None  # one controller: nothing to compare
    with pytest.raises(ValueError, match=r"^rates"):
        uninformative({}, 6)
    with pytest.raises(ValueError, match=r"^n"):
        uninformative({"a": 0.5}, 0)
    with pytest.raises(ValueError, match=r"^rates\['a'\]"):
        uninformative({"a": 1.5}, 6)


@pytest.fixture(scope="module")
def tiny():
    return profile_config(STUDY, "tiny")


def test_bench_episodes_are_reproducible_and_drive_the_bisection(tiny):
    a, b = streams("unicycle", 3, 1), streams("unicycle", 3, 1)
    assert all(np.array_equal(x.standard_normal(4), y.standard_normal(4))
               for x, y in zip(a, b, strict=True))
    assert not np.array_equal(streams("unicycle", 3, 2)[1].standard_normal(4),
                              streams("unicycle", 3, 1)[1].standard_normal(4))
    bench = Bench(tiny, "unicycle", (0,), realisations=2)
    m1 = bench.measure(0.45, ("theta",), levels=(50.0,))
    m2 = bench.measure(0.45, ("theta",), levels=(50.0,))
    assert m1 == m2 and m1.crashes[50.0].n == 2 and m1.goal is not None and m1.goal.n == 2
    assert m1.pooled.n == 2 and any("crash at level 50" in line for line in m1.lines())
    # the bisection drives the bench: each probe is the crash rate over maps x levels
    seen: list[str] = []
    b = calibrate(bench, ("theta",), 0.1, 10.0, levels=(50.0, 100.0), evaluations=1,
                  report=seen.append)
    assert b.probes[0].level_scale == pytest.approx(1.0) and len(b.probes) == 1
    assert any("level 100" in line for line in seen)
    with pytest.raises(ValueError, match=r"^system"):
        Bench(tiny, "hovercraft", (0,))
    with pytest.raises(ValueError, match=r"^seeds"):
        Bench(tiny, "unicycle", ())


def test_command_prints_what_it_measured(capsys):
    assert main(["--system", "unicycle", "--states", "theta", "--scale", "0.45", "--profile",
                 "tiny", "--maps", "1", "--realisations", "1", "--no-goal"]) == 0
    out = capsys.readouterr().out
    assert "disturbed ('theta',), level_scale 0.45" in out and "crash at level 100" in out
    assert "maps spec 0..0" in out and "realisations 1..1" in out

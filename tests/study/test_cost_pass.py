"""The cost pass: methods advance in lock step (one step of each, in a random order, then the
next), the warm-up round is not recorded, the paired order separates what differs and ties what
does not (checked by simulation against known ratios), and the runner measures it once per run,
keeps it on a rerun and never measures it when a report is rebuilt."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from workbench.study import TaskOutput
from workbench.study.cost_pass import (
    RESOLUTION,
    CostPlan,
    apart,
    load_pass,
    order_text,
    pass_costs,
    pass_order,
    run_pass,
    separated,
    stored_pass,
)
from workbench.study.runner import rebuild_report, run
from workbench.study.spec import Declaration, StudySpec, Summary


def _episode(log: list, name: str, steps: int):
    def run():
        for k in range(steps):
            log.append((name, k))
            yield
    return run


def test_lock_step_rounds_and_warm_up(tmp_path):
    log: list = []
    lengths = {"a": 5, "b": 5, "c": 3}  # c's episode ends early (a crash)
    plan = CostPlan({n: _episode(log, n, s) for n, s in lengths.items()}, rounds=3, seed=1,
                    what="toy")
    got = run_pass(plan, tmp_path, "hash")
    # warm-up plus 3 rounds were run; only the 3 rounds are recorded
    assert len(log) == 4 * sum(lengths.values())
    assert got.table.groupby("method").size().to_dict() == {n: 3 * s for n, s in lengths.items()}
    assert sorted(got.table["round"].unique()) == [0, 1, 2]
    # lock step: in each round, every live method does step k before any does step k + 1
    per_round = sum(lengths.values())
    orders = set()
    for r in range(4):
        seq = log[r * per_round:(r + 1) * per_round]
        for i in range(len(seq) - 1):
            assert seq[i + 1][1] >= seq[i][1]
        first = tuple(n for n, k in seq if k == 0)
        assert sorted(first) == ["a", "b", "c"]
        orders.add(first)
    assert len(orders) > 1  # the order within a step is drawn, not fixed
    # stored and read back, for these tasks only
    back = load_pass(tmp_path, "hash")
    assert back is not None and back.meta["rounds"] == 3 and back.meta["what"] == "toy"
    pd.testing.assert_frame_equal(back.table, got.table)
    assert load_pass(tmp_path, "other tasks") is None
    assert load_pass(tmp_path / "empty") is None


def test_plan_refuses_bad_sizes():
    with pytest.raises(ValueError, match=r"CostPlan\.rounds"):
        CostPlan({"a": lambda: iter(())}, rounds=1, seed=0, what="")
    with pytest.raises(ValueError, match=r"CostPlan\.runs"):
        CostPlan({}, rounds=2, seed=0, what="")


def _table(truth: dict[str, float], rounds: int, noise: float, drift: float,
           rng: np.random.Generator, steps: int = 4) -> pd.DataFrame:
    """A pass's table with known costs: each round slows every method alike by a lognormal
    factor (``drift``), each method-round mean has its own lognormal error (``noise``)."""
    rows = []
    for r in range(rounds):
        machine = np.exp(drift * rng.standard_normal())
        for name, ms in truth.items():
            mean = ms * machine * np.exp(noise * rng.standard_normal())
            rows.append(pd.DataFrame({"method": name, "round": r, "step": np.arange(steps),
                                      "wall_ms": mean, "cpu_ms": mean}))
    return pd.concat(rows, ignore_index=True)


def _log_ratios(ratio: float, rounds: int, noise: float, drift: float,
                rng: np.random.Generator) -> np.ndarray:
    """Per-round log-ratios of two methods' mean costs, a true ``ratio`` apart: each round
    slows both alike by a lognormal factor (``drift``, cancels in the ratio), each method-round
    mean has its own lognormal error (``noise``)."""
    machine = drift * rng.standard_normal(rounds)
    a = np.log(ratio) + machine + noise * rng.standard_normal(rounds)
    return a - (machine + noise * rng.standard_normal(rounds))


def test_separation_rate_at_the_resolution():
    """Two methods whose costs differ by exactly the resolution: separated in about 2.5 % of
    passes (one side of a 95 % interval); equal methods less often still; without a
    resolution, equal methods in about 5 %. The table-level function agrees with the core."""
    rng = np.random.default_rng(7)
    edge = 1.0 + RESOLUTION
    at_edge = sum(apart(_log_ratios(edge, 6, 0.02, 0.3, rng)) for _ in range(20000))
    assert 400 <= at_edge <= 600, at_edge  # binomial(20000, 0.025): 500 +- 4.5 sd
    equal = sum(apart(_log_ratios(1.0, 6, 0.02, 0.3, rng)) for _ in range(20000))
    assert equal < at_edge / 2, (equal, at_edge)
    plain = sum(apart(_log_ratios(1.0, 6, 0.02, 0.3, rng), 0.0) for _ in range(20000))
    assert 860 <= plain <= 1140, plain  # binomial(20000, 0.05): 1000 +- 4.5 sd
    for _ in range(20):
        t = _table({"a": 5.0 * edge, "b": 5.0}, 6, 0.02, 0.3, rng)
        means = t.groupby(["method", "round"])["cpu_ms"].mean().unstack("round")
        assert separated(t, "a", "b") == apart(np.log(means.loc["a"]) - np.log(means.loc["b"]))


def test_differences_are_separated_and_ordered():
    """An 8 % difference with 1 % noise per round and 30 % drift between rounds: separated in
    nearly every pass, in the right direction."""
    rng = np.random.default_rng(8)
    truth = {"cheap": 3.0, "x": 5.0, "y": 5.0, "dear": 5.4}
    right = 0
    for _ in range(100):
        t = _table(truth, 6, 0.01, 0.3, rng)
        order = pass_order(t)
        right += order[0] == ("cheap",) and order[-1] == ("dear",)
        assert set(order[0]) | set().union(*order[1:]) == set(truth)
    assert right >= 95, right
    costs = pass_costs(_table(truth, 6, 0.0, 0.0, rng))
    names = list(costs)
    assert names[0] == "cheap" and names[-1] == "dear"
    assert costs["dear"].cpu_ms == pytest.approx(5.4, rel=1e-12)


def test_order_ties_chain_and_text():
    rng = np.random.default_rng(9)
    t = _table({"a": 1.0, "b": 1.0, "c": 2.0}, 8, 0.001, 0.0, rng)
    order = pass_order(t)
    assert order[-1] == ("c",)
    assert order_text((("a",), ("b", "c")), {"a": "A", "b": "B", "c": "C"}) == "A < {B, C}"


# --- the runner: measured once per run, kept on a rerun, never by a rebuild -----------------


@dataclass(frozen=True)
class ToyConfig:
    seed: int = 0


@dataclass(frozen=True)
class Draw:
    i: int


def _task(task, ctx, config):
    return TaskOutput(tables={"draws": {"x": np.array([ctx.rng().standard_normal()])}})


CALLS: list = []


def _cost(finished):
    CALLS.append(finished.out)

    def run():
        for _ in range(3):
            yield
    return CostPlan({"m": run, "n": run}, rounds=2, seed=0, what="toy episode")


def _summary(finished):
    got = stored_pass(finished)
    return Summary({"measured": got is not None}, got)


def _report(finished, summary):
    path = finished.out / "report.md"
    path.write_text("pass: " + ("yes" if summary.value is not None else "no"))
    return path


@pytest.fixture()
def toy(tmp_path) -> StudySpec:
    folder = tmp_path / "toy"
    folder.mkdir()
    (folder / "quick.toml").write_text("seed = 0\n")
    return StudySpec(name="toy-cost", description="toy", config_type=ToyConfig,
                     directory=folder,
                     tasks=lambda c: Declaration(tuple(Draw(i) for i in range(2)), _task),
                     summarise=_summary, report=_report, cost=_cost)


def test_runner_measures_once_and_rebuild_reads(toy, tmp_path):
    out = tmp_path / "run"
    CALLS.clear()
    run(toy, ToyConfig(), out, workers=0, progress=False)
    assert CALLS == [out]
    meta = json.loads((out / "cost_pass.json").read_text())
    assert meta["what"] == "toy episode" and meta["rounds"] == 2
    stamp = (out / "cost_pass.json").stat().st_mtime_ns
    run(toy, ToyConfig(), out, workers=0, progress=False)  # every task stored: pass kept
    rebuild_report(toy, out)
    assert CALLS == [out]
    assert (out / "cost_pass.json").stat().st_mtime_ns == stamp
    assert (out / "report.md").read_text() == "pass: yes"
    assert json.loads((out / "summary.json").read_text())["measured"] is True
    # a folder whose pass is gone: a rebuild reports none and measures nothing
    for f in Path(out).glob("cost_pass.*"):
        f.unlink()
    rebuild_report(toy, out)
    assert CALLS == [out]
    assert (out / "report.md").read_text() == "pass: no"

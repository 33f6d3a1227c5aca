"""The sampling-safety study's cost does not depend on the neighbours: on a small profile the
order of methods by cost (the run's cost pass: each method alone, in lock step, ties within the
resolution) is the same run in-process, on one worker and on two workers at once; the report
gives it, and the wall-clock p50 / p95 / p99 / max per method beside the CPU cost."""

from __future__ import annotations

import pytest

from studies.sampling_safety import STUDY
from workbench.study import RunStore
from workbench.study.cost_pass import load_pass
from workbench.study.latency import orders_agree
from workbench.study.runner import profile_config
from workbench.study.runner import run as run_study

# a cheap, a middle and a costly method (their CPU times differ by about 3x at each step)
CONTROLLERS = ("bas_mppi", "sa_rmppi", "sais_ecbf")


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    cfg = profile_config(STUDY, "tiny", controllers=CONTROLLERS, realisations=1, steps=15)
    out = {}
    for workers in (0, 1, 2):
        folder = tmp_path_factory.mktemp(f"workers{workers}")
        out[workers] = (folder, run_study(STUDY, cfg, folder, workers=workers, progress=False))
    return out


def test_cost_order_is_the_same_with_0_1_and_2_workers(runs):
    orders = {w: outcome.summary.value.cost_order for w, (_, outcome) in runs.items()}
    for w, (folder, _) in runs.items():  # the summary's order is the stored pass's
        stored = load_pass(folder)
        assert stored is not None and stored.order() == orders[w]
        assert stored.meta["rounds"] == 3
    assert orders_agree(*orders.values()), orders
    # the order separates something: a run with every method tied would agree vacuously
    assert all(len(o) >= 2 for o in orders.values()), orders
    assert all(o[0][0] == "bas_mppi" and o[-1][-1] == "sais_ecbf" for o in orders.values())


def test_report_gives_cpu_cost_and_wall_tail(runs):
    folder, outcome = runs[2]
    text = outcome.report.read_text()
    assert "CPU ms / step" in text
    assert "## What a method costs: the cost pass" in text
    assert "Order by cost, cheapest first" in text and "BaS-MPPI <" in text
    for word in ("wall p50", "wall p95", "wall p99", "wall max"):
        assert word in text
    steps = RunStore(folder).table("step_times")
    assert {"wall_ms", "cpu_ms", "step"} <= set(steps.columns)
    assert (steps["cpu_ms"] > 0).all() and (steps["wall_ms"] > 0).all()

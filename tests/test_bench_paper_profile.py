"""The paper-profile estimate and its floor bound, from a synthetic run of known step counts."""

import json

import pandas as pd
import pytest

from benchmarks.paper_profile import cell_counts, estimate
from studies.navigation import STUDY
from studies.navigation.config import ROBUST
from workbench.study.runner import resolve_config


def _write_run(path, cells, wall, loaded=0):
    rows, timing = [], []
    for i, ((ctrl, rule, var), (n, steps, ms)) in enumerate(cells.items()):
        for j in range(n):
            tid = f"{i}-{j}"
            rows.append({"task_id": tid, "controller": ctrl, "rule": rule, "variance": var,
                         "realisation": j, "steps": steps + j})
            timing.append({"task_id": tid, "mean_step_ms": ms})
    pd.DataFrame(rows).to_csv(path / "episodes.csv", index=False)
    pd.DataFrame(timing).to_csv(path / "timing.csv", index=False)
    (path / "run.json").write_text(json.dumps(
        {"wall_time_s": wall, "tasks": {"total": len(rows), "loaded": loaded}}))


def test_estimate_and_bound_from_cells(tmp_path):
    target = cell_counts(resolve_config(STUDY, "tiny"))
    assert sum(target.values()) > len(target)  # several episodes per cell
    # the run: 2 episodes per cell, steps s and s + 1 (mean s + 0.5), step time by controller
    ms = {"sa_rmppi": 4.0, "rmppi": 3.0, "bas_mppi": 1.5, "mppi_crash": 1.0}
    cells = {k: (2, 10 * (i + 1), ms[k[0]]) for i, k in enumerate(target)}
    run_step_s = sum(sum(s + j for j in range(n)) * m / 1e3 for n, s, m in cells.values())
    _write_run(tmp_path, cells, wall=run_step_s / 2 + 30.0)
    floors = {"robust": 2.0, "mppi": 0.5}
    r = estimate(tmp_path, floors, workers=2, profile="tiny")
    steps = {k: s + 0.5 for k, (_, s, _) in cells.items()}
    want = sum(n * steps[k] * cells[k][2] / 1e3 for k, n in target.items()) / 2 + 30.0
    bound = sum(n * steps[k] * floors["robust" if k[0] in ROBUST else "mppi"] / 1e3
                for k, n in target.items()) / 2
    assert r["estimate_s"] == pytest.approx(want, rel=1e-12)
    assert r["fixed_s"] == pytest.approx(30.0, rel=1e-12)
    assert r["lower_bound_s"] == pytest.approx(bound, rel=1e-12)
    assert r["steps"] == pytest.approx(sum(n * steps[k] for k, n in target.items()), rel=1e-12)
    # a resumed run's wall time says nothing about its fixed part
    _write_run(tmp_path, cells, wall=1e6, loaded=3)
    assert estimate(tmp_path, floors, workers=2, profile="tiny")["fixed_s"] == 0.0


def test_missing_cells_are_named(tmp_path):
    target = cell_counts(resolve_config(STUDY, "tiny"))
    first = next(iter(target))
    _write_run(tmp_path, {first: (1, 5, 1.0)}, wall=1.0)
    with pytest.raises(ValueError, match="missing"):
        estimate(tmp_path, {"robust": 1.0, "mppi": 1.0}, profile="tiny")

"""make bench's step-time records: the report gives p50 / p95 / p99 / max per method with the
tail's sources, and the deadline table; the console line of such a record prints the
percentiles."""

from __future__ import annotations

import json
import subprocess

import pytest

import benchmarks.latency as latency
from benchmarks.__main__ import _tail
from benchmarks.latency import markdown
from benchmarks.report import report_markdown
from benchmarks.timing import record

TAIL = {"first_step_ms": 9.0, "p99_without_first_ms": 3.5, "fallback_steps": 2,
        "fallback_median_ms": 4.25, "other_median_ms": 2.0, "after_idle_p50_ms": 2.75,
        "back_to_back_p50_ms": 2.0, "calibration_s": 1.5, "build_s": 0.25}


def records() -> list[dict]:
    lat = record("step_latency_sa_rmppi", 3.75, "ms (wall p99)", None, None,
                 {"steps": 300, "crashed": False, "p50_ms": 2.0, "p95_ms": 3.0, "p99_ms": 3.75,
                  "max_ms": 9.0, "mean_ms": 2.2, "cpu_mean_ms": 2.1, "variance": 100.0,
                  "tail": TAIL})
    dl = record("deadline_sa_rmppi_50hz", 1.5, "ms (max over budget)", None, None,
                {"budget_ms": 20.0, "steps": 1000, "load": 2, "loop": "at the rate",
                 "n_samples": 8192, "misses": 3,
                 "p50_ms": 19.0, "p95_ms": 19.5, "p99_ms": 20.5, "max_ms": 21.5,
                 "truncated": 1.0, "samples_mean": 2048.0, "crash_rate": 0.25, "episodes": 4,
                 "episode_steps": 200, "variance": 100.0, "stated_margin_ms": 5.0,
                 "holds": True, "beyond_margin_steps": 0, "beyond_margin_cpu_max_ms": None,
                 "cpu_p50_ms": 9.0})
    busy = record("deadline_sa_rmppi_50hz_back_to_back", 2.5, "ms (max over budget)", None,
                  None, {**dl["params"], "loop": "back to back", "crash_rate": None,
                         "episodes": 0, "misses": 7})
    return [lat, dl, busy]


def test_report_has_percentiles_tail_sources_and_deadlines():
    text = "\n".join(markdown(records()))
    assert "| method | p50 | p95 | p99 | max |" in text
    assert "| sa_rmppi | 2.00 | 3.00 | 3.75 | 9.00 | 2.10 | 9.00 | 3.50 | 2 (4.25) | 2.75 | " \
           "1.50 | 0.25 |" in text
    assert "| sa_rmppi_50hz | at the rate | 20 | 1000 | 3 | 1.50 | 5.0 | yes | 0 | 19.00 | " \
           "20.50 | 100 % | 2048 | 0.25 (4 × 200 steps) |" in text
    assert "| sa_rmppi_50hz | back to back | 20 | 1000 | 7 | 2.50 | 5.0 | yes | 0 | 19.00 | " \
           "20.50 | 100 % | 2048 | — |" in text
    broken = records()[1]
    broken["params"].update(holds=False, beyond_margin_steps=2, beyond_margin_cpu_max_ms=4.5,
                            beyond_margin_phases_ms=[{"step": 7, "wall_ms": 27.5, "cpu_ms": 4.5,
                                                      "samples": 64, "selection_ms": 20.25,
                                                      "tail_ms": 1.5,
                                                      "chunks": [[48, 2.5, 2.25, 1],
                                                                 [16, 3.0, 1.0, 2]]}])
    text = "\n".join(markdown([broken]))
    assert "| 5.0 | **no** | 2 (4.5) |" in text
    assert ("- sa_rmppi_50hz: wall 27.5, cpu 4.5, selection 20.2, tail 1.5; chunks (samples: "
            "wall / CPU ms) 48: 2.5 / 2.2, 16: 3.0 / 1.0 (2 threads)") in text
    assert "## Deadlines under a load of 2" in report_markdown(records(), {})


def test_console_line_prints_percentiles():
    lat, dl, _ = records()
    assert _tail(lat) == "  p50/p95/p99/max 2.00/3.00/3.75/9.00 ms"
    assert _tail(dl) == "  p50/p95/p99/max 19.00/19.50/20.50/21.50 ms"
    assert _tail(record("other", 1.0, "ms", None, None, {})) == ""


def test_deadline_records_run_in_a_child_process(monkeypatch):
    """The deadline records run in a fresh child and come back as its JSON; a failing child
    raises with its stderr."""
    seen = {}

    def fake_run(cmd, capture_output, text, check):
        seen["cmd"] = cmd
        out = [{"name": "deadline_x", "params": {"budget_ms": 20.0}}]
        return subprocess.CompletedProcess(cmd, 0, json.dumps(out), "")

    monkeypatch.setattr(latency.subprocess, "run", fake_run)
    got = latency.deadline_records_child()
    assert "deadline_records()" in seen["cmd"][-1]
    assert got == [{"name": "deadline_x", "params": {"budget_ms": 20.0}}]

    def failing(cmd, capture_output, text, check):
        return subprocess.CompletedProcess(cmd, 1, "", "Traceback: boom")

    monkeypatch.setattr(latency.subprocess, "run", failing)
    with pytest.raises(RuntimeError, match="boom"):
        latency.deadline_records_child()

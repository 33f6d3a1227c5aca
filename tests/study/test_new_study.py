"""Adding a study: its own config, tasks, summary and report files plus one registration line
(here ``WORKBENCH_STUDIES``; in the repository a line in ``studies/registry.py``). The framework
does the rest: profiles, --set, dry runs, execution, summary.json, run.json, config.toml and the
report; no plumbing is copied."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pandas as pd

WORKBENCH = str(Path(sys.executable).parent / "workbench")

FILES = {
    "__init__.py": '''
        from pathlib import Path

        from toy_study.config import ToyConfig
        from workbench.study.spec import StudySpec

        STUDY = StudySpec(
            name="toy", description="normal draws", config_type=ToyConfig,
            directory=Path(__file__).parent, tasks="toy_study.tasks:declare",
            summarise="toy_study.summary:summary", report="toy_study.report:report")
        ''',
    "config.py": '''
        from dataclasses import dataclass

        from workbench.validation import integer, real


        @dataclass(frozen=True)
        class ToyConfig:
            n: int = 3
            scale: float = 1.0
            seed: int = 0

            def __post_init__(self):
                integer("n", self.n, 1)
                real("scale", self.scale, 0.0, strict=True)
        ''',
    "tasks.py": '''
        from dataclasses import dataclass

        import numpy as np

        from workbench.study import TaskOutput
        from workbench.study.spec import Declaration


        @dataclass(frozen=True)
        class Draw:
            i: int


        def run(task, ctx, config):
            value = config.scale * ctx.rng().standard_normal()
            return TaskOutput(tables={"draws": {"value": np.array([value])}})


        def declare(config):
            tasks = tuple(Draw(i) for i in range(config.n))
            return Declaration(tasks, run, {"scale": config.scale}, plan=tasks)
        ''',
    "summary.py": '''
        from workbench.study.spec import Summary


        def summary(finished):
            mean = float(finished.store.table("draws")["value"].mean())
            return Summary({"mean": mean}, mean, (f"mean {mean:.6f}",))
        ''',
    "report.py": '''
        from workbench.study.io import atomic_write_text


        def report(finished, summary):
            path = finished.out / "report.md"
            atomic_write_text(path, f"# Toy\\n\\nmean {summary.value:.6f}. {finished.run_line}\\n")
            return path
        ''',
    "quick.toml": "n = 4\n",
}


def _package(root: Path) -> Path:
    pkg = root / "toy_study"
    pkg.mkdir()
    for name, text in FILES.items():
        (pkg / name).write_text(textwrap.dedent(text).lstrip())
    return pkg


def _cli(root: Path, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "WORKBENCH_STUDIES": "toy_study",  # the one registration line
           "PYTHONPATH": os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([WORKBENCH, *args], capture_output=True, text=True, env=env,
                          timeout=120, cwd=Path(__file__).parents[2])


def test_a_new_study_needs_only_its_files_and_one_registration_line(tmp_path):
    pkg = _package(tmp_path)
    listed = _cli(tmp_path, "list")
    assert listed.returncode == 0 and "toy" in listed.stdout and "normal draws" in listed.stdout
    dry = _cli(tmp_path, "run", "toy", "--set", "scale=2", "--dry-run")
    assert dry.returncode == 0, dry.stderr
    assert json.loads(dry.stdout)["config"] == {"n": 4, "scale": 2.0, "seed": 0}
    bad = _cli(tmp_path, "run", "toy", "--set", "n=0")
    assert bad.returncode == 2 and "n = 0 is invalid" in bad.stderr
    out = tmp_path / "out"
    ran = _cli(tmp_path, "run", "toy", "--workers", "0", "--out", str(out))
    assert ran.returncode == 0, ran.stderr
    draws = pd.read_parquet(out / "draws.parquet")
    assert len(draws) == 4
    summary = json.loads((out / "summary.json").read_text())
    assert summary == {"study": "toy_study", "mean": float(draws["value"].mean())}
    assert f"mean {summary['mean']:.6f}" in ran.stdout
    record = json.loads((out / "run.json").read_text())
    assert record["profile"] == "quick" and record["tasks"] == {"total": 4, "computed": 4,
                                                                "loaded": 0}
    assert "n = 4" in (out / "config.toml").read_text()
    assert (out / "report.md").read_text().startswith("# Toy")
    assert sorted(p.name for p in pkg.iterdir() if p.suffix in (".py", ".toml")) == sorted(FILES)
    again = _cli(tmp_path, "run", "toy", "--workers", "0", "--out", str(out))
    assert again.returncode == 0, again.stderr
    record = json.loads((out / "run.json").read_text())  # the computing run's record is kept
    assert record["tasks"]["computed"] == 4 and record["last_invocation"]["tasks"]["computed"] == 0

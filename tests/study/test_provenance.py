"""Results are not mixed across code or evaluators: every stored task and the manifest record the
evaluator (compiled kernels or the NumPy fallback) and a hash of the code that ran (edits not
committed included); continuing a run whose stored tasks differ is refused unless allowed."""

from __future__ import annotations

import io
import json
import shutil
import textwrap
import uuid
from pathlib import Path

import numpy as np
import pytest
import study_toy  # tests/study/study_toy.py

from workbench.study import RunStore, Study, provenance, run_study
from workbench.study.execute import MixedResultsError

FILES = ("draws.parquet", "draws.csv")
MODULE = '''
import numpy as np

from workbench.study import TaskOutput


def run_task(task, ctx):
    return TaskOutput(tables={"t": {"x": ctx.rng().standard_normal(3)}})
'''


def _snapshot(root: Path) -> dict[str, tuple[bytes, int]]:
    return {str(p.relative_to(root)): (p.read_bytes(), p.stat().st_mtime_ns)
            for p in sorted(root.rglob("*")) if p.is_file() and not p.name.endswith(".lock")}


@pytest.fixture
def edited_module(tmp_path, monkeypatch):
    """A study whose task function lives in a module file of its own (to be edited)."""
    name = f"prov_mod_{uuid.uuid4().hex[:8]}"
    src = tmp_path / "src"
    src.mkdir()
    (src / f"{name}.py").write_text(textwrap.dedent(MODULE))
    monkeypatch.syspath_prepend(str(src))
    module = __import__(name)
    tasks = tuple(study_toy.ToyTask(c, 0) for c in "abc")
    yield Study("prov", tasks, module.run_task, seed=1), src / f"{name}.py"
    provenance.clear_cache()


def test_every_task_and_the_manifest_record_evaluator_and_code_hash(tmp_path):
    study = study_toy.toy_study(6)
    current = provenance.current(study.run_task)
    assert current["evaluator"] in ("compiled", "fallback") and len(current["code_sha256"]) == 64
    for workers in (0, 2):
        out = tmp_path / f"w{workers}"
        run_study(study, out, workers=workers, progress=False)
        store = RunStore(out)
        assert all(store.provenance(i) == current for i in study.task_ids()), workers
        recorded = json.loads((out / "manifest.json").read_text())["provenance"]
        assert {k: recorded[k] for k in current} == current
        assert recorded["code_roots"] == ["workbench", "study_toy.py"]
        assert "toolchain" in recorded and "environment" in recorded
    for name in FILES:  # the record does not enter the tables: bytes equal across back ends
        assert (tmp_path / "w0" / name).read_bytes() == (tmp_path / "w2" / name).read_bytes()


def test_the_code_hash_counts_every_source_edit_and_nothing_else(tmp_path):
    pkg = tmp_path / "a" / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "mod.py").write_text("x = 1\n")
    (pkg / "data.json").write_text("{}")
    h0 = provenance.tree_hash(pkg)
    (pkg / "notes.md").write_text("not code")
    (pkg / "__pycache__").mkdir()
    (pkg / "__pycache__" / "mod.cpython-311.pyc").write_bytes(b"\0")
    provenance.clear_cache()
    assert provenance.tree_hash(pkg) == h0
    elsewhere = tmp_path / "b" / "pkg"
    shutil.copytree(pkg, elsewhere)
    assert provenance.tree_hash(elsewhere) == h0  # where it is installed does not count
    (pkg / "sub" / "mod.py").write_text("x = 1  # an edit not committed\n")
    assert provenance.tree_hash(pkg) == h0  # cached: the code this process loaded
    provenance.clear_cache()
    h1 = provenance.tree_hash(pkg)
    (pkg / "data.json").write_text('{"a": 1}')
    provenance.clear_cache()
    assert len({h0, h1, provenance.tree_hash(pkg)}) == 3


def test_continuing_after_a_code_edit_is_refused_unless_allowed(tmp_path, edited_module):
    study, source = edited_module
    out = tmp_path / "run"
    run_study(study, out, workers=0, progress=False)
    source.write_text(source.read_text() + "# an edit that is not committed\n")
    provenance.clear_cache()
    before = _snapshot(out)
    with pytest.raises(MixedResultsError) as info:
        run_study(study, out, workers=0, progress=False)
    msg = str(info.value)
    assert msg.startswith(f"3 of 3 stored tasks in {out} were computed by other code")
    assert "allow_mixed=True" in msg and "--allow-mixed" in msg and "--out" in msg
    assert _snapshot(out) == before  # nothing written, nothing recomputed
    allowed = run_study(study, out, workers=0, progress=False, allow_mixed=True)
    assert (allowed.loaded, allowed.computed) == (3, 0)
    assert json.loads((out / "manifest.json").read_text())["execution"]["allow_mixed"] is True


SPEC_MODULE = '''
from dataclasses import dataclass

import numpy as np

from workbench.study import TaskOutput
from workbench.study.io import atomic_write_text
from workbench.study.spec import Declaration, Summary

PREPARED = []


@dataclass(frozen=True)
class Config:
    n: int = 2
    seed: int = 0


@dataclass(frozen=True)
class One:
    i: int


def run(task, ctx, config, prepared):
    return TaskOutput(tables={"t": {"x": ctx.rng().standard_normal(2)}})


def declare(config):
    return Declaration(tuple(One(i) for i in range(config.n)), run)


def prepare(config, out):
    PREPARED.append(out)  # an expensive calibration in a real study
    return 1.0


def summarise(finished):
    return Summary({})


def report(finished, summary):
    atomic_write_text(finished.out / "report.md", "# r\\n")
    return finished.out / "report.md"
'''


def test_the_runner_refuses_mixed_tasks_before_preparing_or_writing(tmp_path, monkeypatch):
    from workbench.study.runner import run
    from workbench.study.spec import StudySpec

    name = f"prov_spec_{uuid.uuid4().hex[:8]}"
    (tmp_path / "src").mkdir()
    source = tmp_path / "src" / f"{name}.py"
    source.write_text(SPEC_MODULE)
    monkeypatch.syspath_prepend(str(tmp_path / "src"))
    m = __import__(name)
    (tmp_path / "profiles").mkdir()
    (tmp_path / "profiles" / "quick.toml").write_text("")
    spec = StudySpec(name="prov-spec", description="", config_type=m.Config,
                     directory=tmp_path / "profiles", tasks=m.declare, summarise=m.summarise,
                     report=m.report, prepare=m.prepare)
    out = tmp_path / "run"
    run(spec, m.Config(), out, workers=0, progress=False)
    source.write_text(SPEC_MODULE + "# edited\n")
    provenance.clear_cache()
    before, prepared = _snapshot(out), len(m.PREPARED)
    try:
        with pytest.raises(MixedResultsError, match=r"^2 of 2 stored tasks"):
            run(spec, m.Config(), out, workers=0, progress=False)
        assert len(m.PREPARED) == prepared and _snapshot(out) == before
        assert run(spec, m.Config(), out, workers=0, progress=False,
                   allow_mixed=True).run.loaded == 2
    finally:
        provenance.clear_cache()


def test_continuing_with_another_evaluator_is_refused(tmp_path, monkeypatch):
    study = study_toy.toy_study(4)
    monkeypatch.setenv("WORKBENCH_NO_CODEGEN", "1")
    assert provenance.evaluator() == "fallback"
    run_study(study, tmp_path, workers=0, progress=False)
    assert RunStore(tmp_path).provenance(study.task_ids()[0])["evaluator"] == "fallback"
    assert run_study(study, tmp_path, workers=0, progress=False).loaded == 4  # same: fine
    monkeypatch.delenv("WORKBENCH_NO_CODEGEN")
    if provenance.evaluator() != "compiled":
        pytest.skip("no C compiler on this machine")
    with pytest.raises(MixedResultsError, match=r"^4 of 4 stored tasks .*evaluator 'compiled'.*"
                                                r"stored: evaluator 'fallback'"):
        run_study(study, tmp_path, workers=0, progress=False)


def test_the_evaluator_follows_the_compiler_switch(monkeypatch):
    monkeypatch.setenv("WORKBENCH_NO_CODEGEN", "1")
    detail = provenance.describe()
    assert detail["evaluator"] == "fallback" and detail["toolchain"] is None
    assert detail["environment"] == {"WORKBENCH_NO_CODEGEN": "1"}
    monkeypatch.setenv("WORKBENCH_NO_CODEGEN", "0")
    assert provenance.evaluator() == ("compiled" if provenance.evaluator_detail()["toolchain"]
                                      else "fallback")


def test_tasks_stored_without_a_record_count_as_other_code(tmp_path):
    """A task file written before the record existed: its code is unknown."""
    study = study_toy.toy_study(4)
    run_study(study, tmp_path, workers=0, progress=False)
    path = RunStore(tmp_path).task_path(study.task_ids()[0])
    with np.load(path) as data:
        entries = {k: data[k] for k in data.files}
    header = json.loads(str(entries["record"]))
    del header["provenance"]
    entries["record"] = np.array(json.dumps(header))
    buf = io.BytesIO()
    np.savez_compressed(buf, **entries)
    path.write_bytes(buf.getvalue())
    assert RunStore(tmp_path).is_done(study.task_ids()[0])
    with pytest.raises(MixedResultsError, match=r"^1 of 4 stored tasks .*no record \(stored by "
                                                r"an earlier version\): 1"):
        run_study(study, tmp_path, workers=0, progress=False)

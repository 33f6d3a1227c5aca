"""A run continued under another result-changing setting of the compiled evaluator (vector
maths, extra compiler flags) is refused like one under another evaluator; the same setting
spelled differently is the same setting."""

from __future__ import annotations

import pytest
import study_toy  # tests/study/study_toy.py

from workbench.study import RunStore, provenance, run_study
from workbench.study.execute import MixedResultsError


@pytest.fixture
def compiled(monkeypatch):
    for name in ("WORKBENCH_NO_CODEGEN", "WORKBENCH_VECTOR_MATH", "WORKBENCH_CFLAGS"):
        monkeypatch.delenv(name, raising=False)
    if provenance.evaluator() != "compiled":
        pytest.skip("no C compiler on this machine")
    return monkeypatch


def test_each_task_records_the_settings(tmp_path, compiled):
    compiled.setenv("WORKBENCH_CFLAGS", "-O2")
    study = study_toy.toy_study(2)
    run_study(study, tmp_path, workers=0, progress=False)
    stored = RunStore(tmp_path).provenance(study.task_ids()[0])
    assert stored["settings"] == {"vector_math": True, "cflags": ["-O2"]}


@pytest.mark.parametrize(("name", "first", "then", "shown"), [
    ("WORKBENCH_VECTOR_MATH", None, "0", "vector_math=True"),
    ("WORKBENCH_VECTOR_MATH", "off", "on", "vector_math=False"),
    ("WORKBENCH_CFLAGS", "-O2", None, r"cflags=\['-O2'\]"),
], ids=["vector-math-off", "vector-math-on", "cflags-removed"])
def test_continuing_under_another_setting_is_refused(tmp_path, compiled, name, first, then,
                                                     shown):
    study = study_toy.toy_study(4)
    if first is not None:
        compiled.setenv(name, first)
    run_study(study, tmp_path, workers=0, progress=False)
    if then is None:
        compiled.delenv(name)
    else:
        compiled.setenv(name, then)
    with pytest.raises(MixedResultsError, match=rf"^4 of 4 stored tasks .*evaluator setting.*"
                                                rf"stored: evaluator 'compiled', settings .*"
                                                rf"{shown}"):
        run_study(study, tmp_path, workers=0, progress=False)
    assert run_study(study, tmp_path, workers=0, progress=False,
                     allow_mixed=True).loaded == 4


def test_the_same_setting_spelled_otherwise_continues(tmp_path, compiled):
    study = study_toy.toy_study(4)
    run_study(study, tmp_path, workers=0, progress=False)
    compiled.setenv("WORKBENCH_VECTOR_MATH", "Yes")
    compiled.setenv("WORKBENCH_CFLAGS", "  ")
    assert run_study(study, tmp_path, workers=0, progress=False).loaded == 4

"""The repository's studies come from the checkout beside ``workbench``, never from another
installed package named ``studies``: ``workbench list``, spawned workers and the Dask worker
plugin, in a process where (as in an editable install of the library alone) only ``workbench``
is importable from the checkout and a foreign ``studies`` comes first on ``sys.path``."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from workbench.study import checkout

ROOT = Path(__file__).parents[2]

# Imports workbench from the checkout, then leaves only the foreign folder on sys.path in its
# place: what an editable install of the library alone sees beside a foreign `studies`.
# forget(): as a fresh process of that install (no studies imported, the checkout not on the path).
PRELUDE = """\
import sys
sys.path.insert(0, {root!r})
import workbench.cli, workbench.study.checkout, workbench.study.cluster
sys.path[:] = [p for p in sys.path if p not in ("", {root!r})]
sys.path.insert(0, {foreign!r})

def forget():
    for name in [m for m in sys.modules if m == "studies" or m.startswith("studies.")]:
        del sys.modules[name]
    sys.path[:] = [p for p in sys.path if p != {root!r}]
"""


def foreign_studies(tmp_path: Path, raising: bool) -> Path:
    """A folder holding an unrelated package ``studies`` (raising ImportError when imported,
    if ``raising``)."""
    pkg = tmp_path / "foreign" / "studies"
    pkg.mkdir(parents=True)
    body = "raise ImportError('the foreign studies package was imported')\n" if raising else ""
    (pkg / "__init__.py").write_text(body + "STUDIES = []\n")
    (pkg / "registry.py").write_text("STUDIES = []\n")
    return pkg.parent


def run(tmp_path: Path, foreign: Path, body: str) -> subprocess.CompletedProcess:
    script = PRELUDE.format(root=str(ROOT), foreign=str(foreign)) + textwrap.dedent(body)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "WORKBENCH_STUDIES")}
    return subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          cwd=tmp_path, env=env, timeout=300)


def test_workbench_list_reads_the_checkout_studies_before_a_foreign_package(tmp_path):
    foreign = foreign_studies(tmp_path, raising=True)
    r = run(tmp_path, foreign, """\
        assert sys.path[0].endswith("foreign")
        rc = workbench.cli.main(["list"])
        import studies
        print("FROM", studies.__file__)
        sys.exit(rc)
    """)
    assert r.returncode == 0, r.stderr
    for name in ("tracking-demo", "navigation", "arena"):
        assert f"  {name} " in r.stdout
    assert f"FROM {ROOT / 'studies' / '__init__.py'}" in r.stdout


def test_a_foreign_studies_package_already_imported_is_refused_naming_both(tmp_path):
    foreign = foreign_studies(tmp_path, raising=False)
    r = run(tmp_path, foreign, """\
        import studies  # the foreign one, before the command runs
        sys.exit(workbench.cli.main(["list"]))
    """)
    assert r.returncode == 2, r.stdout + r.stderr
    assert "workbench list: error:" in r.stderr
    assert str(foreign / "studies") in r.stderr and str(ROOT / "studies") in r.stderr


def test_spawned_workers_and_dask_workers_import_the_checkout_studies(tmp_path):
    foreign = foreign_studies(tmp_path, raising=True)
    r = run(tmp_path, foreign, """\
        import multiprocessing
        import pickle
        from workbench.study.spec import registry
        config_type = registry()["tracking-demo"].config_type  # a class defined in studies
        payload = pickle.dumps(("RAN", config_type, None))  # as a Dask task travels
        with multiprocessing.get_context("spawn").Pool(1) as pool:  # inherits sys.path
            print("SPAWNED", pool.apply(eval, ("__import__('studies.registry').__file__",)))
        forget()
        import functools
        init = functools.partial(print, "INIT")  # the study's initialiser, run after the path
        workbench.study.cluster.WorkerInit(init).setup(worker=None)  # as on a fresh Dask worker
        import studies
        print("DASK", studies.__file__)
        forget()
        workbench.study.cluster.run_pickled(print, payload)  # a task on a Dask worker
        print("TASK", sys.modules["studies"].__file__)
    """)
    assert r.returncode == 0, r.stderr
    assert f"SPAWNED {ROOT / 'studies' / '__init__.py'}" in r.stdout
    assert f"DASK {ROOT / 'studies' / '__init__.py'}" in r.stdout
    assert "INIT" in r.stdout
    assert "RAN <class 'studies.tracking_demo." in r.stdout
    assert f"TASK {ROOT / 'studies' / '__init__.py'}" in r.stdout


def test_no_studies_beside_workbench_is_a_clear_error(monkeypatch, tmp_path):
    monkeypatch.setattr(checkout, "checkout_root", lambda: tmp_path)
    with pytest.raises(checkout.StudiesLocationError, match=str(tmp_path / "studies")):
        checkout.use_checkout_studies()

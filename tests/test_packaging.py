"""What ``pip install`` installs: the ``workbench`` packages only, never top-level ``studies`` or
``benchmarks`` (generic names that would collide with other installed packages); and the type
check that ``make test`` runs first."""

from __future__ import annotations

import subprocess
import tomllib
from pathlib import Path

from setuptools import find_packages

ROOT = Path(__file__).parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
CONFIG = PYPROJECT["tool"]["setuptools"]


def test_only_workbench_packages_are_installed():
    found = find_packages(where=str(ROOT), **CONFIG["packages"]["find"])
    assert "workbench" in found and "workbench.study" in found
    assert all(p == "workbench" or p.startswith("workbench.") for p in found), found


def test_package_data_belongs_to_installed_packages_only():
    assert set(CONFIG["package-data"]) == {"workbench"}
    assert "py.typed" in CONFIG["package-data"]["workbench"]


def test_make_test_runs_the_type_check_before_the_tests():
    r = subprocess.run(["make", "-n", "test"], capture_output=True, text=True, cwd=ROOT,
                       timeout=60)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    mypy = next(i for i, line in enumerate(lines) if line.startswith(".venv/bin/mypy"))
    pytest = next(i for i, line in enumerate(lines) if "-m pytest" in line)
    assert mypy < pytest


def test_the_type_checker_is_configured_for_the_library():
    assert PYPROJECT["tool"]["mypy"]["packages"] == ["workbench"]
    assert any(d.startswith("mypy") for d in PYPROJECT["project"]["optional-dependencies"]["dev"])

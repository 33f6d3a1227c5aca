"""What ``pip install`` installs: the ``workbench`` packages only, never top-level ``studies`` or
``benchmarks`` (generic names that would collide with other installed packages)."""

from __future__ import annotations

import tomllib
from pathlib import Path

from setuptools import find_packages

ROOT = Path(__file__).parents[1]
CONFIG = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]


def test_only_workbench_packages_are_installed():
    found = find_packages(where=str(ROOT), **CONFIG["packages"]["find"])
    assert "workbench" in found and "workbench.study" in found
    assert all(p == "workbench" or p.startswith("workbench.") for p in found), found


def test_package_data_belongs_to_installed_packages_only():
    assert set(CONFIG["package-data"]) == {"workbench"}
    assert "py.typed" in CONFIG["package-data"]["workbench"]

"""Where the repository's studies come from: the checkout that holds this ``workbench`` package.

``studies`` and ``benchmarks`` are not installed (names that generic could collide with other
installed packages): they stay at the top of the repository checkout, beside ``workbench/``,
which an editable install (``pip install -e .``, ``make venv``) imports in place.
:func:`use_checkout_studies` puts that checkout first on ``sys.path`` and refuses, naming both
folders, when ``studies`` is (or would be) imported from anywhere else, e.g. an unrelated
``studies`` package in site-packages. The study registry calls it before reading
``studies/registry.py``; local workers (spawned) inherit the coordinator's ``sys.path``, and
each Dask worker calls it when the run's worker plugin is set up.
"""

from __future__ import annotations

import importlib
import sys
from pathlib import Path
from types import ModuleType

PACKAGE = "studies"


class StudiesLocationError(ImportError):
    """``studies`` is missing beside the installed ``workbench`` or comes from elsewhere."""


def checkout_root() -> Path:
    """The folder that holds the installed ``workbench`` package: the repository checkout
    (in an editable install)."""
    return Path(__file__).resolve().parents[2]


def has_checkout_studies() -> bool:
    """Whether the checkout beside ``workbench`` holds the ``studies`` package."""
    return (checkout_root() / PACKAGE / "__init__.py").is_file()


def _folder(module: ModuleType) -> Path | None:
    where = getattr(module, "__file__", None)
    return Path(where).resolve().parent if where else None


def use_checkout_studies() -> ModuleType:
    """Import ``studies`` from the checkout beside ``workbench`` (its root goes first on
    ``sys.path``) and return it; :class:`StudiesLocationError` when the checkout has no
    ``studies/`` or ``studies`` was already imported from another folder."""
    root = checkout_root()
    expected = root / PACKAGE
    if not has_checkout_studies():
        raise StudiesLocationError(
            f"no study registry: {expected}/__init__.py does not exist beside the installed "
            f"workbench package ({root / 'workbench'}); the studies are not installed, they are "
            "read from a repository checkout installed in editable mode (make venv, or "
            "pip install -e CHECKOUT); studies kept elsewhere can be registered with "
            "$WORKBENCH_STUDIES")
    if not sys.path or Path(sys.path[0] or ".").resolve() != root:
        sys.path.insert(0, str(root))
    module = sys.modules.get(PACKAGE) or importlib.import_module(PACKAGE)
    found = _folder(module)
    if found != expected:
        raise StudiesLocationError(
            f"'studies' was imported from {found or module!s}, not from this checkout's "
            f"{expected}; another package named 'studies' shadows the repository's studies "
            "(uninstall it or take it off PYTHONPATH)")
    return module

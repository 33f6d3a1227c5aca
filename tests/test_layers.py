"""The library's layers, lowest first, the rule that nothing imports upward, and no import cycle.

validation, environment, registry < study (infrastructure: configs, runner, store, statistics) and
codegen < problem < ilqg, filters < sim < sampling.problem < sampling.kernels
< sampling.feedback < sampling < scenarios < bound < cli. The library never imports
``benchmarks`` or ``studies`` (except the command line, which reads the study registry).

No cycle: the import graph of ``workbench``, ``studies`` and ``benchmarks``, read with the imports
inside functions (a function-local import still runs, so it cannot hide a cycle), has no cycle.
Imports under ``if TYPE_CHECKING:`` never run and are not part of that graph (they may point
either way within a layer); the upward rule checks them too. Count the cycles with
``python tests/import_graph.py`` (:mod:`import_graph`).
"""

from __future__ import annotations

import ast
from pathlib import Path

import import_graph  # tests/import_graph.py
import pytest

REPO = Path(__file__).parents[1]
ROOT = REPO / "workbench"
PACKAGES = ("workbench", "studies", "benchmarks")
LAYERS = [
    ("workbench.validation", "workbench.environment", "workbench.registry"),
    ("workbench.study", "workbench.codegen"),
    ("workbench.problem",),
    ("workbench.ilqg", "workbench.filters"),
    ("workbench.sim",),
    ("workbench.sampling.problem",),
    ("workbench.sampling.kernels",),
    ("workbench.sampling.feedback",),
    ("workbench.sampling",),
    ("workbench.scenarios",),
    ("workbench.bound",),
    ("workbench.cli", "workbench"),
]


def layer(module: str) -> int:
    best, rank = -1, None
    for i, prefixes in enumerate(LAYERS):
        for p in prefixes:
            if (module == p or module.startswith(p + ".")) and len(p) > best:
                best, rank = len(p), i
    assert rank is not None, module
    return rank


def check_no_cycle(root: Path, packages) -> None:
    """Fail, naming every cycle and the imports that close it, when the run-time import graph
    of ``packages`` under ``root`` (function-local imports included) has a cycle."""
    edges = import_graph.graph(import_graph.modules(root, packages))
    found = import_graph.cycles(edges)
    assert not found, f"{len(found)} import cycle(s):\n" + import_graph.describe(found, edges)


def private_imports(root: Path, packages, importers: tuple[str, ...] = ("",)) -> list[str]:
    """Every ``from m import _name`` in a module of ``packages`` under ``root`` whose name
    starts with one of ``importers``, where ``m`` is another module of those packages (a helper
    that another module needs should be public)."""
    mods = import_graph.modules(root, packages)
    out = []
    for name, path in mods.items():
        if not name.startswith(importers):
            continue
        for node in import_graph.import_nodes(ast.parse(path.read_text()), type_checking=True):
            if isinstance(node, ast.ImportFrom):
                module = import_graph.absolute(node, name, path.name == "__init__.py")
                out += [f"{name} imports {module}.{a.name}" for a in node.names
                        if module in mods and module != name and a.name.startswith("_")
                        and not a.name.endswith("__")]
    return out


def test_no_study_module_imports_a_private_name_of_another():
    assert not private_imports(REPO, PACKAGES, ("studies.", "workbench.study."))


def test_a_planted_private_import_is_reported(tmp_path):
    root = _package(tmp_path, {"__init__.py": "", "a.py": "def _f():\n    return 1\n",
                               "b.py": "def g():\n    from .a import _f\n    return _f()\n"})
    assert private_imports(root, ["pkg"]) == ["pkg.b imports pkg.a._f"]


def test_nothing_imports_upward_and_the_library_imports_no_study_or_benchmark():
    mods = import_graph.modules(REPO, ["workbench"])
    bad = []
    for name, path in mods.items():
        if name == "workbench":  # the public API re-exports every layer (lazily)
            continue
        for imp in import_graph.imports(path, name, type_checking=True):
            top = imp.split(".")[0]
            if top == "benchmarks" or (top == "studies" and name != "workbench.cli"):
                bad.append(f"{name} imports {imp}")
            if top == "workbench" and imp in mods and layer(imp) > layer(name):
                bad.append(f"{name} (layer {layer(name)}) imports {imp} (layer {layer(imp)})")
    assert not bad, "\n".join(bad)


def test_no_import_cycle_even_through_imports_inside_functions():
    # one graph of the three packages: a cycle may pass through another package
    assert {m.split(".")[0] for m in import_graph.modules(REPO, PACKAGES)} == set(PACKAGES)
    check_no_cycle(REPO, PACKAGES)


def _package(tmp_path: Path, files: dict[str, str]) -> Path:
    for name, text in files.items():
        path = tmp_path / "pkg" / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return tmp_path


TINY = {"__init__.py": "", "a.py": "import pkg.b\n", "c.py": "from pkg import a\n"}


@pytest.mark.parametrize("closing", [
    "def f():\n    from pkg import a\n",  # a function-local import
    "def f():\n    from . import a\n",  # relative, in a function
    "class K:\n    def m(self):\n        import pkg.a\n",  # in a method
    "try:\n    import pkg.c\nexcept ImportError:\n    pass\n",  # c -> a -> b -> c
    "import typing\nif not typing.TYPE_CHECKING:\n    import pkg.a\n",  # a branch that runs
])
def test_a_planted_cycle_is_reported(tmp_path, closing):
    root = _package(tmp_path, {**TINY, "b.py": closing})
    with pytest.raises(AssertionError, match=r"(?s)import cycle.*pkg\.a.*pkg\.b"):
        check_no_cycle(root, ["pkg"])


def test_the_same_package_without_the_closing_import_passes(tmp_path):
    check_no_cycle(_package(tmp_path, {**TINY, "b.py": "def f():\n    return 1\n"}), ["pkg"])


def test_an_import_for_type_checkers_only_is_no_cycle_but_counts_as_an_import(tmp_path):
    b = ("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg.a import X\n"
         "else:\n    import json\n")
    root = _package(tmp_path, {**TINY, "b.py": b})
    check_no_cycle(root, ["pkg"])
    path = root / "pkg" / "b.py"
    assert import_graph.imports(path, "pkg.b") == {"typing", "typing.TYPE_CHECKING", "json"}
    assert "pkg.a" in import_graph.imports(path, "pkg.b", type_checking=True)


def test_the_cycle_finder_on_a_synthetic_graph():
    edges = {"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": {"e"}, "e": {"d"}, "f": {"f"},
             "g": {"a"}}
    assert import_graph.cycles(edges) == [["a", "b", "c"], ["d", "e"], ["f"]]
    assert import_graph.cycles({"a": {"b"}, "b": set()}) == []


def test_the_top_of_the_package_is_small():
    assert sorted(p.name for p in ROOT.glob("*.py")) == ["__init__.py", "cli.py",
                                                         "environment.py", "registry.py",
                                                         "sim.py", "validation.py"]

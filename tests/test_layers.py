"""The library's layers, lowest first, and the rule that nothing imports upward.

validation < study (infrastructure: configs, runner, store, statistics) and codegen < problem
< ilqg, filters < sim < sampling.problem < sampling.kernels < sampling.feedback < sampling
< scenarios < bound < cli. The library never imports ``benchmarks`` or ``studies`` (except the
command line, which reads the study registry), and module-level imports form no cycle.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).parents[1] / "workbench"
LAYERS = [
    ("workbench.validation",),
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


def modules() -> dict[str, Path]:
    out = {}
    for path in sorted(ROOT.rglob("*.py")):
        parts = path.relative_to(ROOT.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


def imports(path: Path, top_level_only: bool) -> set[str]:
    tree = ast.parse(path.read_text())
    nodes = tree.body if top_level_only else list(ast.walk(tree))
    out = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
            out |= {f"{node.module}.{a.name}" for a in node.names}
    return out


def test_nothing_imports_upward_and_the_library_imports_no_study_or_benchmark():
    mods = modules()
    bad = []
    for name, path in mods.items():
        if name == "workbench":  # the public API re-exports every layer (lazily)
            continue
        for imp in imports(path, top_level_only=False):
            top = imp.split(".")[0]
            if top == "benchmarks" or (top == "studies" and name != "workbench.cli"):
                bad.append(f"{name} imports {imp}")
            if top == "workbench" and imp in mods and layer(imp) > layer(name):
                bad.append(f"{name} (layer {layer(name)}) imports {imp} (layer {layer(imp)})")
    assert not bad, "\n".join(bad)


def test_module_level_imports_form_no_cycle():
    mods = modules()
    graph = {n: {i for i in imports(p, top_level_only=True) if i in mods and i != n}
             for n, p in mods.items()}
    state: dict[str, int] = {}

    def visit(n: str, stack: list[str]) -> None:
        state[n] = 1
        for m in graph[n]:
            if state.get(m) == 1:
                raise AssertionError("import cycle: " + " -> ".join([*stack, n, m]))
            if m not in state:
                visit(m, [*stack, n])
        state[n] = 2

    for n in graph:
        if n not in state:
            visit(n, [])


def test_the_top_of_the_package_is_small():
    assert sorted(p.name for p in ROOT.glob("*.py")) == ["__init__.py", "cli.py", "sim.py",
                                                         "validation.py"]

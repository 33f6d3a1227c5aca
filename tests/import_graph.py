"""The import graph of the repository's packages, and its cycles.

An edge ``a -> b`` means module ``a`` imports module ``b`` somewhere in its source: at module
level or inside a function, class or conditional block (a function-local import still runs, so
it still closes a cycle; only its timing differs). Imports under ``if TYPE_CHECKING:`` never run
and are left out of the graph. ``from p import x`` is an edge to ``p`` and, when ``p.x`` is a
module, to ``p.x``; relative imports are resolved against the importing module.

Count the cycles (strongly connected groups of more than one module, or a module importing
itself) from the repository root::

    python tests/import_graph.py workbench studies benchmarks

(``--type-checking`` counts the imports under ``if TYPE_CHECKING:`` too.)
"""

from __future__ import annotations

import ast
import sys
from collections.abc import Iterable, Mapping
from pathlib import Path


def modules(root: Path, packages: Iterable[str]) -> dict[str, Path]:
    """Dotted module name -> source file, for every ``.py`` file under each package of root."""
    out = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            parts = path.relative_to(root).with_suffix("").parts
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def import_nodes(tree: ast.AST, top_level_only: bool = False,
                 type_checking: bool = False) -> list[ast.Import | ast.ImportFrom]:
    """The import statements of a module: all of them, or (``top_level_only``) those outside
    functions and classes. The body of an ``if TYPE_CHECKING:`` block never runs, so it is left
    out unless ``type_checking`` (its ``else`` branch runs, so it is always kept)."""
    out: list[ast.Import | ast.ImportFrom] = []
    scopes = ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef | ast.Lambda

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.Import | ast.ImportFrom):
            out.append(node)
            return
        if top_level_only and isinstance(node, scopes):
            return
        if isinstance(node, ast.If) and _is_type_checking(node.test) and not type_checking:
            children: list[ast.AST] = list(node.orelse)
        else:
            children = list(ast.iter_child_nodes(node))
        for child in children:
            visit(child)

    visit(tree)
    return out


def absolute(node: ast.ImportFrom, name: str, is_package: bool) -> str:
    """The absolute name of the module of ``from ... import`` in module ``name`` (a package's
    ``__init__`` when ``is_package``)."""
    if node.level == 0:
        return node.module or ""
    base = name.split(".")
    base = base if is_package else base[:-1]
    base = base[:len(base) - (node.level - 1)]
    return ".".join([*base, *([node.module] if node.module else [])])


def imports(path: Path, name: str, top_level_only: bool = False,
            type_checking: bool = False) -> set[str]:
    """Every module name that the file at path (module ``name``) imports when it runs (with
    ``type_checking``: also under ``if TYPE_CHECKING:``)."""
    tree = ast.parse(path.read_text())
    out: set[str] = set()
    for node in import_nodes(tree, top_level_only, type_checking):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        else:
            module = absolute(node, name, path.name == "__init__.py")
            out.add(module)
            out |= {f"{module}.{a.name}" for a in node.names}
    return out


def graph(mods: Mapping[str, Path], top_level_only: bool = False,
          type_checking: bool = False) -> dict[str, set[str]]:
    """Module -> the known modules it imports (itself excluded)."""
    return {n: {i for i in imports(p, n, top_level_only, type_checking) if i in mods and i != n}
            for n, p in mods.items()}


def cycles(edges: Mapping[str, Iterable[str]]) -> list[list[str]]:
    """The strongly connected groups of more than one module (Tarjan), each sorted, plus any
    module with an edge to itself; sorted by their first module."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    groups: list[list[str]] = []

    def connect(v: str) -> None:  # iterative, so deep graphs cannot hit the recursion limit
        work = [(v, iter(edges.get(v, ())))]
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(edges.get(child, ()))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                group = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    group.append(w)
                    if w == node:
                        break
                if len(group) > 1 or node in edges.get(node, ()):
                    groups.append(sorted(group))

    for v in sorted(edges):
        if v not in index:
            connect(v)
    return sorted(groups)


def describe(groups: list[list[str]], edges: Mapping[str, Iterable[str]]) -> str:
    """One line per cycle: its modules and the imports among them."""
    lines = []
    for group in groups:
        inside = set(group)
        links = [f"{a} -> {b}" for a in group for b in sorted(edges.get(a, ())) if b in inside]
        lines.append(f"{{{', '.join(group)}}}: {'; '.join(links)}")
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    root = Path(__file__).parents[1]
    type_checking = "--type-checking" in argv
    packages = [a for a in argv if not a.startswith("--")] or ["workbench", "studies",
                                                               "benchmarks"]
    edges = graph(modules(root, packages), type_checking=type_checking)
    for package in packages:
        found = [g for g in cycles(edges) if g[0].split(".")[0] == package]
        print(f"{package}: {len(found)} import cycle(s)")
        if found:
            print(describe(found, edges))
    return 1 if cycles(edges) else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

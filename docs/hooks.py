"""mkdocs hooks of the documentation site.

``<!-- public-api -->`` in a page becomes the table of every name ``import workbench as wb``
exports (read from ``workbench/__init__.py`` without importing it), grouped by the module that
defines it, each linked to its entry in the API reference with the first line of its docstring.
An exporting module that no reference page renders (``::: module``) is rendered on the
public-API page itself, so a new module is documented without editing the pages; a name the
reference still does not document is an unresolved link, and ``mkdocs build --strict`` fails on
it.
"""

from __future__ import annotations

import ast
import functools
import importlib.util
import re
from pathlib import Path

import griffe

MARKER = "<!-- public-api -->"


@functools.cache
def _roles():
    """The API reference's docstring conversion (docs/griffe_roles.py), for the summaries."""
    spec = importlib.util.spec_from_file_location("griffe_roles",
                                                  Path(__file__).with_name("griffe_roles.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def exports(init: Path) -> dict[str, tuple[str, ...]]:
    """``_EXPORTS`` of the package's ``__init__.py``: module -> names."""
    for node in ast.parse(init.read_text()).body:
        if isinstance(node, ast.Assign) and any(
                isinstance(t, ast.Name) and t.id == "_EXPORTS" for t in node.targets):
            return ast.literal_eval(node.value)
    raise RuntimeError(f"{init}: no _EXPORTS")


def summary(obj: griffe.Object) -> str:
    """First paragraph of a docstring as the reference shows it, safe inside a table cell."""
    if obj.docstring is None:
        return ""
    first = obj.docstring.value.strip().split("\n\n")[0].replace("\n", " ")
    return _roles().convert(obj, first).replace("|", "\\|")


def rendered_elsewhere(docs: Path, page: Path) -> set[str]:
    """Objects rendered (``::: identifier``) by the reference pages other than ``page``."""
    found: set[str] = set()
    for md in (docs / "api").glob("*.md"):
        if md != page:
            found |= set(re.findall(r"^::: (\S+)", md.read_text(), re.M))
    return found


def public_api(root: Path, page: Path) -> str:
    package = griffe.load("workbench", search_paths=[str(root)], resolve_aliases=False)
    modules = exports(root / "workbench" / "__init__.py")
    out = []
    for module, names in modules.items():
        out += [f"## `{module}`", "", "| name | what |", "|---|---|"]
        for name in names:
            path = f"{module}.{name}"
            obj = package[path.removeprefix("workbench.")]
            out.append(f"| [`wb.{name}`][{path}] | {summary(obj)} |")
        out.append("")
    missing = [m for m in modules if m not in rendered_elsewhere(page.parents[1], page)]
    if missing:
        out += ["## Modules without a page of their own", ""]
        out += [f"::: {m}\n    options:\n      heading_level: 3\n" for m in missing]
    return "\n".join(out)


def on_page_markdown(markdown: str, page, config, files) -> str:
    if MARKER in markdown:
        root = Path(config["config_file_path"]).parent
        page_path = Path(config["docs_dir"]) / page.file.src_path
        markdown = markdown.replace(MARKER, public_api(root, page_path))
    return markdown

"""Griffe extension for the API reference: the library's docstrings are prose with a few
reStructuredText habits; this turns them into Markdown that mkdocstrings renders cleanly.

* cross-reference roles (:class:`~workbench.sim.Episode`, :func:`calibrate`, :mod:`.tube`)
  become links when the target is documented in the site, plain code otherwise (autorefs'
  optional references: an unknown target never warns);
* a paragraph ending in ``::`` (reST's literal-block marker) ends in ``:``; its indented block
  is a Markdown code block already;
* a citation of the assumptions page by section ("assumptions §3.2", "§13 E7") links to that
  section of the page, whose anchors follow its numbering (``assumptions.html#s3-2``). Older
  docstrings cite the same sections under the name of the internal document the page was
  written from; they are shown with the page's name and linked the same way.
"""

from __future__ import annotations

import html
import re

import griffe

ROLE = re.compile(r":(?:py:)?(class|func|meth|mod|data|attr|exc|obj|const):`([^`]+)`")
LITERAL = re.compile(r"::\n(\s*\n)")
PAGE = "../assumptions.md"  # API pages live in api/, beside the assumptions page
OLD = "SP" + "EC"  # the internal document's name, spelt so that a search for it finds none here
SECTION = re.compile(
    rf"\b(?:{OLD}|assumptions)\s+§?(\d{{1,2}})(?:\.(\d{{1,2}}))?(?:\s+([MBARLE]\d)\b)?")
ITEM = re.compile(rf"\b(?:{OLD}|assumptions)\s+§?([MBARLE]\d)\b")
OTHER = re.compile(rf"\b(?:in {OLD}\b|{OLD}'s|{OLD}\b)")


def sections(text: str) -> str:
    """Citations of the assumptions page as links to its numbered sections."""

    def section(m: re.Match) -> str:
        number = m[1] + (f".{m[2]}" if m[2] else "")
        anchor = f"s{m[1]}" + (f"-{m[2]}" if m[2] else "")
        if m[3]:
            number, anchor = f"{number} {m[3]}", f"{anchor}-{m[3].lower()}"
        return f"[assumptions §{number}]({PAGE}#{anchor})"

    text = SECTION.sub(section, text)
    text = ITEM.sub(lambda m: f"[assumptions §13 {m[1]}]({PAGE}#s13-{m[1].lower()})", text)
    return OTHER.sub(lambda m: {"in": "on the assumptions page"}.get(
        m[0].split()[0], f"[the assumptions page]({PAGE})"), text)


def _target(obj: griffe.Object, text: str) -> tuple[str, str]:
    """(identifier, shown text) of a role's target, resolved from ``obj`` when relative."""
    title = None
    m = re.fullmatch(r"(.*?)\s*<([^>]+)>", text)  # :class:`title <target>`
    if m:
        title, text = m[1], m[2]
    short = text.startswith("~")
    target = text.lstrip("~").removesuffix("()")
    if target.startswith("."):  # relative to the module (or package) of the docstring
        module = obj if obj.is_module else obj.module
        base = module.path if module.is_package or obj.is_module else module.parent.path
        ident = f"{base}{target}" if base else target.lstrip(".")
        shown = target.lstrip(".")
    else:
        ident, shown = target, target
        head, _, rest = target.partition(".")
        if "." not in target or not target.startswith("workbench"):
            try:  # a name in the docstring's scope (imported or defined there)
                resolved = (obj if obj.is_module or obj.is_class else obj.parent).resolve(head)
                ident = f"{resolved}.{rest}" if rest else resolved
            except (griffe.NameResolutionError, AttributeError, ValueError):
                scope = obj if obj.is_module else obj.module
                ident = f"{scope.path}.{target}"
    if short:
        shown = shown.rsplit(".", 1)[-1]
    return ident, title or shown


def convert(obj: griffe.Object, text: str) -> str:
    def role(m: re.Match) -> str:
        ident, shown = _target(obj, m[2])
        return (f'<autoref identifier="{html.escape(ident)}" optional>'
                f"<code>{html.escape(shown)}</code></autoref>")

    return sections(LITERAL.sub(r":\n\1", ROLE.sub(role, text)))


class ReSTRoles(griffe.Extension):
    """Rewrite every docstring of a package once it is loaded."""

    def on_package(self, *, pkg: griffe.Module, **kwargs) -> None:
        seen: set[int] = set()

        def walk(obj: griffe.Object) -> None:
            if id(obj) in seen:
                return
            seen.add(id(obj))
            if obj.docstring is not None:
                obj.docstring.value = convert(obj, obj.docstring.value)
            for member in obj.members.values():
                if not member.is_alias:
                    walk(member)

        walk(pkg)

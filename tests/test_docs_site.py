"""The documentation site builds with ``mkdocs build --strict`` and no warning, offline, with
every page of its navigation; the assumptions page has its stable section anchors, readable
maths and no internal document names; every link into it resolves; the Python blocks of the
non-tutorial pages run and print the outputs they show, at the tolerance marked beside each
(the tutorials are run by test_tutorials.py; the markers are described in shown_output.py)."""

from __future__ import annotations

import contextlib
import html
import io
import os
import re
import subprocess
import sys
import types
from pathlib import Path

import pytest
import shown_output  # tests/shown_output.py
import yaml

ROOT = Path(__file__).parents[1]
DOCS = ROOT / "docs"
ASSUMPTIONS = ROOT / "workbench" / "assumptions.md"
INTERNAL = re.compile(r"\bSPEC\b|\bNOTES\b")
pytestmark = pytest.mark.slow


def nav_pages(nav) -> list[str]:
    """Every Markdown file of the navigation, in order."""
    out = []
    for item in nav:
        value = next(iter(item.values())) if isinstance(item, dict) else item
        out += nav_pages(value) if isinstance(value, list) else [value]
    return out


def config() -> dict:
    return yaml.safe_load((ROOT / "mkdocs.yml").read_text())


def text_of(page: str) -> str:
    """The visible text of a built page's article (tags and scripts removed)."""
    body = re.sub(r"<(script|style)\b.*?</\1>", "", page, flags=re.S)
    return html.unescape(re.sub(r"<[^>]+>", " ", body))


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("site")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-f",
                        str(ROOT / "mkdocs.yml"), "-d", str(out)], cwd=ROOT, env=env,
                       capture_output=True, text=True, timeout=600)
    log = r.stdout + r.stderr
    assert r.returncode == 0, log
    warnings = [line for line in log.splitlines() if "WARNING" in line]
    assert not warnings, "\n".join(warnings)
    return out


def built(site: Path) -> dict[str, str]:
    return {str(p.relative_to(site)): p.read_text() for p in site.rglob("*.html")}


def test_config_builds_offline_into_reports_docs():
    c = config()
    assert c["site_dir"] == "reports/docs" and c["use_directory_urls"] is False
    assert c["theme"]["name"] == "material" and c["theme"]["font"] is False


def test_every_nav_page_is_built(site):
    pages = nav_pages(config()["nav"])
    assert len(pages) == len(set(pages)) >= 20
    for md in pages:
        assert (DOCS / md).is_file(), md
        assert (site / md.replace(".md", ".html")).is_file(), md


def test_pages_load_nothing_from_the_network(site):
    for name, page in built(site).items():
        remote = re.findall(r'<(?:script|link|img)\b[^>]*(?:src|href)="(https?://[^"]+)"', page)
        assert not remote, (name, remote)


def test_no_internal_document_names_in_any_page(site):
    for name, page in built(site).items():
        found = INTERNAL.findall(text_of(page))
        assert not found, (name, found)


def test_assumptions_source_is_written_for_users():
    text = ASSUMPTIONS.read_text()
    for word in (r"\bSPEC\b", r"\bNOTES\b", r"\bissues?\b", r"DES[I]GN\.md", r"\.md\b", r"shared/"):
        assert not re.search(word, text, re.I if word == r"\bissues?\b" else 0), word
    assert "$" not in text  # maths as Unicode text: no TeX delimiters for any renderer


def test_assumptions_sections_have_stable_anchors(site):
    text = ASSUMPTIONS.read_text()
    headings = re.findall(r"^#{2,3} (\d+)(?:\.(\d+))?\.? .*?\{#([\w-]+)\}\s*$", text, re.M)
    numbered = re.findall(r"^#{2,3} \d+(?:\.\d+)?\.? ", text, re.M)
    assert len(headings) == len(numbered) >= 60  # every numbered heading has its anchor
    for major, minor, anchor in headings:
        assert anchor == f"s{major}" + (f"-{minor}" if minor else ""), anchor
    page = (site / "assumptions.html").read_text()
    ids = set(re.findall(r'id="([\w-]+)"', page))
    assert {f"s{i}" for i in range(16)} <= ids
    assert {a for _, _, a in headings} <= ids
    assert {f"s13-{x}" for x in ("m1", "b1", "a3", "r4", "l1", "e1", "e4", "e7")} <= ids
    visible = text_of(page)
    assert "$" not in visible and "{#" not in visible and "{:" not in visible
    assert "Parameter table" in visible and "Table I" in visible


def test_every_link_into_the_assumptions_page_resolves(site):
    ids = set(re.findall(r'id="([\w-]+)"', (site / "assumptions.html").read_text()))
    links = 0
    for name, page in built(site).items():
        for anchor in re.findall(r'href="(?:\.\./)?assumptions\.html#([\w-]+)"', page):
            assert anchor in ids, (name, anchor)
            links += 1
        if name == "assumptions.html":
            for anchor in re.findall(r'href="#([\w-]+)"', page):
                assert anchor in ids, anchor
    assert links > 20  # the concept pages and the API reference cite it by section


def test_public_api_page_lists_every_exported_name(site):
    import workbench

    page = (site / "api" / "index.html").read_text()
    for name in workbench.__all__:
        if name != "__version__":
            assert f"<code>wb.{name}</code></a>" in page, name  # linked to its reference entry


def test_python_blocks_of_the_other_pages_run(tmp_path, monkeypatch):
    """Each page's blocks run in order in one module, as a script of them would (a registered
    module, so that what a block defines can be pickled for worker processes); a block's
    marked output is compared with what it printed."""
    monkeypatch.chdir(tmp_path)
    ran, problems = 0, []
    for md in sorted(DOCS.rglob("*.md")):
        if md.parent.name == "tutorials":
            continue
        module = types.ModuleType(f"docs_page_{md.stem.replace('-', '_')}")
        monkeypatch.setitem(sys.modules, module.__name__, module)
        scope = module.__dict__
        name = str(md.relative_to(DOCS))
        for i, (code, shown) in enumerate(shown_output.page_blocks(md, name)):
            buffer = io.StringIO()
            with contextlib.redirect_stdout(buffer):
                exec(compile(code, f"{name}:block{i}", "exec", dont_inherit=True), scope)
            if shown:
                problems += shown_output.compare(shown, buffer.getvalue())
            ran += 1
        if md.name == "studies.md" and md.parent.name == "concepts":
            # the toy study ran and resumed: computed all four tasks once, then loaded them
            assert (scope["first"].run.computed, scope["again"].run.loaded) == (4, 4)
            assert scope["again"].run.computed == 0 and scope["config"].scale == 2.0
        if md.name == "getting-started.md":
            assert not scope["episode"].crashed and len(scope["episode"].U) == 150
    assert ran >= 5
    assert not problems, "\n".join(problems)

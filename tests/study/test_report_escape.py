"""A string a study echoes from its config into report.md reads as written in report.html and
on the report site: raw HTML is shown as text, and no script, event handler or script address
comes out of the markdown, its attribute lists or its formulas."""

from __future__ import annotations

import html
import textwrap
import uuid
from html.parser import HTMLParser

import pytest

from workbench.cli import main
from workbench.study.html_safe import clean_html, safe_url
from workbench.study.report_site import build_site, markdown_html, render_run
from workbench.study.spec import registry

SCRIPT = "<script>alert(1)</script>"
IMAGE = "<img src=x onerror=alert(2)>"
PAYLOADS = [
    SCRIPT,
    IMAGE,
    '<div onclick="alert(3)">block</div>',
    "<iframe src=javascript:alert(4)></iframe>",
    "[link](javascript:alert(5))",
    "[link](JaVaScRiPt&#58;alert(6))",
    "[link](java\tscript:alert(7))",
    "![pic](data:text/html;base64,PHNjcmlwdD4=)",
    "text {: onmouseover=alert(8) }",
    "## heading {: onclick=alert(9) }",
    '```{ .python onclick="alert(10)" }\ncode\n```',
    r"$\text{<img src=x onerror=alert(11)>}$",
    r"$\href{javascript:alert(12)}{x}$",
    r"$\text{<img/src=x/onerror=alert(15)>}$",
    "<!-- <script>alert(13)</script> -->",
    "<svg/onload=alert(14)>",
    "WBMATH0X WBMATH7X",  # looks like the formulas' placeholder
]


class _Elements(HTMLParser):
    """Every element and attribute of a page, and its text."""

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.tags: list[tuple[str, dict[str, str | None]]] = []
        self.text: list[str] = []

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))

    def handle_startendtag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))

    def handle_data(self, data):
        self.text.append(data)


def parse(page: str) -> _Elements:
    p = _Elements()
    p.feed(page)
    p.close()
    return p


def assert_inert(page: str) -> None:
    """No script-like element, no event handler, no address with a script scheme (in the
    body: the head holds the site's own style sheet)."""
    for tag, attrs in parse(page.split("<body>", 1)[-1]).tags:
        assert tag not in ("script", "iframe", "svg", "object", "embed", "style"), (tag, page)
        for name, value in attrs.items():
            assert not name.startswith("on"), (tag, name, page)
            if name in ("href", "src", "xlink:href"):
                assert safe_url(value or ""), (tag, name, value)


@pytest.mark.parametrize("payload", PAYLOADS)
def test_a_config_string_in_a_report_cannot_inject_markup(payload):
    page = markdown_html(f"# Run\n\nLabel: {payload}\n\n| a |\n|---|\n| {payload} |\n")
    assert_inert(page)


@pytest.mark.parametrize("payload", [SCRIPT, IMAGE, '<div onclick="alert(3)">block</div>'])
def test_raw_html_reads_as_written(payload):
    page = markdown_html(f"Label: {payload}\n\n{payload}\n")
    text = "".join(parse(page).text)
    assert text.count(payload) == 2 and html.escape(payload, quote=False) in page


def test_what_reports_use_still_renders():
    page = markdown_html("# T\n\n[site](https://example.org) [fig](fig.png) "
                         "[mail](mailto:a@b.c) [anchor](#s3) ![f](a%20b.png) $x_1$\n\n"
                         "```\na < b\n```\n\n## Sec {#s3}\n", docs="assumptions.html")
    tags = parse(page).tags
    assert ("a", {"href": "https://example.org"}) in tags and ("a", {"href": "fig.png"}) in tags
    assert ("a", {"href": "mailto:a@b.c"}) in tags and ("a", {"href": "#s3"}) in tags
    assert any(t == "img" and a.get("src") == "a%20b.png" for t, a in tags)
    assert any(t == "h2" and a.get("id") == "s3" for t, a in tags)
    assert "<msub>" in page and "a &lt; b" in page


def test_a_formula_holds_only_mathml():
    page = markdown_html(r"$\text{<img/src=x/onerror=alert(1)>}$ $\text{<b>bold</b>}$ $x^2$")
    assert {t for t, _ in parse(page).tags} <= {"p", "math", "mrow", "mtext", "msup", "mi",
                                                "mn"}
    assert "<mtext>bold</mtext>" in page and "<b>" not in page  # the tag removed, its text kept


def test_clean_html_keeps_elements_and_drops_handlers():
    assert clean_html('<p class="x" onclick="y">a &amp; b<br></p>') == \
        '<p class="x">a &amp; b<br></p>'
    assert clean_html("<blink>x</blink><p>y<!-- z --></p>") == "x<p>y</p>"


# ----------------------------------------------------------------- a study's run, end to end
FILES = {
    "__init__.py": '''
        from pathlib import Path
        from dataclasses import dataclass

        import numpy as np

        from workbench.study import TaskOutput
        from workbench.study.io import atomic_write_text
        from workbench.study.spec import Declaration, StudySpec, Summary


        @dataclass(frozen=True)
        class LabelConfig:
            label: str = "plain"
            seed: int = 0


        @dataclass(frozen=True)
        class One:
            i: int = 0


        def run(task, ctx, config):
            return TaskOutput(tables={"t": {"v": np.array([1.0])}})


        def declare(config):
            return Declaration((One(),), run, {})


        def summary(finished):
            return Summary({})


        def report(finished, summary):
            path = finished.out / "report.md"
            atomic_write_text(path, f"# Labels\\n\\nRun of {finished.config.label}.\\n\\n"
                              f"| label |\\n|---|\\n| {finished.config.label} |\\n")
            return path


        STUDY = StudySpec(name="labels", description="echoes its label",
                          config_type=LabelConfig, directory=Path(__file__).parent,
                          tasks=declare, summarise=summary, report=report)
        ''',
    "quick.toml": "",
}


@pytest.fixture
def label_study(tmp_path, monkeypatch):
    name = f"labels_{uuid.uuid4().hex[:10]}"
    (tmp_path / name).mkdir()
    for file, text in FILES.items():
        (tmp_path / name / file).write_text(textwrap.dedent(text).lstrip())
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("WORKBENCH_STUDIES", name)
    return name


def test_a_runs_report_and_the_site_show_a_config_string_as_text(tmp_path, label_study,
                                                                 capsys):
    label = f"{SCRIPT} {IMAGE} [x](javascript:alert(3))"
    out = tmp_path / "reports" / "labels_custom"
    assert main(["run", "labels", "--workers", "0", "--out", str(out), "--set",
                 f"label={label}"]) == 0, capsys.readouterr().err
    assert label in (out / "report.md").read_text()
    page = (out / "report.html").read_text()
    assert_inert(page)
    assert "".join(parse(page).text).count(f"{SCRIPT} {IMAGE}") == 2
    build_site(out.parent, registry())  # the site renders the run's report again, as "other run"
    for p in (out.parent / "index.html", out / "report.html", render_run(out)):
        assert_inert(p.read_text())

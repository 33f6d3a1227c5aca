"""Reports that read well, without a browser: formulas to MathML before markdown (underscores
stay subscripts), references to the page of assumptions as links, tables in scrolling boxes,
missing numbers as "n/a (why)", figures with labelled axes and nothing cut off, a custom run
told apart from the paper's set-up, and unreadable files reported instead of raised."""

from __future__ import annotations

import json
import math
import re

import matplotlib
import numpy as np
import pytest

matplotlib.use("Agg")
import matplotlib.pyplot as plt

import workbench.study.report_site as report_site
from workbench.study import config_io
from workbench.study.report import (
    config_changes,
    figure_problems,
    fmt_rate,
    num,
    provenance,
    see,
)
from workbench.study.report_site import (
    build_site,
    link_refs_html,
    markdown_html,
    render_markdown,
    render_run,
)
from workbench.study.runner import resolve_config
from workbench.study.spec import registry
from workbench.study.summary import Rate

REG = registry()
LEMMA_LINE = (r"Let $\mathcal{F}_{MC}(S,\mathbb{P},x_0,\lambda)$ be the real one and "
              r"$\mathcal{F}_{MC}(S,\mathbb{P},x_0^*,\lambda)$ the nominal one, $E_M^V$ a bound.")


@pytest.fixture
def assumptions(tmp_path, monkeypatch):
    page = tmp_path / "assumptions.md"
    page.write_text("# Assumptions\n\n## 3.2 The map {#s3-2}\n\nGates: $h_i(x) > 0$.\n\n"
                    "## 13 Ambiguities {#s13}\n\nE4: variance or std.\n")
    monkeypatch.setattr(report_site, "ASSUMPTIONS_SOURCE", page)
    return page


def test_formulas_become_mathml_and_underscores_stay_subscripts():
    html = markdown_html(LEMMA_LINE + "\n\n$$\\Delta\\mathcal{F} \\le 2E_M^V$$\n")
    assert "<em>" not in html and "$" not in html
    assert html.count("<math") == 4 and 'display="block"' in html
    assert "<msub>" in html and "<msubsup>" in html  # F_{MC} and E_M^V as sub/superscripts


def test_code_and_dollar_amounts_are_left_alone():
    html = markdown_html("`$x_1$` costs $5 and $6; but $a_1$ is maths")
    assert "<code>$x_1$</code>" in html and "$5 and $6" in html
    assert html.count("<math") == 1


def test_a_formula_latex2mathml_cannot_read_is_shown_as_source():
    html = markdown_html(r"broken: $\frac{1}{$ and fine: $x$")
    assert "<math" in html
    html = markdown_html(r"broken: $\begin{nonsense}x$")
    assert "$" not in html and 'class="tex"' in html


def test_references_become_links_into_the_page_of_assumptions():
    html = markdown_html(f"({see('3.3')}, §6, §12.1), {see('13')} E7; assumptions §6.1-§6.3",
                         "../assumptions.html")
    hrefs = re.findall(r'href="([^"]+)"', html)
    assert hrefs == ["../assumptions.html#s3-3", "../assumptions.html#s6",
                     "../assumptions.html#s12-1", "../assumptions.html#s13",
                     "../assumptions.html#s6-1", "../assumptions.html#s6-3"]
    assert ">assumptions §3.3</a>" in html and ">§12.1</a>" in html
    assert markdown_html(see("3.3")) == "<p>assumptions §3.3</p>"  # no page: plain text
    assert link_refs_html("band (assumptions §14.4)", "a.html") == \
        'band (<a href="a.html#s14-4">assumptions §14.4</a>)'


def test_tables_sit_in_a_box_that_scrolls():
    html = markdown_html("| a | b |\n|---|---|\n| 1 | 2 |\n")
    assert html.startswith('<div class="wide"><table>') and html.endswith("</table></div>")
    assert ".wide { overflow-x: auto;" in report_site.CSS


def test_missing_numbers_say_why():
    assert num(math.nan, ".3g", "no safe episodes") == "n/a (no safe episodes)"
    assert num(None) == "n/a" and num(float("inf")) == "n/a" and num("x") == "n/a"
    assert num(0.12345, ".2f") == "0.12"
    assert fmt_rate(Rate(0, 0)) == "n/a (no cases)" and fmt_rate(Rate(1, 2), 0) == "50% [9, 91]"


def test_figure_problems_find_unlabelled_axes_and_clipped_lines():
    fig, (a, b) = plt.subplots(1, 2)
    a.plot([0, 1], [0, 1])
    b.plot([0, 20], [0, 1])
    b.set_xlim(0, 10)
    b.set_xlabel("x [m]")
    b.set_ylabel("y [m]")
    problems = figure_problems(fig)
    plt.close(fig)
    assert any("no x label" in p for p in problems) and any("no y label" in p for p in problems)
    assert sum("outside the axes" in p for p in problems) == 1


def test_path_panels_hold_every_path_and_label_their_axes():
    """A path that leaves the generated map's 10 m box is drawn whole (it was cut off)."""
    from studies.navigation import figures

    circles = np.array([[5.0, 5.0, 1.0]])
    path = np.array([[0.5, 0.5], [4.0, -2.5], [11.5, 9.5]])
    captured = {}

    def keep(fig, dpi=100):
        captured["problems"] = figure_problems(fig)
        captured["xlim"] = fig.axes[0].get_xlim()
        plt.close(fig)
        return b""

    orig = figures.png_bytes
    figures.png_bytes = keep
    try:
        figures.paths_figure([("sa_rmppi", 10.0, [path], [True])], circles, (0.5, 0.5),
                             (9.5, 9.5))
    finally:
        figures.png_bytes = orig
    assert captured["problems"] == []
    assert captured["xlim"][1] > 11.5


def test_unreadable_report_and_truncated_manifest_give_pages_not_tracebacks(tmp_path,
                                                                           assumptions):
    root = tmp_path / "reports"
    d = root / "tracking_demo"
    d.mkdir(parents=True)
    (d / "report.md").write_bytes(b"# Demo\n\ncaf\xe9 \xff\n")
    (d / "manifest.json").write_text('{"study": "tracking_demo", "con')
    (d / "summary.json").write_text('{"rows": [')
    index = build_site(root, REG).read_text()
    assert "is not UTF-8 text (byte 0xe9 at offset 11)" in index
    assert "manifest.json is missing, truncated or not JSON" in index
    page = (d / "report.html").read_text()
    assert "is not UTF-8 text" in page and "workbench report" in page
    assert "Paper comparison unavailable" in index  # the demo's summary.json is truncated


def test_a_run_folder_anywhere_renders_with_its_own_page_of_assumptions(tmp_path, assumptions):
    d = tmp_path / "my run"
    d.mkdir()
    (d / "report.md").write_text(f"# Mine\n\nThe map ({see('3.2')}): $h_i > 0$.\n")
    page = render_run(d)
    html = page.read_text()
    assert 'href="assumptions.html#s3-2"' in html and 'id="s3-2"' in (
        d / "assumptions.html").read_text()
    assert "all reports" not in html  # no index to go back to
    (tmp_path / "index.html").write_text("<html></html>")  # inside a built site
    (tmp_path / "assumptions.html").write_text("<html></html>")
    html = render_run(d).read_text()
    assert 'href="../assumptions.html#s3-2"' in html and 'href="../index.html"' in html


def test_render_markdown_without_a_page_of_assumptions_keeps_plain_references(tmp_path):
    (tmp_path / "report.md").write_text(f"# R\n\n{see('12.2')}\n")
    html = render_markdown(tmp_path / "report.md", None, None).read_text()
    assert "assumptions §12.2" in html and "assumptions.html" not in html


# -------------------------------------------------------- custom runs vs the paper's set-up
def test_the_paper_profile_and_sizes_are_comparable_a_user_map_is_not():
    from studies.navigation import STUDY
    from studies.navigation.paper import SIZES

    quick = resolve_config(STUDY, "quick")
    assert provenance(STUDY, quick, sizes=SIZES).comparable
    mine = resolve_config(STUDY, "quick", sets=["scene.circles=[[5.0, 5.0, 1.0]]"])
    prov = provenance(STUDY, mine, sizes=SIZES)
    assert not prov.comparable and prov.changes[0].startswith("scene.circles = [[5.0, 5.0, 1.0]]")
    banner = "\n".join(prov.banner("the paper's Table I"))
    assert banner.startswith("**Custom run: not comparable with the paper's Table I.**")
    weight = resolve_config(STUDY, "quick", sets=["q_beta=0.5"])
    assert config_changes(weight, quick) == (f"q_beta = 0.5 (paper set-up: {quick.q_beta})",)


def test_tracking_with_another_noise_level_is_a_custom_run():
    from studies.tracking_comparison import STUDY
    from studies.tracking_comparison.paper import SIZES

    assert provenance(STUDY, resolve_config(STUDY, "quick"), sizes=SIZES).comparable
    noisy = resolve_config(STUDY, "quick", sets=["noise_std=5"])
    assert [c.split(" =")[0] for c in provenance(STUDY, noisy, sizes=SIZES).changes] == \
        ["base.noise_std"]


def _navigation_folder(tmp_path, config) -> object:
    from studies.navigation.paper import paper_rows

    out = tmp_path / "nav"
    out.mkdir()
    (out / "config.toml").write_text(config_io.dump(config))
    cell = {"controller": "sa_rmppi", "variance": 10.0, "n": 20, "safety": 0.9, "ci_low": 0.7,
            "ci_high": 0.97, "rmse": 0.2, "main": True, "rule": "progress(kappa=0.1)"}
    cells = [cell, {**cell, "rule": "progress(kappa=0)", "main": False},
             {**cell, "rule": "quantile(q=0.9)", "main": False},
             {**cell, "controller": "bas_mppi", "rule": "-", "rmse": None}]
    (out / "summary.json").write_text(json.dumps({"cells": cells}))
    return paper_rows(out)


def test_the_index_shows_each_navigation_cell_once_with_its_rule(tmp_path):
    from studies.navigation import STUDY

    rows = _navigation_folder(tmp_path, resolve_config(STUDY, "quick"))
    assert [r.quantity for r in rows] == [
        "SA-RMPPI safety, variance 10, alpha rule progress(kappa=0.1)",
        "BaS-MPPI safety, variance 10"]
    assert rows[1].note == "RMSE: paper 0.0312 m, ours n/a (no safe episodes)"
    assert "nan" not in repr(rows)


def test_the_index_does_not_compare_a_custom_navigation_run(tmp_path):
    from studies.navigation import STUDY

    mine = resolve_config(STUDY, "quick", sets=["scene.circles=[[5.0, 5.0, 1.0]]"])
    (row,) = _navigation_folder(tmp_path, mine)
    assert row.note.startswith("custom run: not comparable with the paper's Table I "
                               "(scene.circles")

"""The report site in a real browser: headless Chromium from Debian's packages driven by
Selenium (pointed at /usr/bin/chromium and /usr/bin/chromedriver; nothing is downloaded).

Every page (the index, each study's report.html, assumptions.html) loads without console
errors; every image decodes; every local link resolves to a file and every anchor to an element
of its page; no raw ``$`` of a formula, no ``nan`` and no internal document name (SPEC, NOTES,
issue) is left in the text; mathematics is rendered (MathML with a size on screen); no page
scrolls sideways (wide tables scroll inside their box). A broken image, a dead link, a dead
anchor, a raw formula and an internal reference planted in a report are caught.

The same checks run over a copy of ``reports/`` when it holds runs (``make study``). With
``WORKBENCH_SCREENSHOTS=DIR`` the index, the free-energy-bound report and the navigation report
are saved there as PNG screenshots."""

from __future__ import annotations

import contextlib
import io
import os
import re
import shutil
from pathlib import Path
from urllib.parse import unquote, urlparse

import pytest

import workbench.study.report_site as report_site
from workbench.study.report_site import build_site
from workbench.study.spec import registry as discover

CHROMIUM, CHROMEDRIVER = Path("/usr/bin/chromium"), Path("/usr/bin/chromedriver")
REPO = Path(__file__).parents[2]
# the sections of the page of assumptions (its anchors: s3-2 for 3.2), for a placeholder page
SECTIONS = ("0 1 2 2.1 2.2 2.3 2.4 2.5 3 3.1 3.2 3.3 4 4.1 4.2 4.3 4.4 4.5 4.6 5 5.1 5.2 5.3 "
            "5.4 5.5 5.6 6 6.1 6.2 6.3 6.4 7 7.1 7.2 7.3 8 8.1 8.2 9 9.1 9.2 9.3 9.4 9.5 9.6 10 "
            "10.1 10.2 10.3 11 11.1 11.2 11.3 12 12.1 12.2 13 14 14.1 14.2 14.3 14.4 15").split()
INTERNAL = re.compile(r"\bSPEC\b|\bNOTES\b|\b[Ii]ssues?\b")
NAN = re.compile(r"\bnan\b", re.I)


def placeholder_assumptions(path: Path) -> Path:
    """A stand-in for workbench/assumptions.md (tests only): one heading per section."""
    lines = ["# Assumptions", ""]
    for s in SECTIONS:
        lines += [f"{'##' if '.' not in s else '###'} {s} Section {s} {{#s{s.replace('.', '-')}}}",
                  "", f"What the paper says, what we chose: $x_{{k+1}} = f(x_k, u_k)$ ({s}).", ""]
    path.write_text("\n".join(lines))
    return path


@pytest.fixture(autouse=True)
def assumptions_page(tmp_path_factory, monkeypatch):
    """The real page of assumptions when the repository has it, else a placeholder."""
    if not report_site.ASSUMPTIONS_SOURCE.is_file():
        path = tmp_path_factory.getbasetemp() / "assumptions_placeholder.md"
        monkeypatch.setattr(report_site, "ASSUMPTIONS_SOURCE", placeholder_assumptions(path))
    return report_site.ASSUMPTIONS_SOURCE


@pytest.fixture(scope="module")
def site(cli_reports, tmp_path_factory):
    """A reports root with the tracking demo and tracking study (the CLI fixture's runs) plus
    tiny navigation, free-energy-bound and sampling-safety runs."""
    from workbench.cli import main

    root = tmp_path_factory.mktemp("site")
    for d in ("tracking_demo", "tracking_comparison"):
        shutil.copytree(cli_reports[0] / d, root / d)
    for study, d in (("navigation", "navigation"), ("free-energy-bound", "free_energy_bound"),
                     ("sampling-safety", "sampling_safety")):
        with contextlib.redirect_stdout(io.StringIO()):
            assert main(["run", study, "--profile", "tiny", "--workers", "0", "-q",
                         "--out", str(root / d)]) == 0
    # a comparison on a user's own system (the examples' two-link arm), in a folder of its own
    arm = tmp_path_factory.mktemp("arm_config") / "arm.toml"
    arm.write_text(f'system = "{REPO / "examples" / "user_models.py"}:arm_system"\n'
                   'controllers = ["bas_mppi", "mppi_crash"]\nvariances = [2.0]\n'
                   'realisations = 2\nsteps = 25\n[sampler]\nn_samples = 64\nhorizon = 20\n'
                   'sigma = [1.5, 1.5]\nlam = 0.1\n')
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["run", "sampling-safety", "--config", str(arm), "--workers", "0", "-q",
                     "--out", str(root / "my_arm")]) == 0
    return root


def test_a_run_on_your_own_system_is_in_the_site(site):
    """A run folder that is not a study's own is listed under "Other runs" with its study,
    and its report is rendered; the report says where it ran and where its settings came
    from."""
    html = build_site(site, discover()).read_text()
    assert '<section id="other-runs">' in html
    assert '<a href="my_arm/report.html">my_arm</a>: sampling_safety' in html
    page = (site / "my_arm" / "report.html").read_text()
    assert "two link arm (your model: its own start, goal and constraints)" in page
    assert "Where the settings came from" in page


def test_site_html_without_a_browser(cli_reports, tmp_path):
    """Structure, independent of Chromium: sections, links, paper table, not-run studies, the
    page of assumptions and links into it."""
    root, _ = cli_reports
    reg = discover()
    html = build_site(root, reg).read_text()
    for name in reg:
        assert f'id="{name}"' in html
    assert "Not run yet: <code>workbench run navigation</code>" in html
    for href in ("tracking_comparison/report.html", "tracking_comparison/manifest.json",
                 "tracking_comparison/summary.json", "tracking_comparison/rollouts.csv",
                 "tracking_comparison/rollouts.parquet", "tracking_comparison/config.toml",
                 "tracking_demo/trajectories.png", "assumptions.html"):
        assert f'href="{href}"' in html, href
    assert "Paper vs ours" in html and "60% (≈60% of MC trajectories unsafe)" in html
    assert '(<a href="assumptions.html#s14-4">assumptions §14.4</a>): inside' in html
    assert "SPEC" not in html
    page = (root / "tracking_comparison" / "report.html").read_text()
    assert '<div class="wide"><table>' in page and '<img alt="' in page
    assert 'href="../index.html"' in page and 'href="../assumptions.html#s13">' in page
    assert (root / "assumptions.html").is_file()


@pytest.fixture(scope="module")
def browser():
    if not (CHROMIUM.exists() and CHROMEDRIVER.exists()):
        pytest.skip("Chromium is not installed (/usr/bin/chromium, /usr/bin/chromedriver): "
                    "`apt-get install -y chromium chromium-driver` (.ci/run does this where apt "
                    "is available)")
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium (dev extra) missing")
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = str(CHROMIUM)
    for a in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu",
              "--window-size=1400,2000", "--hide-scrollbars"):
        opts.add_argument(a)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(options=opts, service=Service(str(CHROMEDRIVER)))
    driver.set_page_load_timeout(30)
    yield driver
    driver.quit()


def _ids(page: Path) -> set[str]:
    return set(re.findall(r'\bid="([^"]+)"', page.read_text(errors="replace")))


# the page's text outside links into the page of assumptions, and what a check needs to know
PAGE_FACTS = """
const docs = Array.from(document.querySelectorAll('a[href*="assumptions.html"]'));
const copy = document.body.cloneNode(true);
copy.querySelectorAll('a[href*="assumptions.html"]').forEach(a => a.remove());
copy.querySelectorAll('math').forEach(m => m.remove());
return {
  text: document.body.innerText,
  outside_docs: copy.textContent,
  math: Array.from(document.querySelectorAll('math')).map(
      m => [m.getBoundingClientRect().width, m.getBoundingClientRect().height]),
  page_width: document.documentElement.scrollWidth,
  window_width: window.innerWidth,
};
"""


def check_page(driver, path: Path) -> tuple[list[str], list[Path], int]:
    """Load ``path``; return the problems found, the local HTML pages it links and its number
    of images."""
    driver.get(path.resolve().as_uri())
    driver.execute_script("window.scrollTo(0, document.body.scrollHeight)")
    name = f"{path.parent.name}/{path.name}"
    problems = [f"{name}: console {e['level']}: {e['message']}"
                for e in driver.get_log("browser") if e["level"] in ("SEVERE", "WARNING")]
    images = driver.execute_script(
        "return Array.from(document.images).map(i => [i.src, i.complete && i.naturalWidth > 0])")
    problems += [f"{name}: image does not load: {src}" for src, ok in images if not ok]
    pages = []
    for href in driver.execute_script("return Array.from(document.links).map(a => a.href)"):
        url = urlparse(href)
        if url.scheme != "file":
            problems.append(f"{name}: link leaves the offline site: {href}")
            continue
        target = Path(unquote(url.path))
        if not target.is_file():
            problems.append(f"{name}: dead link: {href}")
            continue
        if url.fragment and url.fragment not in _ids(target):
            problems.append(f"{name}: dead anchor: {href}")
        if target.suffix == ".html":
            pages.append(target)
    facts = driver.execute_script(PAGE_FACTS)
    if "$" in facts["text"]:
        at = facts["text"].index("$")
        problems.append(f"{name}: raw $ in the text: {facts['text'][max(at - 40, 0):at + 40]!r}")
    for m in INTERNAL.finditer(facts["outside_docs"]):
        t = facts["outside_docs"]
        problems.append(f"{name}: internal reference {m.group(0)!r} in the text: "
                        f"{t[max(m.start() - 40, 0):m.end() + 40]!r}")
    for m in NAN.finditer(facts["text"]):
        t = facts["text"]
        problems.append(f"{name}: {m.group(0)!r} in the text: "
                        f"{t[max(m.start() - 60, 0):m.end() + 20]!r}")
    problems += [f"{name}: a formula is not rendered (size {w}x{h})"
                 for w, h in facts["math"] if not (w > 0 and h > 0)]
    if facts["page_width"] > facts["window_width"]:
        problems.append(f"{name}: the page scrolls sideways ({facts['page_width']} px wide in a "
                        f"{facts['window_width']} px window)")
    return problems, pages, len(images)


def check_site(driver, index: Path) -> tuple[list[str], list[Path], int]:
    """Check the index and every HTML page it links, and the pages those link; (problems,
    pages checked, images on the index)."""
    problems, pages, n_images = check_page(driver, index)
    if driver.title != "SAIS Workbench reports":
        problems.append(f"index title {driver.title!r}")
    seen, todo = {index.resolve()}, [p.resolve() for p in pages]
    while todo:
        page = todo.pop()
        if page in seen:
            continue
        seen.add(page)
        found, more, _ = check_page(driver, page)
        problems += found
        todo += [p.resolve() for p in more]
    return problems, sorted(seen), n_images


def test_every_page_loads_cleanly_in_chromium(browser, site):
    index = build_site(site, discover())
    problems, pages, n_images = check_site(browser, index)
    assert problems == []
    reports = {p.parent.name for p in pages if p.name == "report.html"}
    assert reports == {"tracking_demo", "tracking_comparison", "navigation",
                       "free_energy_bound", "sampling_safety", "my_arm"}
    assert site / "assumptions.html" in pages
    studies_own = [p for p in site.glob("*/*.png") if p.parent.name != "my_arm"]
    assert n_images == len(studies_own) >= 15  # every study's figure on the index


def test_mathematics_is_rendered(browser, site):
    """The bound report's Lemma 1: MathML with a size on screen, subscripts kept (not turned
    into italics by the markdown parser)."""
    build_site(site, discover())
    page = site / "free_energy_bound" / "report.html"
    html = page.read_text()
    assert "<em>" not in html.split("Reading used")[0]  # no underscore became emphasis
    assert html.count("<math") >= 40 and '<math xmlns="http://www.w3.org/1998/Math/MathML" ' \
        'display="block">' in html
    browser.get(page.resolve().as_uri())
    sizes = browser.execute_script(
        "return Array.from(document.querySelectorAll('math')).map("
        "m => m.getBoundingClientRect().height)")
    assert len(sizes) >= 40 and min(sizes) > 5


def test_the_navigation_report_of_a_custom_run_leaves_out_table_i(site):
    """The tiny profile's 20-step episodes are not the paper's set-up: labelled, no Table I."""
    build_site(site, discover())
    text = (site / "navigation" / "report.md").read_text()
    assert "**Custom run: not comparable with the paper's Table I.**" in text
    assert "steps = 20 (paper set-up: 1000)" in text and "Table I beside ours" not in text
    index = (site / "index.html").read_text()
    assert "custom run: not comparable with the paper&#x27;s Table I" in index


def test_the_browser_check_catches_what_it_should(browser, cli_reports, tmp_path):
    root, _ = cli_reports
    copy = tmp_path / "reports"
    shutil.copytree(root / "tracking_demo", copy / "tracking_demo")
    md = copy / "tracking_demo" / "report.md"
    md.write_text(md.read_text() + "\n![gone](missing.png)\n\n[data](gone.csv)\n\n"
                  "[see](../assumptions.html#s99-9)\n\nPrice: \\$x_1\\$ and SPEC §3.3, and "
                  "a result of nan.\n")
    problems, _, _ = check_site(browser, build_site(copy, discover()))
    assert any("image does not load" in p and "missing.png" in p for p in problems)
    assert any("dead link" in p and "gone.csv" in p for p in problems)
    assert any("dead anchor" in p and "s99-9" in p for p in problems)
    assert any("console SEVERE" in p and "missing.png" in p for p in problems)
    assert any("raw $" in p for p in problems)
    assert any("internal reference 'SPEC'" in p for p in problems)
    assert any("'nan' in the text" in p for p in problems)


def test_a_wide_table_scrolls_inside_its_box(browser, tmp_path):
    """A 40-column table: the page keeps the window's width; the table's box scrolls."""
    d = tmp_path / "wide"
    d.mkdir()
    header = [f"column {i}" for i in range(40)]
    (d / "report.md").write_text("# Wide\n\n| " + " | ".join(header) + " |\n|"
                                 + "---|" * 40 + "\n| " + " | ".join("1234567" for _ in header)
                                 + " |\n")
    page = report_site.render_run(d)
    problems, _, _ = check_page(browser, page)
    assert problems == []
    box = browser.execute_script("const b = document.querySelector('.wide'); "
                                 "return [b.scrollWidth, b.clientWidth]")
    assert box[0] > box[1]  # the table is wider than its box, which scrolls


def _screenshot(driver, page: Path, path: Path) -> None:
    driver.get(page.resolve().as_uri())
    height = driver.execute_script("return document.body.scrollHeight")
    driver.set_window_size(1400, min(max(height + 40, 1000), 6000))
    driver.save_screenshot(str(path))
    driver.set_window_size(1400, 2000)


def _reports_copy(tmp_path: Path) -> Path | None:
    """A copy of the repository's reports/ with every study's report rebuilt from its stored
    results by this code (None if no study ran there)."""
    from workbench.study.runner import rebuild_report

    src = REPO / "reports"
    runs = [e for e in discover().values()
            if (src / e.default_out.name / "manifest.json").is_file()]
    if not runs:
        return None
    dst = tmp_path / "reports"
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("*.html"))
    for e in runs:
        rebuild_report(e, dst / e.default_out.name)
    return dst


@pytest.mark.skipif(not os.environ.get("WORKBENCH_CHECK_REPORTS"),
                    reason="set WORKBENCH_CHECK_REPORTS=1 to check the runs in reports/")
def test_the_repositorys_reports_in_chromium(browser, site, tmp_path):
    """The real runs in reports/ (from `make study`), rebuilt in a copy, pass every check;
    screenshots of the index, the bound and the navigation report with
    WORKBENCH_SCREENSHOTS=DIR (the fixture's tiny runs stand in for a study not run)."""
    root = _reports_copy(tmp_path)
    if root is not None:
        problems, _, _ = check_site(browser, build_site(root, discover()))
        assert problems == []
    shots = os.environ.get("WORKBENCH_SCREENSHOTS")
    if shots:
        out = Path(shots)
        out.mkdir(parents=True, exist_ok=True)
        build_site(site, discover())
        for name, rel in (("index", "index.html"),
                          ("bound", "free_energy_bound/report.html"),
                          ("navigation", "navigation/report.html")):
            page = root / rel if root is not None and (root / rel).is_file() else site / rel
            _screenshot(browser, page, out / f"{name}.png")

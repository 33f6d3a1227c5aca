"""reports/index.html in a real browser: headless Chromium from Debian's packages driven by
Selenium (pointed at /usr/bin/chromium and /usr/bin/chromedriver; nothing is downloaded). The
page and every report page it links load without console errors, every image decodes and every
link resolves to a file. A broken image and a dead link planted in a report are caught."""

from __future__ import annotations

import shutil
from pathlib import Path
from urllib.parse import unquote, urlparse

import pytest

from workbench.study.report_site import build_site
from workbench.study.spec import registry as discover

CHROMIUM, CHROMEDRIVER = Path("/usr/bin/chromium"), Path("/usr/bin/chromedriver")


def test_site_html_without_a_browser(cli_reports, tmp_path):
    """Structure, independent of Chromium: sections, links, paper table, not-run studies."""
    root, _ = cli_reports
    reg = discover()
    html = build_site(root, reg).read_text()
    for name in reg:
        assert f'id="{name}"' in html
    assert "Not run yet: <code>workbench run navigation</code>" in html
    for href in ("tracking_comparison/report.html", "tracking_comparison/manifest.json",
                 "tracking_comparison/summary.json", "tracking_comparison/rollouts.csv",
                 "tracking_comparison/rollouts.parquet", "tracking_comparison/config.toml",
                 "tracking_demo/trajectories.png"):
        assert f'href="{href}"' in html, href
    assert "Paper vs ours" in html and "60% (≈60% of MC trajectories unsafe)" in html
    assert "SPEC 14.4 band" in html
    page = (root / "tracking_comparison" / "report.html").read_text()
    assert "<table>" in page and '<img alt="' in page and 'href="../index.html"' in page


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
              "--window-size=1400,1000"):
        opts.add_argument(a)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(options=opts, service=Service(str(CHROMEDRIVER)))
    driver.set_page_load_timeout(30)
    yield driver
    driver.quit()


def check_page(driver, path: Path) -> tuple[list[str], list[Path], int]:
    """Load ``path``; return the problems found, the local HTML pages it links and its number
    of images."""
    driver.get(path.resolve().as_uri())
    driver.execute_script("window.scrollTo(0, document.body.scrollHeight)")
    problems = [f"{path.name}: console {e['level']}: {e['message']}"
                for e in driver.get_log("browser") if e["level"] in ("SEVERE", "WARNING")]
    images = driver.execute_script(
        "return Array.from(document.images).map(i => [i.src, i.complete && i.naturalWidth > 0])")
    problems += [f"{path.name}: image does not load: {src}" for src, ok in images if not ok]
    pages = []
    for href in driver.execute_script(
            "return Array.from(document.links).map(a => a.href)"):
        url = urlparse(href)
        if url.scheme != "file":
            problems.append(f"{path.name}: link leaves the offline site: {href}")
            continue
        target = Path(unquote(url.path))
        if not target.is_file():
            problems.append(f"{path.name}: dead link: {href}")
        elif target.suffix == ".html":
            pages.append(target)
    return problems, pages, len(images)


def check_site(driver, index: Path) -> tuple[list[str], int, int]:
    """Check the index and every HTML page it links; (problems, pages checked, images on the
    index)."""
    problems, pages, n_images = check_page(driver, index)
    title = driver.title
    others = sorted(set(pages) - {index.resolve()})
    for page in others:
        problems += check_page(driver, page)[0]
    if title != "SAIS Workbench reports":
        problems.append(f"index title {title!r}")
    return problems, 1 + len(others), n_images


def test_index_loads_cleanly_in_chromium(browser, cli_reports):
    root, _ = cli_reports
    index = build_site(root, discover())
    problems, n_pages, n_images = check_site(browser, index)
    assert problems == []
    figures = len(list(root.glob("*/*.png")))
    assert n_pages == 3 and n_images == figures >= 8  # index + both report pages; every figure


def test_the_browser_check_catches_broken_images_and_links(browser, cli_reports, tmp_path):
    root, _ = cli_reports
    copy = tmp_path / "reports"
    shutil.copytree(root / "tracking_demo", copy / "tracking_demo")
    md = copy / "tracking_demo" / "report.md"
    md.write_text(md.read_text() + "\n![gone](missing.png)\n\n[data](gone.csv)\n")
    problems, _, _ = check_site(browser, build_site(copy, discover()))
    assert any("image does not load" in p and "missing.png" in p for p in problems)
    assert any("dead link" in p and "gone.csv" in p for p in problems)
    assert any("console SEVERE" in p and "missing.png" in p for p in problems)

"""``reports/index.html``: one offline page over every study's results.

For each registered study whose run directory (``ROOT/<dir of its default_out>``) exists: its
report.md rendered to report.html beside it (so the report's relative figure links keep
working), links to report.md, summary.json, manifest.json, config.toml and the tidy tables, the
paper's numbers beside ours (``StudySpec.paper``) and every figure as a thumbnail. Studies not
run yet are listed with the command that runs them. No scripts, no network: plain HTML and CSS.
"""

from __future__ import annotations

import html
import json
import os
import time
from collections.abc import Mapping
from pathlib import Path
from urllib.parse import quote

import markdown

from workbench.study.io import atomic_write_text, make_dirs

CSS = """
body { font: 15px/1.45 system-ui, sans-serif; max-width: 72rem; margin: 2rem auto;
       padding: 0 1rem; color: #222; }
h1, h2, h3 { line-height: 1.2; }
table { border-collapse: collapse; margin: .6rem 0; }
th, td { border: 1px solid #ccc; padding: .25rem .5rem; text-align: left; vertical-align: top; }
th { background: #f3f3f3; }
code, pre { background: #f6f6f6; font-size: 90%; }
pre { padding: .5rem; overflow-x: auto; }
img { max-width: 100%; }
.figs { display: flex; flex-wrap: wrap; gap: .6rem; }
.figs a { display: block; width: 22rem; }
.figs img { border: 1px solid #ddd; }
.muted { color: #666; }
section { border-top: 2px solid #ddd; margin-top: 2rem; }
"""

TABLE_SUFFIXES = (".csv", ".parquet")


def _page(title: str, body: str) -> str:
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            # an empty data: icon: no favicon request (a missing favicon is a console error)
            "<link rel=\"icon\" href=\"data:,\">"
            f"<title>{html.escape(title)}</title><style>{CSS}</style></head>\n"
            f"<body>\n{body}\n</body></html>\n")


def _href(*parts: str) -> str:
    return "/".join(quote(p) for p in parts)


def render_markdown(md_path: Path, back: str = "../index.html") -> Path:
    """``report.md`` -> ``report.html`` beside it (tables, fenced code), with a link back."""
    text = md_path.read_text()
    body = markdown.markdown(text, extensions=["tables", "fenced_code", "sane_lists"])
    title = next((ln.lstrip("# ").strip() for ln in text.splitlines() if ln.startswith("#")),
                 md_path.parent.name)
    out = md_path.with_suffix(".html")
    nav = (f"<p class=\"muted\"><a href=\"{back}\">all reports</a> · "
           f"<a href=\"{_href(md_path.name)}\">{html.escape(md_path.name)}</a></p>")
    atomic_write_text(out, _page(title, nav + body))
    return out


def _links(d: Path, rel: str) -> list[str]:
    items = []
    for name, label in (("report.html", "report"), ("report.md", "report.md"),
                        ("summary.json", "summary.json"), ("manifest.json", "manifest"),
                        ("config.toml", "config.toml"), ("run.json", "run.json"),
                        ("errors.json", "errors")):
        if (d / name).is_file():
            items.append(f"<a href=\"{_href(rel, name)}\">{label}</a>")
    for p in sorted(d.iterdir()):
        if p.suffix in TABLE_SUFFIXES and p.is_file():
            items.append(f"<a href=\"{_href(rel, p.name)}\">{html.escape(p.name)}</a>")
    return items


def _paper_table(entry, d: Path) -> str:
    if entry.paper is None:
        return "<p class=\"muted\">The paper reports no numbers for this study.</p>"
    try:
        rows = entry.fn("paper")(d)
    except Exception as exc:  # a report site must not fail over one study's old files
        return (f"<p class=\"muted\">Paper comparison unavailable: "
                f"{html.escape(type(exc).__name__)}: {html.escape(str(exc))}</p>")
    if not rows:
        return ""
    cells = "".join(
        "<tr>" + "".join(f"<td>{html.escape(str(v))}</td>" for v in r) + "</tr>" for r in rows)
    return ("<h3>Paper vs ours</h3><table><tr><th>quantity</th><th>paper</th><th>ours</th>"
            f"<th>note</th></tr>{cells}</table>")


def _study_section(entry, root: Path) -> str:
    d = root / entry.default_out.name
    rel = entry.default_out.name
    head = (f"<section id=\"{html.escape(entry.name)}\"><h2>{html.escape(entry.name)}</h2>"
            f"<p>{html.escape(entry.description)}</p>")
    if not d.is_dir() or not ((d / "report.md").is_file() or (d / "summary.json").is_file()):
        return (head + "<p class=\"muted\">Not run yet: <code>workbench run "
                f"{html.escape(entry.name)}</code> (profiles: "
                f"{html.escape(', '.join(entry.profiles))}).</p></section>")
    if (d / "report.md").is_file():
        render_markdown(d / "report.md")
    parts = [head]
    profile = _profile(d)
    when = time.strftime("%Y-%m-%d %H:%M UTC",
                         time.gmtime(max(p.stat().st_mtime for p in d.iterdir())))
    parts.append(f"<p class=\"muted\">Profile: {html.escape(profile)} · last written {when} · "
                 f"directory <code>{html.escape(rel)}/</code></p>")
    parts.append("<p>" + " · ".join(_links(d, rel)) + "</p>")
    parts.append(_paper_table(entry, d))
    figs = sorted(d.glob("*.png"), key=lambda p: (p.name != entry.figure, p.name))
    if figs:
        parts.append("<h3>Figures</h3><div class=\"figs\">" + "".join(
            f"<a href=\"{_href(rel, p.name)}\"><img src=\"{_href(rel, p.name)}\" "
            f"alt=\"{html.escape(p.stem)}\"></a>" for p in figs) + "</div>")
    parts.append("</section>")
    return "\n".join(parts)


def _profile(d: Path) -> str:
    for name in ("manifest.json", "summary.json"):
        p = d / name
        if p.is_file():
            try:
                data = json.loads(p.read_text())
            except ValueError:
                continue
            prof = (data.get("config") or {}).get("profile") or data.get("profile")
            if prof:
                return str(prof)
    return "unknown"


def _num(v, spec: str) -> str:
    """A number of a strict-JSON file (null where the writer had NaN or inf: "n/a")."""
    return "n/a" if v is None else format(float(v), spec)


def _bench_section(root: Path) -> str:
    p = root / "bench" / "bench.json"
    if not p.is_file():
        return ("<section id=\"bench\"><h2>bench</h2><p class=\"muted\">Not run yet: "
                "<code>workbench bench</code>.</p></section>")
    try:
        records = json.loads(p.read_text())
        records = records.get("records", records) if isinstance(records, dict) else records
        rows = "".join(
            f"<tr><td>{html.escape(str(r.get('name')))}</td><td>{_num(r.get('value'), '.4g')} "
            f"{html.escape(str(r.get('unit', '')))}</td><td>{html.escape(str(r.get('baseline')))}"
            f"</td><td>{_num(r.get('ratio'), '.3g')}</td></tr>" for r in records)
        table = ("<table><tr><th>benchmark</th><th>value</th><th>baseline</th>"
                 f"<th>speed-up</th></tr>{rows}</table>")
    except (ValueError, TypeError, AttributeError) as exc:
        table = f"<p class=\"muted\">Unreadable: {html.escape(str(exc))}</p>"
    return (f"<section id=\"bench\"><h2>bench</h2><p><a href=\"{_href('bench', 'bench.json')}\">"
            f"bench.json</a></p>{table}</section>")


def build_site(root: Path | str, registry: Mapping[str, object]) -> Path:
    """Write ``root/index.html`` (and each study's report.html); return its path. Files get
    mode ``0666 & ~umask``, directories ``0777 & ~umask`` (readable by others when the umask
    allows it)."""
    root = Path(os.path.expanduser(str(root)))
    make_dirs(root)
    toc = " · ".join(f"<a href=\"#{html.escape(n)}\">{html.escape(n)}</a>"
                     for n in [*registry, "bench"])
    body = [
        "<h1>SAIS Workbench reports</h1>",
        "<p>Every study's report, figures, tidy tables and manifest, with the paper's numbers "
        "beside ours. Regenerate with <code>make reports</code> (<code>workbench report</code>); "
        "run a study with <code>workbench run NAME</code>.</p>",
        f"<p>{toc}</p>",
        *(_study_section(e, root) for e in registry.values()),
        _bench_section(root),
    ]
    path = root / "index.html"
    atomic_write_text(path, _page("SAIS Workbench reports", "\n".join(body)))
    return path

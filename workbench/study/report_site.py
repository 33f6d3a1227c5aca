"""``reports/index.html``: one offline page over every study's results.

For each registered study whose run directory (``ROOT/<dir of its default_out>``) exists: its
report.md rendered to report.html beside it (so the report's relative figure links keep
working), links to report.md, summary.json, manifest.json, config.toml and the tidy tables, to
the report of each other profile's run (``ROOT/<dir>_<profile>``, where the make targets write
them), the paper's numbers beside ours (``StudySpec.paper``) and every figure as a thumbnail.
Studies not run yet are listed with the command that runs them. The page of assumptions
(``workbench/assumptions.md``) is rendered to ``assumptions.html`` beside the index; every
``assumptions §x.y`` in a report becomes a link to its section (``assumptions.html#sx-y``).

Mathematics in a report (LaTeX between ``$...$`` or ``$$...$$``) is converted to MathML
(latex2mathml) before the markdown is parsed, so that its underscores and asterisks stay
mathematics; browsers render MathML natively. No scripts, no network: plain HTML and CSS.

A run folder anywhere (``workbench report FOLDER``, ``workbench run --out FOLDER``) is rendered
on its own by :func:`render_run`: report.html and a copy of assumptions.html in the folder.
A report.md that is not UTF-8 or a truncated JSON file gives a page that says so, not a
traceback.
"""

from __future__ import annotations

import html
import json
import logging
import os
import re
import secrets
import time
from collections.abc import Mapping
from pathlib import Path
from urllib.parse import quote

import markdown

from workbench.study.html_safe import MATHML_TAGS, NoRawHtml, clean_html
from workbench.study.io import atomic_write_text, make_dirs

log = logging.getLogger("workbench.study")

ASSUMPTIONS_SOURCE = Path(__file__).resolve().parents[1] / "assumptions.md"
ASSUMPTIONS_PAGE = "assumptions.html"

CSS = """
body { font: 15px/1.45 system-ui, sans-serif; max-width: 72rem; margin: 2rem auto;
       padding: 0 1rem; color: #222; }
h1, h2, h3 { line-height: 1.2; }
.wide { overflow-x: auto; max-width: 100%; margin: .6rem 0; }
table { border-collapse: collapse; }
th, td { border: 1px solid #ccc; padding: .25rem .5rem; text-align: left; vertical-align: top; }
th { background: #f3f3f3; }
.nw { white-space: nowrap; }
code, pre { background: #f6f6f6; font-size: 90%; }
pre { padding: .5rem; overflow-x: auto; }
math { font-size: 110%; }
math[display="block"] { display: block math; margin: .8rem 0; overflow-x: auto;
                        max-width: 100%; }
img { max-width: 100%; }
.figs { display: flex; flex-wrap: wrap; gap: .6rem; }
.figs a { display: block; width: 22rem; }
.figs img { border: 1px solid #ddd; }
.muted { color: #666; }
.problem { color: #a00; }
section { border-top: 2px solid #ddd; margin-top: 2rem; }
"""

TABLE_SUFFIXES = (".csv", ".parquet")
MD_EXTENSIONS = ["tables", "fenced_code", "sane_lists", "attr_list", "toc"]


class ReportError(ValueError):
    """A report file that cannot be rendered (not UTF-8, unreadable): the message says which
    file, what is wrong and how to rebuild it."""


def _page(title: str, body: str) -> str:
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            # an empty data: icon: no favicon request (a missing favicon is a console error)
            "<link rel=\"icon\" href=\"data:,\">"
            f"<title>{html.escape(title)}</title><style>{CSS}</style></head>\n"
            f"<body>\n{body}\n</body></html>\n")


def _href(*parts: str) -> str:
    return "/".join(quote(p) for p in parts)


def read_text(path: Path) -> str:
    """The UTF-8 text of ``path``; :class:`ReportError` naming the file and the first bad
    byte when it is not UTF-8, or the reason when it cannot be read."""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise ReportError(f"{path}: cannot be read ({exc.strerror or exc})") from exc
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ReportError(f"{path} is not UTF-8 text (byte 0x{data[exc.start]:02x} at offset "
                          f"{exc.start}); rebuild it with `workbench report "
                          f"{Path(path).parent}`") from exc


def read_json(path: Path) -> dict | None:
    """A JSON object from ``path``; None when it is missing, truncated or not an object."""
    try:
        data = json.loads(read_text(path))
    except (ReportError, ValueError):
        return None
    return data if isinstance(data, dict) else None


# ------------------------------------------------------------------- mathematics and markdown
_CODE = re.compile(r"(```.*?```|`[^`\n]+`)", re.S)
_DISPLAY = re.compile(r"\$\$(.+?)\$\$", re.S)
# pandoc's rule: no space after the opening $, none before the closing $, no digit after it
_INLINE = re.compile(r"(?<![\\$\w])\$(?![\s$])([^$\n]+?)(?<![\s\\])\$(?![\d$])")
# "assumptions §3.3", "assumptions §3.3, §6, §12.1", "assumptions §6.1-§6.3"
_REF = re.compile(r"(?<!\[)\bassumptions (§\d+(?:\.\d+)*(?:(?:, |-| and )§\d+(?:\.\d+)*)*)")
_SECTION = re.compile(r"§(\d+(?:\.\d+)*)")
# a short table cell (a number with its interval) is kept on one line
_SHORT_CELL = re.compile(r"<(td|th)>([^<]{1,32})</\1>")


def anchor(section: str) -> str:
    """The anchor of a section of the page of assumptions: ``3.2`` -> ``s3-2``."""
    return "s" + section.replace(".", "-")


def _refs(match: re.Match, link) -> str:
    """One reference (or a list of them) with every section linked by ``link(text, section)``;
    the first link's text includes the word "assumptions"."""
    first = True

    def one(m: re.Match) -> str:
        nonlocal first
        text = ("assumptions " if first else "") + m.group(0)
        first = False
        return link(text, m.group(1))

    return _SECTION.sub(one, match.group(1))


def latex_to_mathml(latex: str, display: bool = False) -> str:
    """One LaTeX formula as MathML; a formula latex2mathml cannot convert is shown as its
    source in a ``<code>`` element (and logged)."""
    from latex2mathml.converter import convert

    try:
        return convert(latex.strip(), display="block" if display else "inline")
    except Exception as exc:  # latex2mathml raises several types for unsupported input
        log.warning("report: cannot convert the formula %r to MathML: %s", latex, exc)
        return f"<code class=\"tex\">{html.escape(latex.strip())}</code>"


def _protect_math(text: str, tag: str) -> tuple[str, list[str]]:
    """Replace every formula outside code by a token (``WBMATH<tag>N<i>X``: ``tag`` is new
    for every page, so no text of a report can name a token); return the text and the MathML
    of each token (in order)."""
    formulas: list[str] = []

    def keep(mathml: str) -> str:
        formulas.append(mathml)
        return f"WBMATH{tag}N{len(formulas) - 1}X"

    parts = _CODE.split(text)
    for i in range(0, len(parts), 2):  # even parts are outside code
        part = _DISPLAY.sub(lambda m: keep(latex_to_mathml(m.group(1), True)), parts[i])
        parts[i] = _INLINE.sub(lambda m: keep(latex_to_mathml(m.group(1))), part)
    return "".join(parts), formulas


def _link_refs(text: str, docs: str | None) -> str:
    """``assumptions §x.y`` outside code -> a markdown link to ``docs#sx-y``."""
    if docs is None:
        return text
    parts = _CODE.split(text)
    for i in range(0, len(parts), 2):
        parts[i] = _REF.sub(lambda m: _refs(m, lambda t, s: f"[{t}]({docs}#{anchor(s)})"),
                            parts[i])
    return "".join(parts)


def link_refs_html(escaped: str, docs: str | None) -> str:
    """``assumptions §x.y`` in already escaped HTML text -> a link to ``docs#sx-y``."""
    if docs is None:
        return escaped
    return _REF.sub(lambda m: _refs(m, lambda t, s: f"<a href=\"{docs}#{anchor(s)}\">{t}</a>"),
                    escaped)


def markdown_html(text: str, docs: str | None = None) -> str:
    """Markdown (with LaTeX formulas) -> HTML: formulas as MathML, ``assumptions §x.y`` as
    links to ``docs`` (None: left as text), every table in a box that scrolls sideways. Raw
    HTML in the text is shown as text, and only markdown's and MathML's elements come out,
    without scripts or event handlers (:mod:`workbench.study.html_safe`): a string a study
    echoes from its config reads as written."""
    tag = secrets.token_hex(8)
    text, formulas = _protect_math(text, tag)
    body = markdown.markdown(_link_refs(text, docs), extensions=[*MD_EXTENSIONS, NoRawHtml()])
    body = _SHORT_CELL.sub(r'<\1 class="nw">\2</\1>', body)
    body = re.sub(rf"WBMATH{tag}N(\d+)X",
                  lambda m: clean_html(formulas[int(m.group(1))], MATHML_TAGS | {"code"}), body)
    return clean_html(body).replace("<table>", "<div class=\"wide\"><table>").replace(
        "</table>", "</table></div>")


def _problem_page(title: str, message: str, nav: str = "") -> str:
    return _page(title, f"{nav}<h1>{html.escape(title)}</h1><p class=\"problem\">"
                        f"{html.escape(message)}</p>")


def render_markdown(md_path: Path, back: str | None = "../index.html",
                    docs: str | None = "../" + ASSUMPTIONS_PAGE) -> Path:
    """``report.md`` -> ``report.html`` beside it (tables, fenced code, MathML), with links
    back to the index (``back``) and to the page of assumptions (``docs``; None: none). A file
    that cannot be read gives a page that says why (and a warning in the log)."""
    md_path = Path(md_path)
    out = md_path.with_suffix(".html")
    links = [f"<a href=\"{back}\">all reports</a>"] if back else []
    links.append(f"<a href=\"{_href(md_path.name)}\">{html.escape(md_path.name)}</a>")
    if docs:
        links.append(f"<a href=\"{docs}\">assumptions</a>")
    nav = f"<p class=\"muted\">{' · '.join(links)}</p>"
    try:
        text = read_text(md_path)
    except ReportError as exc:
        log.warning("report: %s", exc)
        atomic_write_text(out, _problem_page(f"{md_path.parent.name}: report unreadable",
                                             str(exc), nav))
        return out
    title = next((ln.lstrip("# ").strip() for ln in text.splitlines() if ln.startswith("#")),
                 md_path.parent.name)
    atomic_write_text(out, _page(title, nav + markdown_html(text, docs)))
    return out


def render_assumptions(folder: Path, back: str | None = None,
                       source: Path | None = None) -> Path | None:
    """``workbench/assumptions.md`` -> ``folder/assumptions.html`` (None, and nothing
    written, when the installation has no such page)."""
    source = Path(source or ASSUMPTIONS_SOURCE)
    if not source.is_file():
        log.warning("report: %s is missing; reports link no assumptions page", source)
        return None
    out = Path(folder) / ASSUMPTIONS_PAGE
    try:
        text = read_text(source)
    except ReportError as exc:
        atomic_write_text(out, _problem_page("Assumptions", str(exc)))
        return out
    nav = f"<p class=\"muted\"><a href=\"{back}\">all reports</a></p>" if back else ""
    title = next((ln.lstrip("# ").strip() for ln in text.splitlines() if ln.startswith("# ")),
                 "Assumptions")
    atomic_write_text(out, _page(title, nav + markdown_html(text, docs=ASSUMPTIONS_PAGE)))
    return out


def render_run(folder: Path | str) -> Path:
    """``FOLDER/report.md`` -> ``FOLDER/report.html`` for a run folder anywhere. Inside a
    built site (the parent holds index.html and assumptions.html) the page links them;
    otherwise the page of assumptions is rendered into the folder itself."""
    folder = Path(os.path.expanduser(str(folder)))
    parent = folder.resolve().parent
    if (parent / "index.html").is_file() and (parent / ASSUMPTIONS_PAGE).is_file():
        return render_markdown(folder / "report.md", "../index.html", "../" + ASSUMPTIONS_PAGE)
    page = render_assumptions(folder)
    return render_markdown(folder / "report.md", None, ASSUMPTIONS_PAGE if page else None)


# ---------------------------------------------------------------------------------- the index
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


def _cell(value: object, docs: str | None) -> str:
    return link_refs_html(html.escape(str(value)), docs)


def _paper_table(entry, d: Path, docs: str | None) -> str:
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
        "<tr>" + "".join(f"<td>{_cell(v, docs)}</td>" for v in r) + "</tr>" for r in rows)
    return ("<h3>Paper vs ours</h3><div class=\"wide\"><table><tr><th>quantity</th>"
            f"<th>paper</th><th>ours</th><th>note</th></tr>{cells}</table></div>")


def _study_section(entry, root: Path, docs: str | None) -> str:
    d = root / entry.default_out.name
    rel = entry.default_out.name
    head = (f"<section id=\"{html.escape(entry.name)}\"><h2>{html.escape(entry.name)}</h2>"
            f"<p>{html.escape(entry.description)}</p>")
    others = _profile_runs(entry, root, docs)
    if not d.is_dir() or not ((d / "report.md").is_file() or (d / "summary.json").is_file()):
        return (head + "<p class=\"muted\">Not run yet: <code>workbench run "
                f"{html.escape(entry.name)}</code> (profiles: "
                f"{html.escape(', '.join(entry.profiles))}).</p>{others}</section>")
    parts = [head]
    if (d / "report.md").is_file():
        render_markdown(d / "report.md", "../index.html", f"../{docs}" if docs else None)
        try:
            read_text(d / "report.md")
        except ReportError as exc:
            parts.append(f"<p class=\"problem\">{html.escape(str(exc))}</p>")
    profile = _profile(d)
    when = time.strftime("%Y-%m-%d %H:%M UTC",
                         time.gmtime(max(p.stat().st_mtime for p in d.iterdir())))
    parts.append(f"<p class=\"muted\">Profile: {html.escape(profile)} · last written {when} · "
                 f"directory <code>{html.escape(rel)}/</code></p>")
    if read_json(d / "manifest.json") is None:
        parts.append("<p class=\"problem\">manifest.json is missing, truncated or not JSON: "
                     "this run's record is incomplete; <code>workbench run "
                     f"{html.escape(entry.name)} --out {html.escape(str(d))}</code> writes it "
                     "again (stored tasks are reused).</p>")
    parts.append("<p>" + " · ".join(_links(d, rel)) + "</p>")
    parts.append(others)
    parts.append(_paper_table(entry, d, docs))
    figs = sorted(d.glob("*.png"), key=lambda p: (p.name != entry.figure, p.name))
    if figs:
        parts.append("<h3>Figures</h3><div class=\"figs\">" + "".join(
            f"<a href=\"{_href(rel, p.name)}\"><img src=\"{_href(rel, p.name)}\" "
            f"alt=\"{html.escape(p.stem)}\"></a>" for p in figs) + "</div>")
    parts.append("</section>")
    return "\n".join(parts)


def profile_folders(entry, root: Path) -> dict[str, Path]:
    """The runs of ``entry``'s other profiles under ``root`` (``make study-... PROFILE=P``
    writes them to ``<study folder>_<P>``), by profile, that hold a run's manifest."""
    out = {}
    for profile in entry.profiles:
        d = root / f"{entry.default_out.name}_{profile}"
        if profile != entry.default_profile and (d / "manifest.json").is_file():
            out[profile] = d
    return out


def _profile_runs(entry, root: Path, docs: str | None) -> str:
    """A line linking the report of each other profile's run (rendered here)."""
    items = []
    for profile, d in profile_folders(entry, root).items():
        if (d / "report.md").is_file():
            render_markdown(d / "report.md", "../index.html", f"../{docs}" if docs else None)
            items.append(f"<a href=\"{_href(d.name, 'report.html')}\">{html.escape(profile)}</a>")
        else:
            items.append(f"{html.escape(profile)} (<code>{html.escape(d.name)}/</code>, no "
                         "report yet)")
    return f"<p>Other profiles' runs: {' · '.join(items)}</p>" if items else ""


def _other_runs(root: Path, registry: Mapping[str, object], docs: str | None) -> str:
    """The run folders under ``root`` that are not a study's own (e.g. a comparison on your
    own system, ``workbench run sampling-safety --config arm.toml --out reports/arm``): a
    link to each one's report, rendered here, with its study."""
    own = {e.default_out.name for e in registry.values()} | {"bench"}  # type: ignore[attr-defined]
    own |= {d.name for e in registry.values() for d in profile_folders(e, root).values()}
    runs = [d for d in sorted(root.iterdir())
            if d.is_dir() and d.name not in own and (d / "manifest.json").is_file()]
    if not runs:
        return ""
    items = []
    for d in runs:
        study = (read_json(d / "manifest.json") or {}).get("study", "unknown study")
        if (d / "report.md").is_file():
            render_markdown(d / "report.md", "../index.html", f"../{docs}" if docs else None)
            link = f"<a href=\"{_href(d.name, 'report.html')}\">{html.escape(d.name)}</a>"
        else:
            link = f"{html.escape(d.name)} (no report yet)"
        items.append(f"<li>{link}: {html.escape(str(study))}</li>")
    return ("<section id=\"other-runs\"><h2>Other runs</h2><p>Run folders beside the "
            "studies' own (your own systems, other configs).</p><ul>" + "".join(items)
            + "</ul></section>")


def _profile(d: Path) -> str:
    """The profile run.json records ("none (config file)" for a run from a config file)."""
    record = read_json(d / "run.json")
    if record is not None and "profile" in record:
        return str(record["profile"]) if record["profile"] else "none (config file)"
    for name in ("manifest.json", "summary.json"):
        data = read_json(d / name)
        if data is None:
            continue
        config = data.get("config")
        if not isinstance(config, dict):
            config = {}
        prof = config.get("profile") or data.get("profile")
        if prof:
            return str(prof)
    return "unknown"


def _num(v, spec: str) -> str:
    """A number of a strict-JSON file (null where the writer had NaN or inf: "n/a")."""
    try:
        return "n/a" if v is None else format(float(v), spec)
    except (TypeError, ValueError):
        return "n/a"


def _bench_section(root: Path) -> str:
    p = root / "bench" / "bench.json"
    if not p.is_file():
        return ("<section id=\"bench\"><h2>bench</h2><p class=\"muted\">Not run yet: "
                "<code>workbench bench</code>.</p></section>")
    try:
        records = json.loads(read_text(p))
        records = records.get("records", records) if isinstance(records, dict) else records
        rows = "".join(
            f"<tr><td>{html.escape(str(r.get('name')))}</td><td>{_num(r.get('value'), '.4g')} "
            f"{html.escape(str(r.get('unit', '')))}</td><td>{html.escape(str(r.get('baseline')))}"
            f"</td><td>{_num(r.get('ratio'), '.3g')}</td></tr>" for r in records)
        table = ("<div class=\"wide\"><table><tr><th>benchmark</th><th>value</th>"
                 f"<th>baseline</th><th>speed-up</th></tr>{rows}</table></div>")
    except (ReportError, ValueError, TypeError, AttributeError) as exc:
        table = f"<p class=\"problem\">Unreadable: {html.escape(str(exc))}</p>"
    return (f"<section id=\"bench\"><h2>bench</h2><p><a href=\"{_href('bench', 'bench.json')}\">"
            f"bench.json</a></p>{table}</section>")


def build_site(root: Path | str, registry: Mapping[str, object]) -> Path:
    """Write ``root/index.html``, ``root/assumptions.html`` and each study's report.html;
    return the index's path. Files get mode ``0666 & ~umask``, directories ``0777 & ~umask``
    (readable by others when the umask allows it)."""
    root = Path(os.path.expanduser(str(root)))
    make_dirs(root)
    docs = ASSUMPTIONS_PAGE if render_assumptions(root, back="index.html") else None
    toc = " · ".join(f"<a href=\"#{html.escape(n)}\">{html.escape(n)}</a>"
                     for n in [*registry, "bench"])
    about = (f"<p>What the paper states, what the workbench assumes where it is silent, and "
             f"where each choice comes from: <a href=\"{docs}\">assumptions</a>.</p>"
             if docs else "")
    body = [
        "<h1>SAIS Workbench reports</h1>",
        "<p>Every study's report, figures, tidy tables and manifest, with the paper's numbers "
        "beside ours. Regenerate with <code>make reports</code> (<code>workbench report</code>); "
        "run a study with <code>workbench run NAME</code>.</p>",
        about,
        f"<p>{toc}</p>",
        *(_study_section(e, root, docs) for e in registry.values()),
        _other_runs(root, registry, docs),
        _bench_section(root),
    ]
    path = root / "index.html"
    atomic_write_text(path, _page("SAIS Workbench reports", "\n".join(body)))
    return path

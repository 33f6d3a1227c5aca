"""Reports as HTML that shows what a config says, never runs it.

A study's report.md echoes strings from its config (labels, names, paths); on the report site
they must read as text. Two steps, in :func:`workbench.study.report_site.markdown_html`, cover
every study:

- the markdown is parsed without raw HTML (:class:`NoRawHtml`): ``<script>`` or
  ``<img onerror=...>`` in a report is shown as those characters;
- the HTML that comes out (markdown's, and the MathML of the formulas) is written again by
  :func:`clean_html`: only the elements that markdown and MathML produce are kept as elements
  (only MathML's inside a formula; any other tag is shown as text), event-handler attributes
  (``on...``), ``style`` and namespaced attributes are dropped, and a link or image whose
  address has a scheme other than http, https or mailto (``javascript:``, ``data:``) loses
  that address.
"""

from __future__ import annotations

import html
import re
from html.parser import HTMLParser

from markdown import Markdown
from markdown.extensions import Extension

__all__ = ["MATHML_TAGS", "NoRawHtml", "clean_html", "safe_url"]

MARKDOWN_TAGS = frozenset(
    "a abbr blockquote br code dd del div dl dt em h1 h2 h3 h4 h5 h6 hr img li ol p pre "
    "span strong sub sup table tbody td tfoot th thead tr ul".split())
MATHML_TAGS = frozenset(
    "math annotation menclose merror mfenced mfrac mi mmultiscripts mn mo mover mpadded "
    "mphantom mprescripts mroot mrow ms mspace msqrt mstyle msub msubsup msup mtable mtd "
    "mtext mtr munder munderover none semantics".split())
ALLOWED_TAGS = MARKDOWN_TAGS | MATHML_TAGS
VOID_TAGS = frozenset({"br", "hr", "img", "mspace", "mprescripts", "none"})
URL_ATTRIBUTES = frozenset({"href", "src", "action", "background", "poster", "cite"})
SAFE_SCHEMES = frozenset({"http", "https", "mailto"})
_SCHEME = re.compile(r"^([a-z][a-z0-9+.\-]*):")
_IGNORED_IN_URLS = re.compile(r"[\x00-\x20\x7f]+")  # browsers skip these inside a scheme


class NoRawHtml(Extension):
    """Markdown without raw HTML: tags in the text (a block or inline) stay text, escaped."""

    def extendMarkdown(self, md: Markdown) -> None:  # markdown's API names it
        md.preprocessors.deregister("html_block")
        md.inlinePatterns.deregister("html")


def safe_url(value: str) -> bool:
    """Whether a link or image address is relative or uses http, https or mailto."""
    match = _SCHEME.match(_IGNORED_IN_URLS.sub("", value).lower())
    return match is None or match.group(1) in SAFE_SCHEMES


def _attribute_kept(name: str, value: str | None) -> bool:
    if name.startswith("on") or name in ("style", "srcdoc", "formaction") or (
            ":" in name and name != "xmlns"):
        return False
    return name not in URL_ATTRIBUTES or safe_url(value or "")


class _Cleaner(HTMLParser):
    def __init__(self, tags: frozenset[str]) -> None:
        super().__init__(convert_charrefs=True)
        self.out: list[str] = []
        self.tags = tags

    def _tag(self, tag: str, attrs: list[tuple[str, str | None]], end: str) -> None:
        if tag not in self.tags:
            self.out.append(html.escape(self.get_starttag_text() or f"<{tag}>"))
            return
        kept = "".join(f' {k}="{html.escape(v or "")}"' for k, v in attrs
                       if _attribute_kept(k, v))
        self.out.append(f"<{tag}{kept}{end}>")

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self._tag(tag, attrs, " /" if tag in VOID_TAGS and tag in MARKDOWN_TAGS else "")

    def handle_startendtag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self._tag(tag, attrs, " /")

    def handle_endtag(self, tag: str) -> None:
        if tag in self.tags:
            if tag not in VOID_TAGS or tag not in MARKDOWN_TAGS:
                self.out.append(f"</{tag}>")
        else:
            self.out.append(html.escape(f"</{tag}>"))

    def handle_data(self, data: str) -> None:
        self.out.append(html.escape(data, quote=False))

    def handle_comment(self, data: str) -> None:
        pass  # markdown writes none; a comment could hide markup from a reader

    def handle_decl(self, decl: str) -> None:
        self.out.append(html.escape(f"<!{decl}>"))

    def unknown_decl(self, data: str) -> None:
        self.out.append(html.escape(f"<![{data}]>"))

    def handle_pi(self, data: str) -> None:
        self.out.append(html.escape(f"<?{data}>"))


def clean_html(fragment: str, tags: frozenset[str] = ALLOWED_TAGS) -> str:
    """``fragment`` written again with only the elements ``tags`` (markdown's and MathML's;
    :data:`MATHML_TAGS` for a formula), without event handlers, styles or addresses of other
    schemes; anything else is shown as text."""
    cleaner = _Cleaner(tags)
    cleaner.feed(fragment)
    cleaner.close()
    return "".join(cleaner.out)

"""Reports as HTML that shows what a config says, never runs it.

A study's report.md echoes strings from its config (labels, names, paths); on the report site
they must read as text. Two steps, in :func:`workbench.study.report_site.markdown_html`, cover
every study:

- the markdown is parsed without raw HTML (:class:`NoRawHtml`): ``<script>`` or
  ``<img onerror=...>`` in a report is shown as those characters;
- the HTML that comes out (markdown's, and the MathML of the formulas) is cleaned by
  :func:`clean_html` with nh3 (the Ammonia sanitiser): only the elements and attributes that
  markdown and MathML produce are kept (only MathML's inside a formula; any other element is
  removed, its text kept), so no event handler or style survives, and a link or image whose
  address has a scheme other than http, https or mailto (``javascript:``, ``data:``) loses
  that address.
"""

from __future__ import annotations

import html

import nh3
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
# the attributes markdown (with its attribute lists, tables and headings) and latex2mathml write
ATTRIBUTES = {
    "*": {"class", "id", "title", "align"},
    "a": {"href"}, "img": {"src", "alt", "width", "height"}, "td": {"colspan", "rowspan"},
    "th": {"colspan", "rowspan"}, "ol": {"start"},
    **{t: {"display", "xmlns", "mathvariant", "mathsize", "displaystyle", "scriptlevel",
           "fence", "stretchy", "symmetric", "maxsize", "minsize", "largeop", "movablelimits",
           "accent", "accentunder", "form", "lspace", "rspace", "separator", "separators", "open",
           "close", "width", "height", "depth", "linethickness", "columnalign", "rowalign",
           "columnspacing", "rowspacing", "columnlines", "rowlines", "frame", "notation",
           "encoding"} for t in MATHML_TAGS},
}
SAFE_SCHEMES = frozenset({"http", "https", "mailto"})


class NoRawHtml(Extension):
    """Markdown without raw HTML: tags in the text (a block or inline) stay text, escaped."""

    def extendMarkdown(self, md: Markdown) -> None:  # markdown's API names it
        md.preprocessors.deregister("html_block")
        md.inlinePatterns.deregister("html")


def safe_url(value: str) -> bool:
    """Whether a link or image address is relative or uses http, https or mailto (as
    :func:`clean_html` keeps it)."""
    kept = nh3.clean(f'<a href="{html.escape(value)}">x</a>', tags={"a"},
                     attributes={"a": {"href"}}, url_schemes=set(SAFE_SCHEMES), link_rel=None)
    return "href=" in kept


def clean_html(fragment: str, tags: frozenset[str] = ALLOWED_TAGS) -> str:
    """``fragment`` cleaned by nh3 to the elements ``tags`` (markdown's and MathML's;
    :data:`MATHML_TAGS` for a formula) and the attributes they use, with addresses only of
    http, https, mailto or relative; comments dropped."""
    return nh3.clean(fragment, tags=set(tags), attributes={
        t: a for t, a in ATTRIBUTES.items() if t == "*" or t in tags},
        url_schemes=set(SAFE_SCHEMES), link_rel=None, strip_comments=True)

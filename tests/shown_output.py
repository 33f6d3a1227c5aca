"""Shown output checked against printed output, number by number.

A page shows what a ```python block prints in the ```text block after it, marked by an HTML
comment that states the tolerance::

    <!-- output: rtol=0.02 atol=0.005; "final error {} m": atol=0.1; "{} ms per step": unchecked -->

Clauses are separated by ``;``. The first gives every number of the block its tolerance:
``exact`` (the printed token, character for character) or ``rtol=R [atol=A]`` (a number passes
when ``|printed - shown| <= max(R * |shown|, A)``; A, default 0, is the floor for numbers near
zero). Each further clause ``"PATTERN": TOLERANCE`` overrides it for the numbers at ``{}`` in
the quoted text around them (``*`` stands for any text on the line), and ``unchecked`` marks
numbers that vary by machine, such as timings. A pattern that matches no number is an error.
Text other than numbers must match exactly, modulo whitespace; a hexadecimal hash is text.

A figure quoted in prose from an example script's output is marked right after it::

    ends at about 0.09 m<!-- figure: own_model.py "BaS-MPPI: * final error {} m" atol=0.1 -->

The last number before the comment is compared with the first number the example prints at
``{}`` (the first matching line), at the stated tolerance (``exact`` or ``rtol``/``atol``, as
above; ``scale=100`` compares a printed fraction with a quoted percentage). A pattern
``json:a.b`` reads ``out["a"]["b"]`` from the JSON object an example prints as its last line.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

# a number is not part of a word, a file name or a hexadecimal hash ("fig5", "840e0695eb86")
NUMBER = re.compile(r"(?<![\w.])[-+]?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?(?![\w])")
OUTPUT = re.compile(r"<!-- output(?::(?P<spec>.*?))? -->\s*```text\n(?P<text>.*?)```", re.S)
FENCE = re.compile(r"^```(\w*)\n(.*?)^```", re.S | re.M)
FIGURE = re.compile(r"(?<!`)<!-- figure:\s+(?P<spec>.*?)\s*-->", re.S)  # not one quoted in `code`


@dataclass(frozen=True)
class Tolerance:
    """``rtol``/``atol`` as above; ``exact`` compares printed tokens; ``checked`` False skips."""

    rtol: float = 0.0
    atol: float = 0.0
    exact: bool = False
    checked: bool = True

    def accepts(self, printed: str, shown: str) -> bool:
        if not self.checked:
            return True
        if self.exact:
            return printed == shown
        p, s = float(printed), float(shown)
        return abs(p - s) <= max(self.rtol * abs(s), self.atol)

    def __str__(self) -> str:
        if not self.checked:
            return "unchecked"
        return "exact" if self.exact else f"rtol={self.rtol:g}, atol={self.atol:g}"


def parse_tolerance(text: str, where: str) -> tuple[Tolerance, dict[str, str]]:
    """``exact`` | ``unchecked`` | ``rtol=R [atol=A] [key=value ...]``: the tolerance and any
    other ``key=value`` options (e.g. ``scale``)."""
    words = text.split()
    if words == ["exact"]:
        return Tolerance(exact=True), {}
    if words == ["unchecked"]:
        return Tolerance(checked=False), {}
    options = {}
    for word in words:
        key, eq, value = word.partition("=")
        if not eq or key in options:
            raise ValueError(f"{where}: cannot read tolerance {text!r} (write 'exact', "
                             "'unchecked' or 'rtol=R atol=A')")
        options[key] = value
    if "rtol" not in options and "atol" not in options:
        raise ValueError(f"{where}: tolerance {text!r} states neither rtol nor atol")
    tol = Tolerance(float(options.pop("rtol", 0)), float(options.pop("atol", 0)))
    return tol, options


def pattern_regex(pattern: str) -> re.Pattern:
    """``{}`` -> a captured number, ``*`` -> any text on the line, whitespace -> any run."""
    parts = []
    for piece in re.split(r"(\{\}|\*|\s+)", pattern):
        if piece == "{}":
            parts.append(f"({NUMBER.pattern})")
        elif piece == "*":
            parts.append(r"[^\n]*?")
        elif piece.isspace():
            parts.append(r"\s+")
        elif piece:
            parts.append(re.escape(piece))
    if pattern.count("{}") != 1:
        raise ValueError(f"pattern {pattern!r} must hold exactly one {{}}")
    return re.compile("".join(parts))


@dataclass(frozen=True)
class Shown:
    """One marked output block: its text, its first line in the page and its tolerances."""

    page: str
    index: int  # 1-based among the page's output blocks
    line: int
    text: str
    default: Tolerance
    overrides: tuple[tuple[str, Tolerance], ...]

    @property
    def name(self) -> str:
        return f"{self.page}, output block {self.index} (line {self.line})"

    def tolerances(self) -> list[Tolerance]:
        """The tolerance of each number of the shown text, in order."""
        spans = [m.span() for m in NUMBER.finditer(self.text)]
        tols = [self.default] * len(spans)
        for pattern, tol in self.overrides:
            hits = [spans.index(m.span(1)) for m in pattern_regex(pattern).finditer(self.text)
                    if m.span(1) in spans]
            if not hits:
                raise ValueError(f"{self.name}: pattern {pattern!r} matches no shown number")
            for i in hits:
                tols[i] = tol
        return tols


def parse_output_spec(spec: str | None, where: str) -> tuple[Tolerance, tuple]:
    if spec is None or not spec.strip():
        raise ValueError(f"{where}: the output marker states no tolerance (write e.g. "
                         "'<!-- output: exact -->' or '<!-- output: rtol=0.01 atol=0.001 -->')")
    clauses = [c.strip() for c in re.split(r';(?=(?:[^"]*"[^"]*")*[^"]*$)', spec)]  # not in "..."
    default = block_tolerance(clauses[0], where)
    overrides = []
    for clause in clauses[1:]:
        m = re.fullmatch(r'"(.+)"\s*:\s*(.+)', clause, re.S)
        if not m:
            raise ValueError(f'{where}: cannot read clause {clause!r} (write "PATTERN": TOL)')
        pattern_regex(m[1])  # fails early on a pattern without {}
        overrides.append((m[1], block_tolerance(m[2], where)))
    return default, tuple(overrides)


def block_tolerance(text: str, where: str) -> Tolerance:
    tol, options = parse_tolerance(text, where)
    if options:
        raise ValueError(f"{where}: unknown tolerance options {sorted(options)} in {text!r}")
    return tol


def page_blocks(path: Path, name: str | None = None) -> list[tuple[str, Shown | None]]:
    """(code, its shown output or None) of each ```python block of a page, in order. A ```text
    block right after a python block is shown output and must be marked; a marker elsewhere is
    an error."""
    name = name or path.name
    text = path.read_text()
    marked = {m.start("text") - len("```text\n"): m for m in OUTPUT.finditer(text)}
    if text.count("<!-- output") != len(marked):
        raise ValueError(f"{name}: an output marker that is not right above a ```text block")
    out: list[tuple[str, Shown | None]] = []
    previous: tuple[str, int] | None = None  # the language and end of the fence before
    for m in FENCE.finditer(text):
        lang, body, start = m[1], m[2], m.start()
        line = text.count("\n", 0, start) + 2  # the first line inside the fence
        after_python = previous is not None and previous[0] == "python" and re.fullmatch(
            r"\s*(<!--.*?-->\s*)?", text[previous[1]:start], re.S) is not None
        if start in marked:
            where = f"{name}, line {line}"
            if not after_python:
                raise ValueError(f"{where}: an output block that follows no python block")
            default, overrides = parse_output_spec(marked[start]["spec"], where)
            index = sum(shown is not None for _, shown in out) + 1
            out[-1] = (out[-1][0], Shown(name, index, line, body, default, overrides))
        elif lang == "text" and after_python:
            raise ValueError(f"{name}, line {line}: a text block right after a python block is "
                             "shown output: mark it with <!-- output: TOLERANCE -->")
        elif lang == "python":
            out.append((body, None))
        previous = (lang, m.end())
    return out


def template(text: str) -> str:
    """The text with every number replaced by '#', whitespace collapsed."""
    return " ".join(NUMBER.sub("#", text).split())


def compare(shown: Shown, printed: str) -> list[str]:
    """What differs between a shown block and what its code printed, one message each."""
    if template(printed) != template(shown.text):
        want, got = shown.text.strip().splitlines(), printed.strip().splitlines()
        for i in range(max(len(want), len(got))):
            w = want[i] if i < len(want) else "(nothing)"
            g = got[i] if i < len(got) else "(nothing)"
            if template(w) != template(g):
                return [f"{shown.name}: text differs on line {shown.line + i}:\n  shown   "
                        f"{w.strip()}\n  printed {g.strip()}"]
        return [f"{shown.name}: text differs:\n{shown.text}\nprinted\n{printed}"]
    problems = []
    starts = [m.start() for m in NUMBER.finditer(shown.text)]
    pairs = zip(NUMBER.findall(shown.text), NUMBER.findall(printed), shown.tolerances(), starts,
                strict=True)
    for s, p, tol, start in pairs:
        if not tol.accepts(p, s):
            line = shown.line + shown.text.count("\n", 0, start)
            context = shown.text.splitlines()[line - shown.line].strip()
            problems.append(f"{shown.name}: number {s} on line {line} is printed as {p}, beyond "
                            f"its tolerance ({tol}): {context!r}")
    return problems


@dataclass(frozen=True)
class Figure:
    """A figure quoted in prose, with the example output it is checked against."""

    page: str
    line: int
    value: str
    example: str
    pattern: str
    tolerance: Tolerance
    scale: float

    def printed_value(self, output: str) -> float:
        if self.pattern.startswith("json:"):
            value = json.loads(output.strip().splitlines()[-1])
            for key in self.pattern[5:].split("."):
                value = value[key]
            return self.scale * float(value)
        m = pattern_regex(self.pattern).search(output)
        if not m:
            raise AssertionError(f"{self.page}, line {self.line}: {self.example} printed no "
                                 f"line matching {self.pattern!r}:\n{output}")
        return self.scale * float(m[1])

    def check(self, output: str) -> list[str]:
        printed = self.printed_value(output)
        tol = self.tolerance
        text = f"{printed:g}"
        if tol.exact:
            ok = float(self.value) == printed
        else:
            ok = tol.accepts(text, self.value)
        if ok:
            return []
        return [f"{self.page}, line {self.line}: figure {self.value} is printed by {self.example} "
                f"as {text}, beyond its tolerance ({tol})"]


def figures(path: Path, name: str | None = None) -> list[Figure]:
    """Every ``<!-- figure: ... -->`` of a page, with the number quoted before it."""
    name = name or path.name
    text = path.read_text()
    found = []
    for m in FIGURE.finditer(text):
        line = text.count("\n", 0, m.start()) + 1
        where = f"{name}, line {line}"
        spec = re.fullmatch(r'(\S+\.py)\s+("(?P<q>.+?)"|(?P<j>json:\S+))\s+(?P<tol>.+)',
                            m["spec"].strip())
        if not spec:
            raise ValueError(f'{where}: cannot read figure marker {m[0]!r} (write '
                             '<!-- figure: EXAMPLE.py "PATTERN {}" TOLERANCE -->)')
        before = NUMBER.findall(re.sub(r"<!--.*?-->", "", text[:m.start()], flags=re.S)[-80:])
        if not before:
            raise ValueError(f"{where}: no quoted number before the figure marker")
        tol, options = parse_tolerance(spec["tol"], where)
        scale = float(options.pop("scale", 1))
        if options:
            raise ValueError(f"{where}: unknown options {sorted(options)}")
        pattern = spec["q"] or spec["j"]
        if not pattern.startswith("json:"):
            pattern_regex(pattern)
        found.append(Figure(name, line, before[-1], spec[1], pattern, tol, scale))
    return found

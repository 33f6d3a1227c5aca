"""Report formatting: markdown tables, rates with intervals, numbers that may be missing,
claims that are printed only when the numbers support them, references to the page of
assumptions, whether a run is comparable with the paper, and figures as PNG bytes."""

from __future__ import annotations

import io
import json
import logging
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import workbench.study.config_io as config_io
from workbench.study.spec import PaperRow
from workbench.study.summary import Rate

log = logging.getLogger("workbench.study")

ASSUMPTIONS = "assumptions"  # the documentation page of assumptions (assumptions.html)


def md_table(header: Sequence[str], rows: Iterable[Sequence[object]]) -> list[str]:
    """A markdown table as lines."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return lines


def pct(x: float, digits: int = 1) -> str:
    return f"{100 * x:.{digits}f}%"


def fmt_rate(rate: Rate, digits: int = 1) -> str:
    """``12.3% [10.1, 14.9]`` (95% Wilson interval, in percent); ``n/a (no cases)`` for an
    empty rate."""
    if rate.n == 0 or not math.isfinite(rate.value):
        return "n/a (no cases)"
    return (f"{100 * rate.value:.{digits}f}% [{100 * rate.low:.{digits}f}, "
            f"{100 * rate.high:.{digits}f}]")


def num(x: Any, spec: str = ".3g", why: str = "") -> str:
    """``x`` formatted with ``spec``; ``n/a`` (with the reason ``why``, when given) for a
    missing or non-finite number, so that a report never prints ``nan`` or ``inf``."""
    try:
        ok = x is not None and math.isfinite(float(x))
    except (TypeError, ValueError):
        ok = False
    if not ok:
        return f"n/a ({why})" if why else "n/a"
    return format(float(x), spec)


def see(section: str) -> str:
    """A reference to a section of the page of assumptions: ``assumptions §11.2``. The report
    site turns it into a link to ``assumptions.html#s11-2``."""
    return f"{ASSUMPTIONS} §{section}"


@dataclass(frozen=True)
class Claim:
    """An interpretive sentence, the condition under which the data support it (computed from
    the numbers, not typed in), and the numbers that decide it."""

    text: str
    holds: bool
    evidence: str = ""


def supported(claims: Iterable[Claim], bullet: str = "- ") -> list[str]:
    """The sentences of the claims that hold; the others are not printed."""
    return [f"{bullet}{c.text}" for c in claims if c.holds]


def tasks_phrase(computed: int, n_tasks: int) -> str:
    """How many tasks a run computed, and how many it resumed from the store."""
    rest = n_tasks - computed
    return (f"{computed} of {n_tasks} tasks computed"
            + (f", {rest} resumed from `tasks/`" if rest else ""))


# ------------------------------------------------------------------ comparable with the paper?
@dataclass(frozen=True)
class Provenance:
    """Where a run's config comes from and whether the paper's numbers apply to it.

    profile: the profile recorded for the run (run.json; None for a config file or no record);
    reference: the profile that reproduces the paper's set-up; changes: every difference from
    it outside the sizes (``key = ours (paper set-up: theirs)``)."""

    profile: str | None
    reference: str
    changes: tuple[str, ...]

    @property
    def comparable(self) -> bool:
        return not self.changes

    def banner(self, what: str) -> list[str]:
        """Report lines for a custom run (nothing for a comparable one)."""
        if self.comparable:
            return []
        shown = "; ".join(self.changes[:8]) + ("; ..." if len(self.changes) > 8 else "")
        return [f"**Custom run: not comparable with {what}.** Its set-up differs from the "
                f"paper's (profile `{self.reference}`) beyond the sample sizes: {shown}. The "
                "paper's numbers are left out of this report; every statement below is about "
                "this run alone.", ""]


def _flat(d: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, Mapping):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _short(v: Any, width: int = 60) -> str:
    if isinstance(v, list | tuple) and len(v) > 4:
        text = f"{len(v)} items: " + json.dumps(list(v[:2]), default=str)[:-1] + ", ...]"
    else:
        text = json.dumps(v, default=str) if not isinstance(v, str) else repr(v)
    return text if len(text) <= width else text[: width - 3] + "..."


def config_changes(config: Any, reference: Any, sizes: Iterable[str] = ()) -> tuple[str, ...]:
    """Every dotted key whose value differs between two configs of one dataclass, outside
    ``sizes`` (a size key also covers the keys below it, e.g. ``sweep`` -> ``sweep.x``)."""
    ours, theirs = (_flat(config_io.to_dict(c)) for c in (config, reference))
    skip = tuple(sizes)

    def sized(key: str) -> bool:
        return any(key == s or key.startswith(s + ".") for s in skip)

    keys = sorted(k for k in set(ours) | set(theirs) if not sized(k))
    return tuple(f"{k} = {_short(ours.get(k))} (paper set-up: {_short(theirs.get(k))})"
                 for k in keys if ours.get(k) != theirs.get(k))


def recorded_profile(out: Path | str) -> str | None:
    """The profile run.json records for the run in ``out`` (None if none or unreadable)."""
    try:
        prof = json.loads((Path(out) / "run.json").read_text()).get("profile")
    except (OSError, ValueError, AttributeError):
        return None
    return prof if isinstance(prof, str) else None


def provenance(spec: Any, config: Any, out: Path | str | None = None, sizes: Iterable[str] = (),
               reference: str = "paper") -> Provenance:
    """Compare ``config`` with the config of the study's ``reference`` profile (the paper's
    set-up), ignoring ``sizes`` (counts, seeds, sweeps: keys whose change keeps the paper's
    numbers comparable)."""
    ref = config_io.load(spec.config_type, config_io.read_toml(spec.profiles[reference]),
                         aliases=spec.aliases)
    return Provenance(recorded_profile(out) if out is not None else None, reference,
                      config_changes(config, ref, sizes))


def not_compared_row(prov: Provenance | None, paper: str, what: str):
    """The report site's one row for a run whose numbers are not set beside the paper's (a
    custom run, or a run whose config.toml is unreadable); None for a comparable run."""
    if prov is not None and prov.comparable:
        return None
    why = ("its config.toml is unreadable" if prov is None else
           "; ".join(prov.changes[:3]) + ("; ..." if len(prov.changes) > 3 else ""))
    return PaperRow("this run", paper, "not compared",
                    f"custom run: not comparable with {what} ({why})")


def run_provenance(spec: Any, out: Path | str, sizes: Iterable[str] = (),
                   reference: str = "paper") -> Provenance | None:
    """:func:`provenance` of the finished run in ``out`` (its config.toml); None when the
    config cannot be read."""
    try:
        config = config_io.load(spec.config_type, config_io.read_toml(Path(out) / "config.toml"),
                                aliases=spec.aliases)
    except (OSError, ValueError):
        return None
    return provenance(spec, config, out, sizes, reference)


# ------------------------------------------------------------------------------------ figures
def figure_problems(fig) -> list[str]:
    """What makes a figure hard to read: an axes without an x or y label, or a line whose
    points fall outside the axes' limits (clipped; an axes with gid ``"zoom"`` may)."""
    import numpy as np

    problems = []
    for i, ax in enumerate(fig.get_axes()):
        if not ax.get_visible() or not ax.axison:
            continue
        name = ax.get_title() or f"axes {i}"
        if not ax.get_xlabel().strip():
            problems.append(f"{name}: no x label")
        if not ax.get_ylabel().strip():
            problems.append(f"{name}: no y label")
        if ax.get_gid() == "zoom":  # a zoom cuts off its lines on purpose
            continue
        (x0, x1), (y0, y1) = sorted(ax.get_xlim()), sorted(ax.get_ylim())
        for line in ax.get_lines():
            x = np.asarray(line.get_xdata(), float)
            y = np.asarray(line.get_ydata(), float)
            if x.shape != y.shape or x.size == 0 or line.get_transform() != ax.transData:
                continue
            ok = np.isfinite(x) & np.isfinite(y)
            tol = 1e-9 * max(1.0, abs(x1 - x0), abs(y1 - y0))
            out = ok & ((x < x0 - tol) | (x > x1 + tol) | (y < y0 - tol) | (y > y1 + tol))
            if out.any():
                problems.append(f"{name}: {int(out.sum())} of {int(ok.sum())} points of a "
                                "line outside the axes (clipped)")
                break
    return problems


def png_bytes(fig, dpi: int = 100) -> bytes:
    """A matplotlib figure as PNG bytes (tight layout); the figure is closed. A figure with an
    unlabelled axis or clipped lines is logged as a warning (logger ``workbench.study``)."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.tight_layout()
    for p in figure_problems(fig):
        log.warning("figure: %s", p)
    fig.savefig(buf, format="png", dpi=dpi)
    plt.close(fig)
    return buf.getvalue()

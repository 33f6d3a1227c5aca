"""Report formatting: markdown tables, rates with intervals, claims that are printed only
when the numbers support them, figures as PNG bytes."""

from __future__ import annotations

import io
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from workbench.study.summary import Rate


def md_table(header: Sequence[str], rows: Iterable[Sequence[object]]) -> list[str]:
    """A markdown table as lines."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return lines


def pct(x: float, digits: int = 1) -> str:
    return f"{100 * x:.{digits}f}%"


def fmt_rate(rate: Rate, digits: int = 1) -> str:
    """``12.3% [10.1, 14.9]`` (95% Wilson interval, in percent)."""
    return (f"{100 * rate.value:.{digits}f}% [{100 * rate.low:.{digits}f}, "
            f"{100 * rate.high:.{digits}f}]")


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


def png_bytes(fig, dpi: int = 100) -> bytes:
    """A matplotlib figure as PNG bytes (tight layout); the figure is closed."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png", dpi=dpi)
    plt.close(fig)
    return buf.getvalue()

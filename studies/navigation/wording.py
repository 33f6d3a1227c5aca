"""How the navigation study words its results: the controllers' display names and the number
phrases that the findings, the evidence, the figures and the report share."""

from __future__ import annotations

from workbench.study.report import num

NAMES = {"bas_mppi": "BaS-MPPI", "sa_rmppi": "SA-RMPPI", "rmppi": "RMPPI (plain iLQG gains)",
         "mppi_crash": "MPPI (crash cost only)"}


def points(x: float) -> str:
    """A fraction in percent with one decimal, without the percent sign: ``12.3``."""
    return f"{100 * x:.1f}"


def metres(x: float, why: str = "no safe episodes") -> str:
    """A distance in metres, or why there is none."""
    v = num(x, ".4f", why)
    return v if v.startswith("n/a") else f"{v} m"


def seconds(x: float) -> str:
    """A time in seconds, or why there is none."""
    v = num(x, ".2f", "none within the goal radius")
    return v if v.startswith("n/a") else f"{v} s"


def paired_difference(p) -> str:
    """A paired safety difference (:class:`~studies.navigation.paired.Paired`): points with
    their 95% interval and the exact McNemar test."""
    return (f"{points(p.difference)} points [{points(p.low)}, {points(p.high)}], McNemar p = "
            f"{num(p.p_value, '.3g')} (b = {p.b}, c = {p.c}, n = {p.n})")

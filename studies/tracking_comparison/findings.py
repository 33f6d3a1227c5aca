"""Every interpretive sentence of the report, as a claim whose condition is computed from the
summary's numbers and 95% intervals; the report prints only the claims that hold."""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise

from studies.tracking_comparison.config import RELEVANT
from studies.tracking_comparison.paper import PAPER_BY_METHOD, PAPER_ORDER, TOUCH_TOLERANCE
from studies.tracking_comparison.summary import Outcome, TrackingSummary
from studies.tracking_comparison.wording import PARAM_NAMES, SHORT
from workbench.study import Claim, Rate, fmt_rate


@dataclass(frozen=True)
class Ranking:
    """Methods ordered by a rate (point estimates, lowest first), whether that is the paper's
    order, and whether neighbours' 95% intervals are disjoint."""

    metric: str
    order: tuple[str, ...]
    paper_order: bool
    separated: bool

    @classmethod
    def of(cls, outcomes: tuple[Outcome, ...], metric: str) -> Ranking | None:
        rates = {o.method: getattr(o, metric) for o in outcomes}
        if set(rates) != set(PAPER_ORDER):
            return None
        order = tuple(sorted(rates, key=lambda m: (rates[m].value, m)))
        strict = all(rates[a].value < rates[b].value for a, b in pairwise(PAPER_ORDER))
        sep = all(rates[a].below(rates[b]) for a, b in pairwise(PAPER_ORDER))
        return cls(metric, order, strict, sep)

    def text(self) -> str:
        return " < ".join(SHORT[m] for m in self.order)


def _sweep_rates(s: TrackingSummary, method: str, parameter: str) -> list[tuple[object, Outcome]]:
    pts = [(p.value, p.get(method)) for p in s.sweep if p.parameter == parameter]
    return [(v, o) for v, o in pts if o is not None]


def ecbf_claims(s: TrackingSummary) -> list[Claim]:
    e = s.method("ecbf")
    if e is None:
        return []
    before_cfg = s.config["base"]["ecbf_noise"] == "before"
    out = [Claim(f"With the noise entering before the filter, no ECBF rollout left the safe set "
                 f"(0 of {e.n}); every ECBF failure ({e.failure.k} of {e.n}) is a missed target.",
                 before_cfg and e.unsafe.k == 0 and e.failure.k > 0,
                 f"unsafe {e.unsafe.k}, failure {e.failure.k}")]
    b, a = (s.point("ecbf_noise", v) for v in ("before", "after"))
    if a and b and a.get("ecbf") and b.get("ecbf"):
        ua, ub = a.get("ecbf").unsafe, b.get("ecbf").unsafe
        out.append(Claim(
            f"With the noise after the filter (assumptions §13 E7) ECBF is unsafe in "
            f"{fmt_rate(ua)} of rollouts against {fmt_rate(ub)} with the noise before it: where "
            "the noise enters decides whether ECBF loses safety, and the paper's remark that the "
            "filter 'is unable to maintain safety with large control deviations' fits the "
            "noise-after placement.",
            ua.above(ub), "disjoint 95% intervals"))
    main = [p for p in s.radius if p.source == "main" and p.method == "ecbf"]
    if len(main) >= 2:
        lo, hi = main[0], main[-1]
        out.append(Claim(
            f"The ECBF failure rate depends strongly on the assumed success radius: "
            f"{fmt_rate(lo.failure)} at {lo.radius:g} m, {fmt_rate(hi.failure)} at "
            f"{hi.radius:g} m.", lo.failure.above(hi.failure), "disjoint 95% intervals"))
        paper = PAPER_BY_METHOD["ecbf"].value
        inside = [p.radius for p in main if p.failure.contains(paper)]
        out.append(Claim(f"The paper's ≈{100 * paper:.0f}% ECBF failure lies inside our 95% "
                         f"interval at a success radius of {', '.join(f'{r:g}' for r in inside)}"
                         " m.", bool(inside), "interval contains the paper's value"))
        out.append(Claim(f"At no swept success radius does our 95% interval of the ECBF failure "
                         f"rate contain the paper's ≈{100 * paper:.0f}%.", not inside))
        pair = next(((a, b) for a, b in pairwise(main)
                     if a.failure.low > paper > b.failure.high), None)
        if pair:
            a, b = pair
            out.append(Claim(
                f"The paper's ≈{100 * paper:.0f}% corresponds to a success radius between "
                f"{a.radius:g} m ({fmt_rate(a.failure)}) and {b.radius:g} m "
                f"({fmt_rate(b.failure)}).", True, "intervals on either side of the value"))
    return out


def al_claims(s: TrackingSummary) -> list[Claim]:
    al = s.method("al")
    nom = next((n for n in s.nominal if n.method == "al"), None)
    if al is None or nom is None:
        return []
    h = nom.info["closed_loop_min_h"]
    out = [Claim(f"AL-iLQG's nominal trajectory touches the constraint (noise-free closed-loop "
                 f"min h = {h:.1e} m², |min h| < {TOUCH_TOLERANCE:g} m²); under noise "
                 f"{fmt_rate(al.unsafe)} of its rollouts are unsafe.", abs(h) < TOUCH_TOLERANCE)]
    paper = PAPER_BY_METHOD["al"].value
    assumed = [p for p in RELEVANT["al"] if p != "noise_std"]  # the noise level is the paper's
    pts = [(p, v, o) for p in assumed for v, o in _sweep_rates(s, "al", p)]
    if pts:
        p, v, best = min(pts, key=lambda t: t[2].unsafe.value)
        out.append(Claim(
            "No swept assumed value brings the AL unsafe rate down to the paper's "
            f"≈{100 * paper:.0f}%: its lowest point, {fmt_rate(best.unsafe)} at "
            f"{PARAM_NAMES[p]} = {v}, has its 95% interval above it, so the gap is not "
            "explained by the swept assumed values.",
            best.unsafe.low > paper))
    return out


def bas_claims(s: TrackingSummary) -> list[Claim]:
    bas = s.method("bas")
    if bas is None:
        return []
    qb = sorted(_sweep_rates(s, "bas", "q_beta"), key=lambda t: float(t[0]))
    out = []
    if len(qb) >= 2:
        o0, o1 = qb[0][1], qb[-1][1]
        rates = [o.unsafe.value for _, o in qb]
        text = ", ".join(f"{v:g}: {fmt_rate(o.unsafe)}" for v, o in qb)
        out.append(Claim(f"A heavier barrier weight makes BaS safer: its unsafe rate falls as "
                         f"q_beta grows ({text}).",
                         all(a >= b for a, b in pairwise(rates)) and o0.unsafe.above(
                             o1.unsafe), "monotone, end points with disjoint intervals"))
        out.append(Claim(f"A heavier barrier weight makes BaS less safe: its unsafe rate rises "
                         f"with q_beta ({text}).", o0.unsafe.below(o1.unsafe)))
    all_bas = [bas, *(o for p in s.sweep for o in p.outcomes if o.method == "bas")]
    out.append(Claim("BaS-iLQG left the safe set in no rollout, at the base point and at every "
                     "sweep point.", all(o.unsafe.k == 0 for o in all_bas)))
    return out


def ranking_claims(s: TrackingSummary) -> list[Claim]:
    r = Ranking.of(s.methods, "failure")
    if r is None:
        return []
    out = [Claim("By failure rate the paper's ranking BaS < ECBF < AL holds, with disjoint 95% "
                 "intervals.", r.paper_order and r.separated),
           Claim("By failure rate the paper's ranking BaS < ECBF < AL holds by point estimates, "
                 "but neighbouring 95% intervals overlap.", r.paper_order and not r.separated),
           Claim(f"By failure rate the paper's ranking does not hold: {r.text()}.",
                 not r.paper_order)]
    pts = [Ranking.of(p.outcomes, "failure") for p in s.sweep]
    pts = [p for p in pts if p is not None]
    if pts:
        held = sum(p.paper_order for p in pts)
        out.append(Claim(f"The paper's ranking by failure rate holds at {held} of {len(pts)} "
                         "sweep points (point estimates; ties count as not holding).", True))
    return out


def drivers(s: TrackingSummary, method: str, metric: str) -> list[tuple[str, float, str]]:
    """(parameter, range of the rate, text) per swept parameter, largest range first."""
    out = []
    for p in RELEVANT[method]:
        pts = _sweep_rates(s, method, p)
        if len(pts) < 2:
            continue
        rates: list[Rate] = [getattr(o, metric) for _, o in pts]
        text = ", ".join(f"{v:g}: {100 * r.value:.1f}%" if not isinstance(v, str) else
                         f"{v}: {100 * r.value:.1f}%" for (v, _), r in zip(pts, rates, strict=True))
        out.append((p, max(r.value for r in rates) - min(r.value for r in rates), text))
    return sorted(out, key=lambda t: -t[1])


def all_claims(s: TrackingSummary) -> dict[str, list[Claim]]:
    return {"ecbf": ecbf_claims(s), "al": al_claims(s), "bas": bas_claims(s),
            "ranking": ranking_claims(s)}

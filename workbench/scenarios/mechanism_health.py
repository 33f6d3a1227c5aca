"""Whether each safe-sampling method's mechanism did its job: checks of the activity a method
reports (:attr:`~workbench.scenarios.methods.MethodSpec.activity`, a key of
:attr:`~workbench.sampling.step_stats.StepStats.activity`) and of its safety against the method
it wraps (:attr:`~workbench.scenarios.methods.MethodSpec.wraps`).

Activity values are per-step numbers in [0, 1]: a flag (a shield repair, a backup control, a
tracked nominal) or a share (of samples, sample-steps or horizon steps). They count effects,
not calls: a step counts only when the mechanism changed the applied control, or the samples'
controls, costs or gains that determine it (:mod:`workbench.sampling.feedback.effect`). A
mechanism

- **never acted** when its activity is 0 on every step: the method ran as if without it;
- **acted on every step** when its activity is 1 on every step: a flag raised on every step, or
  a share at its largest (every sample or horizon step) on every step. It then no longer
  responds to the state (a backup that overrides every proposal). A share that is positive on
  every step but below 1 is a mechanism at work, not a finding.

The same two rules decide a study cell from the per-episode means of its episodes (a mean is 0,
or 1, exactly when every step's value is). Neither is judged on fewer than :data:`MIN_STEPS`
steps (assumptions §12.3).

A method is **less safe than the method it wraps** when, on the same disturbance realisations
(common random numbers: same cell and realisation), the one-sided exact McNemar test on the
discordant pairs (:func:`less_safe_p`: only the wrapped method safe in ``c`` of the ``b + c``
discordant realisations, against ``c ~ Binomial(b + c, 1/2)``) rejects equal safety at
:data:`LEVEL` after Holm's correction over the comparisons of one report that have a
discordant pair (assumptions §12.3).

:func:`episode_health` checks one closed-loop episode; the registered methods built by
:func:`workbench.scenarios.methods.build` carry an :class:`EpisodeCheck`, so
:func:`workbench.sim.closed_loop` warns (:class:`MechanismWarning`) when one of them never
acted or acted on every step. :func:`study_health` checks a study's tidy tables;
:func:`report_lines` renders its findings for a report.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from workbench.sampling.feedback.effect import EFFECT_RTOL
from workbench.scenarios.methods.spec import MethodSpec, method, names
from workbench.study.report import md_table
from workbench.study.stats import paired_counts, paired_difference_interval
from workbench.validation import fail, integer, real

if TYPE_CHECKING:
    import pandas as pd

    from workbench.sim import Episode

LEVEL = 0.05  # family-wise significance level of the less-safe check (assumptions §12.3)
MIN_STEPS = 20  # fewer steps (of an episode, or of a cell's episodes) are not judged (§12.3)

# never, always, unreported and less_safe are problems; not_checked is a note (why a check
# was not made)
KINDS = ("never", "always", "unreported", "less_safe", "not_checked")
PROBLEMS = KINDS[:4]
TITLES = {"never": "mechanism never acted", "always": "mechanism acted on every step",
          "unreported": "activity not reported", "less_safe": "less safe than {wraps}",
          "not_checked": "not checked"}


class MechanismWarning(UserWarning):
    """A method's safety mechanism never acted, acted on every step, or is not reported."""


@dataclass(frozen=True)
class PairedSafety:
    """``method`` against the method it wraps on the same realisations of one cell: counts
    a (both safe), b (only ``method`` safe), c (only ``wraps`` safe), d (neither); each one's
    safety; the difference ``method`` minus ``wraps`` with Newcombe's 95 % interval; the
    one-sided exact McNemar p-value (:func:`less_safe_p`), its Holm-adjusted value (None when
    b + c = 0: such a pair cannot be significant and is not counted in the correction) and
    whether it is flagged."""

    method: str
    wraps: str
    cell: dict[str, object]
    n: int
    a: int
    b: int
    c: int
    d: int
    safety: float
    safety_wrapped: float
    difference: float
    low: float
    high: float
    p_value: float
    p_holm: float | None = None
    flagged: bool = False


@dataclass(frozen=True)
class Finding:
    """One result of a check: ``kind`` (:data:`KINDS`), the ``method`` (registered name), the
    ``cell`` it holds for ({} for one episode), a short ``title``, the ``figures`` behind it and
    what to do (``advice``); ``text`` is all of it in one sentence. Activity findings name the
    ``activity`` key and count ``episodes`` and ``steps``; a less-safe finding holds its
    ``comparison``."""

    kind: str
    method: str
    label: str
    cell: dict[str, object]
    title: str
    figures: str
    advice: str = ""
    activity: str | None = None
    episodes: int = 0
    steps: int | None = None
    comparison: PairedSafety | None = None

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise fail("Finding.kind", self.kind, f"must be one of {KINDS}")

    @property
    def problem(self) -> bool:
        """A finding to act on (every kind but ``not_checked``)."""
        return self.kind in PROBLEMS

    @property
    def where(self) -> str:
        """The cell as text, e.g. ``variance 100``; "this episode" for an episode."""
        return cell_text(self.cell) or "this episode"

    @property
    def text(self) -> str:
        """The finding in full: method, cell (when any), title, figures and advice."""
        where = f", {self.where}" if self.cell else ""
        out = f"{self.label}{where}: {self.title}: {self.figures}."
        return out + (f" {self.advice}" if self.advice else "")


@dataclass(frozen=True)
class StudyHealth:
    """Every finding of a study (problems and notes, cell by cell in the tables' order), every
    less-safe comparison made (flagged or not), the level and the number of comparisons the
    Holm correction counted."""

    findings: tuple[Finding, ...]
    comparisons: tuple[PairedSafety, ...]
    level: float
    n_tested: int
    cell: tuple[str, ...] = ()
    pair: tuple[str, ...] = ("realisation",)
    checked: dict[str, int] = field(default_factory=dict)  # cells checked per kind of check

    @property
    def problems(self) -> tuple[Finding, ...]:
        return tuple(f for f in self.findings if f.problem)

    @property
    def notes(self) -> tuple[Finding, ...]:
        return tuple(f for f in self.findings if not f.problem)

    def of(self, method_name: str, cell: dict[str, object] | None = None) -> tuple[Finding, ...]:
        """The problems of ``method_name`` (in ``cell`` when given)."""
        return tuple(f for f in self.problems if f.method == method_name
                     and (cell is None or _same_cell(f.cell, cell)))


def cell_text(cell: dict[str, object]) -> str:
    return ", ".join(f"{k} {v:g}" if isinstance(v, float) else f"{k} {v}"
                     for k, v in cell.items())


def _same_cell(a: dict[str, object], b: dict[str, object]) -> bool:
    return a.keys() == b.keys() and all(a[k] == b[k] for k in a)


def _spec(m: str | MethodSpec) -> MethodSpec:
    if isinstance(m, MethodSpec):
        return m
    if not isinstance(m, str):
        raise fail("method", m, f"must be a method name or a MethodSpec; registered: {names()}")
    return method(m)


def _settings_hint(spec: MethodSpec, idle: bool = False) -> str:
    tuned = ", ".join(p.name for p in spec.tunable)
    return ("Check its settings" + (f" ({tuned})" if tuned else "")
            + (" and whether the run ever brought it into play." if idle else "."))


def extreme(values) -> str | None:
    """"never" when every finite value is 0, "always" when every one is 1 (or more), None
    otherwise or with no finite value."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return None
    if np.all(v == 0.0):
        return "never"
    if np.all(v >= 1.0):
        return "always"
    return None


def _activity_finding(spec: MethodSpec, kind: str, cell: dict[str, object], episodes: int,
                      steps: int | None, reported: Sequence[str] = ()) -> Finding:
    key = spec.activity or ""
    of_eps = f" of its {episodes} episodes" if episodes > 1 else ""
    on = f"all {steps} steps{of_eps}" if steps is not None else f"every step{of_eps}"
    if kind == "never":
        figures = f"{key} = 0 on {on}"
        advice = ("It ran as the method without its mechanism would. "
                  + _settings_hint(spec, idle=True))
    elif kind == "always":
        figures = f"{key} = 1 (its largest value) on {on}"
        advice = ("A mechanism that acts on every step no longer responds to the state. "
                  + _settings_hint(spec))
    else:
        figures = (f"the method declares {key!r}, which none of its steps reported "
                   f"(reported: {', '.join(reported) or 'none'})")
        advice = "Report it in the step info's stats.activity under that key."
    return Finding(kind, spec.name, spec.label, dict(cell), TITLES[kind], figures, advice,
                   spec.activity, episodes, steps)


def _note(spec_name: str, label: str, cell: dict[str, object], why: str) -> Finding:
    return Finding("not_checked", spec_name, label, dict(cell), TITLES["not_checked"], why)


def episode_health(method_name: str | MethodSpec, episode: Episode,
                   min_steps: int = MIN_STEPS) -> tuple[Finding, ...]:
    """The activity findings of one closed-loop episode of a method (a registered name or a
    spec): () when its mechanism acted on some steps and not on others, or when it has no
    mechanism of its own; a ``not_checked`` note for an episode of fewer than ``min_steps``
    steps. The episode needs its step infos (``closed_loop(..., keep_infos=True)``)."""
    spec = _spec(method_name)
    min_steps = integer("min_steps", min_steps, 1)
    infos = getattr(episode, "infos", None)
    if infos is None:
        raise fail("episode", type(episode).__name__, "must be an Episode of closed_loop")
    if spec.activity is None:
        return ()
    n = len(infos)
    if n == 0:
        raise fail("episode.infos", "()", "are empty: run closed_loop with keep_infos=True")
    if n < min_steps:
        return (_note(spec.name, spec.label, {},
                      f"{n} steps, fewer than {min_steps}: too few to judge its mechanism"),)
    if not all(getattr(i, "stats", None) is not None for i in infos):
        raise fail("episode.infos", "steps without stats",
                   "every step info must have stats (a StepStats)")
    stats = [i.stats for i in infos]
    values = [s.activity.get(spec.activity, math.nan) for s in stats]
    if not np.any(np.isfinite(np.asarray(values, dtype=float))):
        reported = sorted({k for s in stats for k in s.activity})
        return (_activity_finding(spec, "unreported", {}, 1, n, reported),)
    kind = extreme(values)
    return () if kind is None else (_activity_finding(spec, kind, {}, 1, n),)


@dataclass(frozen=True)
class EpisodeCheck:
    """The ``check_episode`` hook of a registered method's controller: warns
    (:class:`MechanismWarning`) once per problem :func:`episode_health` finds."""

    method: str

    def __call__(self, episode: Episode) -> None:
        for f in episode_health(self.method, episode):
            if f.problem:
                # 3: this call, closed_loop, the caller of closed_loop
                warnings.warn(f.text, MechanismWarning, stacklevel=3)


_EPISODES = ("task_id", "controller", "crashed")
_ACTIVITY = ("task_id", "mechanism", "activity")


def _columns(name: str, table: pd.DataFrame, needed: Sequence[str]) -> None:
    missing = [c for c in needed if c not in getattr(table, "columns", ())]
    if missing:
        have = list(getattr(table, "columns", []))
        raise fail(name, f"columns {have}", f"needs the columns {list(needed)}; missing "
                   f"{missing}")


def _order(controllers) -> list[str]:
    known = names()
    return sorted(controllers, key=lambda c: (known.index(c) if c in known else len(known),
                                              str(c)))


def study_health(episodes: pd.DataFrame, activity: pd.DataFrame, cell: Sequence[str],
                 pair: Sequence[str] = ("realisation",), level: float = LEVEL,
                 min_steps: int = MIN_STEPS) -> StudyHealth:
    """The mechanism checks of a study, cell by cell.

    ``episodes``: one row per episode with ``task_id``, ``controller`` (a registered method),
    ``crashed``, the ``cell`` columns, the ``pair`` columns and optionally ``steps``;
    ``activity``: ``task_id``, ``mechanism`` and ``activity`` (the episode's mean activity of
    that key). In each cell (one value of the ``cell`` columns), per method with a mechanism:
    never acted, acted on every step, or not reported, over all its episodes of the cell (not
    judged under ``min_steps`` steps in all, when ``steps`` is given). Per method that wraps
    another: paired with it on the ``pair`` columns (common random numbers) and flagged when
    the wrapped one is safer (one-sided exact McNemar, Holm over every comparison with a
    discordant pair, family-wise ``level``). A wrapped method that did not run in the cell,
    or no common realisation, is a ``not_checked`` note."""
    cell, pair = tuple(cell), tuple(pair)
    for name, cols in (("cell", cell), ("pair", pair)):
        if isinstance(cols, str) or not all(isinstance(c, str) for c in cols):
            raise fail(name, cols, "must be a sequence of column names")
    if not pair:
        raise fail("pair", pair, "needs at least one column (e.g. 'realisation')")
    level = real("level", level, 0.0, strict=True, maximum=1.0)
    min_steps = integer("min_steps", min_steps, 1)
    _columns("episodes", episodes, (*_EPISODES, *cell, *pair))
    _columns("activity", activity, _ACTIVITY)
    items: list[Finding | PairedSafety] = []  # in report order; comparisons decided below
    checked = {"activity": 0, "paired": 0}
    by_cell = episodes.groupby(list(cell), sort=False) if cell else [((), episodes)]
    for key, rows in by_cell:
        values = key if isinstance(key, tuple) else (key,)
        where = {c: _plain(v) for c, v in zip(cell, values, strict=True)}
        for name in _order(rows["controller"].unique()):
            mine = rows[rows["controller"] == name]
            if name not in names():
                items.append(_note(str(name), str(name), where,
                                   "not a registered method: no mechanism to check"))
                continue
            spec = method(name)
            dup = mine.duplicated(list(pair))
            if dup.any():
                at = {c: _plain(v) for c, v in zip(pair, mine.loc[dup, list(pair)].iloc[0],
                                                   strict=True)}
                raise fail("pair", pair, f"does not identify one episode: {name} has several "
                           f"at {cell_text(where)}, {at}; add the columns that tell them apart")
            if spec.activity is not None:
                found = _cell_activity(spec, where, mine, activity, min_steps)
                checked["activity"] += not (found and found[0].kind == "not_checked")
                items += found
            if spec.wraps is not None:
                item = _paired(spec, where, mine, rows, pair)
                checked["paired"] += isinstance(item, PairedSafety)
                items.append(item)
    tests = [t for t in items if isinstance(t, PairedSafety)]
    comparisons, flagged = _holm(tests, level)
    decided = dict(zip(map(id, tests), flagged, strict=True))
    out = [f for f in (decided[id(t)] if isinstance(t, PairedSafety) else t for t in items)
           if f is not None]
    n_tested = sum(p.p_holm is not None for p in comparisons)
    return StudyHealth(tuple(out), tuple(comparisons), level, n_tested, cell, pair, checked)


def _plain(v):
    return v.item() if isinstance(v, np.generic) else v


def _cell_activity(spec: MethodSpec, where: dict[str, object], mine: pd.DataFrame,
                   activity: pd.DataFrame, min_steps: int) -> list[Finding]:
    n_ep = len(mine)
    steps = int(mine["steps"].sum()) if "steps" in mine else None
    if steps is not None and steps < min_steps:
        return [_note(spec.name, spec.label, where, f"{steps} steps in {n_ep} episodes, fewer "
                      f"than {min_steps}: too few to judge its mechanism")]
    act = activity[activity["task_id"].isin(set(mine["task_id"]))]
    means = act.loc[act["mechanism"] == spec.activity, "activity"].to_numpy(float)
    if not np.any(np.isfinite(means)):
        reported = sorted(str(k) for k in act["mechanism"].unique())
        return [_activity_finding(spec, "unreported", where, n_ep, steps, reported)]
    kind = extreme(means)
    return [] if kind is None else [_activity_finding(spec, kind, where, n_ep, steps)]


def _paired(spec: MethodSpec, where: dict[str, object], mine: pd.DataFrame,
            rows: pd.DataFrame, pair: tuple[str, ...]) -> PairedSafety | Finding:
    wraps = spec.wraps or ""
    label = method(wraps).label if wraps in names() else wraps
    other = rows[rows["controller"] == wraps]
    if not len(other):
        return _note(spec.name, spec.label, where, f"it adds its mechanism to {label}, "
                     "which did not run here: not compared")
    m = mine[[*pair, "crashed"]].merge(other[[*pair, "crashed"]].drop_duplicates(list(pair)),
                                       on=list(pair), suffixes=("_1", "_2"))
    if not len(m):
        return _note(spec.name, spec.label, where, f"no realisation in common with {label}: "
                     "not compared")
    a, b, c, d = paired_counts(~m["crashed_1"].to_numpy(bool), ~m["crashed_2"].to_numpy(bool))
    n = a + b + c + d
    diff, low, high = paired_difference_interval(a, b, c, d)
    return PairedSafety(spec.name, wraps, dict(where), n, a, b, c, d, (a + b) / n, (a + c) / n,
                        diff, low, high, less_safe_p(b, c))


def less_safe_p(b: int, c: int) -> float:
    """One-sided exact McNemar p-value that the wrapping method is less safe: P(X >= c) for
    X ~ Binomial(b + c, 1/2), with b the realisations where only the wrapping method was
    safe and c those where only the wrapped one was (1 without discordant pairs)."""
    if b + c == 0:
        return 1.0
    from scipy.stats import binomtest

    return float(binomtest(c, b + c, 0.5, alternative="greater").pvalue)


def holm_flags(tests: Sequence[tuple[int, int]], level: float = LEVEL
               ) -> list[tuple[float, float | None, bool]]:
    """For each comparison's discordant counts (b: only the wrapping method safe, c: only the
    wrapped one): the one-sided p-value (:func:`less_safe_p`), its Holm-adjusted value over
    the comparisons with b + c > 0 (None for the others) and whether it is flagged (adjusted
    p <= ``level`` and c > b: the wrapped method is the safer one)."""
    p = [less_safe_p(b, c) for b, c in tests]
    idx = [i for i, (b, c) in enumerate(tests) if b + c > 0]
    adj: list[float | None] = [None] * len(tests)
    if idx:
        from statsmodels.stats.multitest import multipletests

        for i, v in zip(idx, multipletests([p[i] for i in idx], alpha=level,
                                           method="holm")[1], strict=True):
            adj[i] = float(v)
    return [(p[i], a, a is not None and a <= level and c > b)
            for i, ((b, c), a) in enumerate(zip(tests, adj, strict=True))]


def _holm(tests: list[PairedSafety], level: float
          ) -> tuple[list[PairedSafety], list[Finding | None]]:
    marks = holm_flags([(t.b, t.c) for t in tests], level)
    out, found = [], []
    for t, (_, adj, flag) in zip(tests, marks, strict=True):
        t = PairedSafety(**{**t.__dict__, "p_holm": adj, "flagged": flag})
        out.append(t)
        found.append(_less_safe(t, level) if flag else None)
    return out, found


def _less_safe(t: PairedSafety, level: float) -> Finding:
    spec = method(t.method)
    wl = method(t.wraps).label
    figures = (f"safe in {100 * t.safety:.0f} % of {t.n} paired realisations, {wl} in "
               f"{100 * t.safety_wrapped:.0f} %; only it safe in {t.b}, only {wl} in {t.c}; "
               f"difference {100 * t.difference:+.0f} points, 95 % interval "
               f"[{100 * t.low:+.0f}, {100 * t.high:+.0f}]; one-sided exact McNemar p = "
               f"{t.p_value:.2g}, "
               f"Holm-adjusted {t.p_holm:.2g} <= {level:g}")
    advice = (f"Its mechanism made {wl}, the method it adds it to, less safe on the same "
              "disturbances. " + _settings_hint(spec))
    return Finding("less_safe", t.method, spec.label, dict(t.cell),
                   TITLES["less_safe"].format(wraps=wl), figures, advice,
                   comparison=t)


def report_lines(h: StudyHealth) -> list[str]:
    """The "Mechanism health" section of a report (markdown lines, heading included): what is
    checked, a table of the problems with their figures (or a line saying there are none),
    what was checked, and the notes (checks not made, and why)."""
    cells = " x ".join(h.cell) or "the whole run"
    kinds = [f.kind for f in h.problems]
    flagged = sum(t.flagged for t in h.comparisons)
    lines = [
        "## Mechanism health", "",
        f"Each method with a safety mechanism is checked in each cell ({cells}), over all its "
        "episodes there: whether the mechanism never acted (activity 0 on every step) or acted "
        "on every step (activity 1 on every step: a flag raised on every step, or a share at "
        "its largest). Activity counts effects: a step counts only when the mechanism changed "
        "the applied control, or the samples' controls, costs or gains behind it, by more "
        f"than {EFFECT_RTOL:g} relative. A cell of fewer than {MIN_STEPS} steps in all is not "
        "judged. Each "
        "method that adds its mechanism to another is paired with that method on the same "
        f"disturbances ({' and '.join(h.pair)}) and flagged as less safe when the other is the "
        "safer one and a one-sided exact McNemar test rejects equal safety at level "
        f"{h.level:g} after Holm's correction over the comparisons of this report that have a "
        "discordant pair (one crashed, the other did not).", ""]
    if h.problems:
        rows = [[f.label, f.where, f.title, f.figures] for f in h.problems]
        lines += md_table(["method", "cell", "finding", "figures"], rows)
    else:
        lines.append("No problem found in this run.")
    lines += [
        "",
        f"- Activity: {_count(h.checked.get('activity', 0), '(method, cell) check')}; never "
        f"acted in {kinds.count('never')}, acted on every step in {kinds.count('always')}, "
        f"not reported in {kinds.count('unreported')}.",
        f"- Safety against the wrapped method: {_count(len(h.comparisons), 'comparison')}, "
        f"{h.n_tested} with a discordant pair (the Holm family), {flagged} flagged."]
    if h.notes:
        lines += ["", "Not checked:", ""]
        lines += [f"- {f.label}, {f.where}: {f.figures}." for f in h.notes]
    return [*lines, ""]


def _count(n: int, what: str) -> str:
    return f"{n} {what}{'s' * (n != 1)}"


def headline(h: StudyHealth, most: int = 5) -> str:
    """One line for the top of a report: the number of problems and the first ``most`` of
    them, or that there is none."""
    found = h.problems
    if not found:
        return "Mechanism health: no problem found (see the section Mechanism health)."
    shown = "; ".join(f"{f.label}, {f.where}: {f.title}" for f in found[:most])
    more = f"; and {len(found) - most} more" if len(found) > most else ""
    return (f"**Mechanism health: {_count(len(found), 'problem')} found**: "
            f"{shown}{more} (figures in the section Mechanism health).")


def console_lines(h: StudyHealth) -> tuple[str, ...]:
    """One console line per problem, or one saying there is none."""
    if not h.problems:
        return ("mechanism health: no problem found",)
    return tuple(f"mechanism health: {f.label}, {f.where}: {f.title}" for f in h.problems)

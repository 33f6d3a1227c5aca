"""Mechanism health: every branch of the episode and study checks on tables whose truth is
known, the less-safe statistics against an independent computation and, by simulation, at most
the nominal false-flag rate when the two methods are equally safe; one real closed loop."""

from __future__ import annotations

import functools
import warnings
from dataclasses import dataclass

import numpy as np
import pandas as pd
import pytest
from scipy.stats import binom
from statsmodels.stats.contingency_tables import mcnemar
from statsmodels.stats.multitest import multipletests

import workbench as wb
from workbench.sampling.step_stats import StepStats
from workbench.scenarios.mechanism_health import (
    LEVEL,
    MIN_STEPS,
    EpisodeCheck,
    MechanismWarning,
    console_lines,
    episode_health,
    extreme,
    headline,
    holm_flags,
    report_lines,
    study_health,
)
from workbench.scenarios.methods import method
from workbench.study.stats import paired_counts, paired_difference_interval

STEPS = 50  # steps per synthetic episode


def tables(cells: dict, steps: int = STEPS, cell: str = "variance"):
    """Tidy ``episodes`` and ``activity`` tables from {cell value: {controller: [(crashed,
    mean activity or None), ...]}}, realisation j being the j-th entry of each list; the
    activity row uses the controller's registered key (none for None or a method without)."""
    ep, act, tid = [], [], 0
    for value, ctrls in cells.items():
        for c, runs in ctrls.items():
            key = method(c).activity
            for j, (crashed, a) in enumerate(runs):
                ep.append({"task_id": tid, "controller": c, cell: value, "realisation": j,
                           "crashed": crashed, "steps": steps})
                if key is not None and a is not None:
                    act.append({"task_id": tid, "mechanism": key, "activity": a})
                tid += 1
    return pd.DataFrame(ep), pd.DataFrame(act, columns=["task_id", "mechanism", "activity"])


def runs(crashed, activity=0.5):
    """Episodes with these crash flags, each with the same mean activity."""
    return [(bool(c), activity) for c in crashed]


SAFE10 = [False] * 10


def kinds(h, **where) -> list[tuple[str, str]]:
    return [(f.method, f.kind) for f in h.findings
            if all(f.cell.get(k) == v for k, v in where.items())]


# --- activity: never, always, shares, unreported, too few steps -------------------------------

def test_never_and_always_over_a_cell():
    h = study_health(*tables({10.0: {
        "sais_al": runs(SAFE10, 0.0),  # AL gains never active: the users' case
        "tube_mppi": runs(SAFE10, 1.0),  # a tube that never falls back to MPPI's control
        "bas_mppi": runs(SAFE10, None), "mppi_crash": runs(SAFE10, None)}}),
        cell=("variance",))
    assert kinds(h) == [("tube_mppi", "always"), ("sais_al", "never")]
    never = next(f for f in h.findings if f.kind == "never")
    assert never.activity == "al_active" and never.episodes == 10 and never.steps == 10 * STEPS
    assert never.cell == {"variance": 10.0} and never.problem
    assert "al_active = 0 on all 500 steps of its 10 episodes" in never.figures
    always = next(f for f in h.findings if f.kind == "always")
    assert "nominal_tracked = 1" in always.figures and "tube.threshold" in always.advice
    assert h.checked == {"activity": 2, "paired": 2}


@pytest.mark.parametrize("means", [
    [0.3] * 10,  # a share positive on every step but below 1: at work, not a finding
    [0.0] * 9 + [0.01],  # acted in one episode
    [1.0] * 9 + [0.99],  # not saturated in one episode
    [0.0] * 5 + [1.0] * 5,  # never in some episodes, always in others: it responds
])
def test_a_mechanism_at_work_is_no_finding(means):
    h = study_health(*tables({10.0: {"cbf_projection": [(False, m) for m in means],
                                     "mppi_crash": runs(SAFE10, None)}}), cell=("variance",))
    assert h.problems == ()


def test_an_activity_no_episode_reported_is_a_finding():
    ep, act = tables({10.0: {"gatekeeper": runs(SAFE10, None), "mppi_crash": runs(SAFE10)}})
    other = pd.DataFrame({"task_id": ep["task_id"][:10], "mechanism": "something_else",
                          "activity": 0.5})
    h = study_health(ep, pd.concat([act, other]), cell=("variance",))
    (f,) = h.problems
    assert (f.method, f.kind) == ("gatekeeper", "unreported")
    assert "'backup_used'" in f.figures and "something_else" in f.figures


def test_too_few_steps_are_not_judged():
    h = study_health(*tables({10.0: {"sais_al": runs([False, False], 0.0),
                                     "bas_mppi": runs([False, False])}}, steps=MIN_STEPS // 2 - 1),
                     cell=("variance",))
    assert h.problems == () and [f.kind for f in h.notes] == ["not_checked"]
    assert "fewer than 20" in h.notes[0].figures


# --- less safe than the wrapped method --------------------------------------------------------

def pairs(b: int, c: int, a: int = 0, d: int = 0):
    """Crash flags of (method, wrapped) with a both safe, b only the method safe, c only the
    wrapped one, d neither."""
    first = [False] * a + [False] * b + [True] * c + [True] * d
    second = [False] * a + [True] * b + [False] * c + [True] * d
    return first, second


def test_less_safe_significant_with_its_figures():
    first, second = pairs(b=1, c=12, a=15, d=2)  # the gatekeeper crashes where MPPI does not
    h = study_health(*tables({50.0: {"gatekeeper": runs(first), "mppi_crash": runs(second)}}),
                     cell=("variance",))
    (f,) = h.problems
    assert (f.method, f.kind, f.title) == ("gatekeeper", "less_safe",
                                           "less safe than MPPI (crash cost)")
    t = f.comparison
    assert t is not None and t.flagged and (t.a, t.b, t.c, t.d, t.n) == (15, 1, 12, 2, 30)
    # independent: half statsmodels' two-sided exact McNemar on the 2x2 table (c > b: the
    # symmetric binomial's two tails are equal), Newcombe's interval
    table = [[15, 1], [12, 2]]  # rows: method safe / crashed; columns: wrapped safe / crashed
    assert t.p_value == pytest.approx(mcnemar(table, exact=True).pvalue / 2, rel=1e-12)
    assert (t.difference, t.low, t.high) == paired_difference_interval(15, 1, 12, 2)
    assert t.difference == pytest.approx((1 - 12) / 30)
    assert t.safety == pytest.approx(16 / 30) and t.safety_wrapped == pytest.approx(27 / 30)
    assert t.p_holm == t.p_value  # one comparison with discordant pairs: Holm leaves it
    assert h.n_tested == 1
    for figure in ("-37 points", f"p = {t.p_value:.2g}", "only MPPI (crash cost) in 12"):
        assert figure in f.figures


def test_less_safe_not_significant_is_recorded_not_flagged():
    first, second = pairs(b=1, c=4, a=20)
    h = study_health(*tables({50.0: {"gatekeeper": runs(first), "mppi_crash": runs(second)}}),
                     cell=("variance",))
    assert h.problems == ()
    (t,) = h.comparisons
    assert not t.flagged and t.c > t.b and t.p_holm == pytest.approx(0.1875)  # 6 / 32


def test_safer_than_the_wrapped_method_is_not_flagged():
    first, second = pairs(b=15, c=0, a=10)
    h = study_health(*tables({50.0: {"shield_mppi": runs(first), "mppi_crash": runs(second)}}),
                     cell=("variance",))
    (t,) = h.comparisons
    assert t.p_value == 1.0 and not t.flagged and h.problems == ()  # P(X >= 0)


def test_wrapped_method_missing_is_said_and_not_compared():
    h = study_health(*tables({50.0: {"sa_rmppi": runs(SAFE10)}}), cell=("variance",))
    assert h.comparisons == () and h.problems == ()
    (note,) = h.notes
    assert note.kind == "not_checked" and not note.problem
    assert "BaS-MPPI, which did not run here" in note.figures


def test_no_common_realisation_is_said():
    ep, act = tables({50.0: {"sa_rmppi": runs(SAFE10), "bas_mppi": runs(SAFE10)}})
    ep.loc[ep["controller"] == "bas_mppi", "realisation"] += 100
    h = study_health(ep, act, cell=("variance",))
    assert h.comparisons == () and "no realisation in common" in h.notes[0].figures


def test_baselines_have_nothing_to_check():
    h = study_health(*tables({0.0: {"bas_mppi": runs(SAFE10), "mppi_crash": runs(SAFE10)}}),
                     cell=("variance",))
    assert h.findings == () and h.comparisons == () and h.checked == {"activity": 0, "paired": 0}
    assert "No problem found" in "\n".join(report_lines(h))


def test_a_method_without_activity_is_only_compared():
    first, second = pairs(b=0, c=10, a=10)
    h = study_health(*tables({10.0: {"rmppi": runs(first, None), "bas_mppi": runs(second)}}),
                     cell=("variance",))
    assert kinds(h) == [("rmppi", "less_safe")] and h.checked == {"activity": 0, "paired": 1}


def test_multiple_cells_holm_over_every_comparison():
    rng = np.random.default_rng(3)
    cells = {}
    for v, (b, c) in zip((10.0, 50.0, 100.0), ((0, 0), (3, 9), (1, 14)), strict=True):
        first, second = pairs(b=b, c=c, a=30 - b - c)
        cells[v] = {"tube_mppi": runs(first, float(rng.uniform(0.1, 0.9))),
                    "mppi_crash": runs(second),
                    "sais_al": runs(SAFE10 * 3, 0.0 if v == 100.0 else 0.2),
                    "bas_mppi": runs(SAFE10 * 3)}
    h = study_health(*tables(cells), cell=("variance",))
    tube = [t for t in h.comparisons if t.method == "tube_mppi"]
    assert [t.p_holm is None for t in tube] == [True, False, False]  # no discordant pair
    tested = [t for t in h.comparisons if t.p_holm is not None]
    assert h.n_tested == len(tested) == 2  # sais_al vs bas_mppi: never discordant
    expect = multipletests([t.p_value for t in tested], method="holm")[1]
    assert [t.p_holm for t in tested] == pytest.approx(list(expect))
    assert kinds(h, variance=50.0) == []  # p = 299 / 4096 = 0.073, Holm 0.073: not flagged
    assert kinds(h, variance=100.0) == [("tube_mppi", "less_safe"), ("sais_al", "never")]
    assert [f.where for f in h.problems] == ["variance 100", "variance 100"]
    assert h.of("sais_al", {"variance": 100.0})[0].kind == "never"
    assert h.of("sais_al", {"variance": 10.0}) == ()


def test_arena_cells_pair_on_map_and_realisation():
    rows, act = [], []
    first, second = pairs(b=0, c=6, a=2)
    for k, (c, crashes) in enumerate((("gatekeeper", first), ("mppi_crash", second))):
        for j, crashed in enumerate(crashes):
            tid = 100 * k + j
            rows.append({"task_id": tid, "controller": c, "system": "unicycle",
                         "disturbance": "kick(1)", "tuning": "hand", "map": f"spec-{j % 2}",
                         "realisation": j // 2, "crashed": crashed, "steps": 30})
            if c == "gatekeeper":
                act.append({"task_id": tid, "mechanism": "backup_used", "activity": 0.0})
    ep, ac = pd.DataFrame(rows), pd.DataFrame(act)
    h = study_health(ep, ac, cell=("system", "disturbance", "tuning"),
                     pair=("map", "realisation"))
    assert kinds(h) == [("gatekeeper", "never"), ("gatekeeper", "less_safe")]
    (t,) = h.comparisons  # one cell over both maps: 8 pairs, all 6 discordant ones MPPI's
    assert (t.n, t.b, t.c) == (8, 0, 6) and t.p_value == pytest.approx(1 / 64) and t.flagged
    assert h.findings[0].where == "system unicycle, disturbance kick(1), tuning hand"
    with pytest.raises(ValueError, match=r"^pair"):  # realisation alone: two maps collide
        study_health(ep, ac, cell=("system", "disturbance", "tuning"))


def test_unregistered_controller_and_bad_tables_name_the_field():
    ep, act = tables({10.0: {"bas_mppi": runs(SAFE10)}})
    ep.loc[:4, "controller"] = "my_own"
    h = study_health(ep, act, cell=("variance",))
    assert [(f.method, f.kind) for f in h.notes] == [("my_own", "not_checked")]
    with pytest.raises(ValueError, match=r"^episodes.*'crashed'"):
        study_health(ep.drop(columns="crashed"), act, cell=("variance",))
    with pytest.raises(ValueError, match=r"^activity"):
        study_health(ep, act.drop(columns="mechanism"), cell=("variance",))
    with pytest.raises(ValueError, match=r"^level"):
        study_health(ep, act, cell=("variance",), level=0.0)
    with pytest.raises(ValueError, match=r"^pair"):
        study_health(ep, act, cell=("variance",), pair=())


# --- the statistics ---------------------------------------------------------------------------

@pytest.fixture
def fast_holm(monkeypatch):
    """For the tests that call the statistics thousands of times: statsmodels' Holm correction
    runs gc.collect() on every call (about 0.3 s in a process holding compiled kernels),
    skipped here, and the one-sided p-value (a pure function of b and c) is memoised."""
    import gc

    import workbench.scenarios.mechanism_health as health

    monkeypatch.setattr(gc, "collect", lambda generation=2: 0)
    monkeypatch.setattr(health, "less_safe_p", functools.lru_cache(health.less_safe_p))


@pytest.mark.usefixtures("fast_holm")
def test_holm_flags_match_an_independent_computation():
    rng = np.random.default_rng(11)
    for _ in range(50):
        tests = [tuple(int(x) for x in rng.integers(0, 12, 2)) for _ in range(rng.integers(1, 6))]
        got = holm_flags(tests)
        for (b, c), (p, _, _) in zip(tests, got, strict=True):
            # P(X >= c), X ~ Binomial(b + c, 1/2), from the survival function
            want = 1.0 if b + c == 0 else float(binom.sf(c - 1, b + c, 0.5))
            assert p == pytest.approx(want, rel=1e-9, abs=1e-15)
        live = [i for i, (b, c) in enumerate(tests) if b + c > 0]
        # Holm by hand: step down over the sorted p-values, running maximum, capped at 1
        ps = [got[i][0] for i in live]
        order = np.argsort(ps, kind="stable")
        adj, run = np.empty(len(ps)), 0.0
        for rank, i in enumerate(order):
            run = max(run, min(1.0, (len(ps) - rank) * ps[i]))
            adj[i] = run
        for k, i in enumerate(live):
            assert got[i][1] == pytest.approx(adj[k])
            b, c = tests[i]
            assert got[i][2] == (adj[k] <= LEVEL and c > b)
        assert all(got[i][1] is None and not got[i][2] for i in set(range(len(tests))) - set(live))


@pytest.mark.usefixtures("fast_holm")
def test_false_flags_under_equal_safety_stay_below_the_level():
    """Three comparisons per report, 30 paired realisations each, both methods safe with
    probability 0.8 and correlated through a shared disturbance: the share of reports with
    any flag is at most the level, and a single comparison's false flags at most the level."""
    rng = np.random.default_rng(2024)
    reps, flagged_reports, flagged_single = 3000, 0, 0
    for _ in range(reps):
        tests = []
        for _ in range(3):
            hard = rng.random(30) < 0.5  # the realisation's disturbance is a hard one
            p = np.where(hard, 0.65, 0.95)
            first, second = rng.random(30) < p, rng.random(30) < p  # safe flags
            _, b, c, _ = paired_counts(first, second)
            tests.append((b, c))
        flags = holm_flags(tests)
        flagged_reports += any(f for _, _, f in flags)
        flagged_single += holm_flags(tests[:1])[0][2]
    assert flagged_reports / reps <= LEVEL
    assert flagged_single / reps <= LEVEL + 3 * np.sqrt(LEVEL * (1 - LEVEL) / reps)


@pytest.mark.usefixtures("fast_holm")
def test_a_real_difference_is_found():
    rng = np.random.default_rng(7)
    hits = 0
    for _ in range(200):
        first, second = rng.random(60) < 0.5, rng.random(60) < 0.9  # safe flags
        _, b, c, _ = paired_counts(first, second)
        hits += holm_flags([(b, c)])[0][2]
    assert hits / 200 > 0.9


def test_extreme():
    assert extreme([0, 0.0, np.nan]) == "never" and extreme([1, 1.0]) == "always"
    assert extreme([0, 1]) is None and extreme([np.nan]) is None and extreme([]) is None


# --- one episode ------------------------------------------------------------------------------

@dataclass(frozen=True)
class Info:
    stats: StepStats


def episode(values, key="backup_used") -> wb.Episode:
    n = len(values)
    infos = tuple(Info(StepStats(10, 10, 5.0, {} if v is None else {key: v})) for v in values)
    return wb.Episode(X=np.zeros((n + 1, 4)), U=np.zeros((n, 2)), crashed=False, crash_step=None,
                      min_margin=1.0, step_time_s=np.zeros(n), infos=infos)


def test_episode_health_branches():
    n = MIN_STEPS
    (f,) = episode_health("gatekeeper", episode([0.0] * n))
    assert (f.kind, f.steps, f.episodes, f.cell) == ("never", n, 1, {})
    assert f.text.startswith("Gatekeeper (braking backup): mechanism never acted: "
                             f"backup_used = 0 on all {n} steps.")
    (f,) = episode_health(method("gatekeeper"), episode([1.0] * n))
    assert f.kind == "always"
    assert episode_health("gatekeeper", episode([0.0] * (n - 1) + [1.0])) == ()
    assert episode_health("cbf_projection", episode([0.4] * n, "projected")) == ()
    (f,) = episode_health("gatekeeper", episode([None] * n))
    assert f.kind == "unreported"
    (f,) = episode_health("gatekeeper", episode([0.0] * (n - 1)))
    assert f.kind == "not_checked" and not f.problem
    assert episode_health("bas_mppi", episode([0.0] * n)) == ()  # no mechanism of its own
    with pytest.raises(ValueError, match=r"^episode\.infos"):
        episode_health("gatekeeper", episode([]))
    with pytest.raises(ValueError, match=r"^min_steps"):
        episode_health("gatekeeper", episode([0.0] * n), min_steps=0)


def test_the_hook_warns_only_on_a_problem():
    with pytest.warns(MechanismWarning, match="never acted"):
        EpisodeCheck("gatekeeper")(episode([0.0] * MIN_STEPS))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        EpisodeCheck("gatekeeper")(episode([0.0] * (MIN_STEPS - 1)))  # a note: no warning
        EpisodeCheck("gatekeeper")(episode([0.0, 1.0] * MIN_STEPS))


def test_closed_loop_warns_about_a_tube_that_resets_on_every_step():
    """Tube-MPPI with its default threshold resets its nominal on every undisturbed step, so
    the plant gets MPPI's control on every step: its mechanism never acted (it counted as
    acting on every step while resets were counted), and closed_loop says so, pointing at the
    caller's line; check_episode=False is silent."""
    nav = wb.navigation_setup(mppi=wb.MPPIConfig(n_samples=64, horizon=30, sigma=(5.0, 5.0),
                                                 lam=10.0))
    ctrl = nav.controller("tube_mppi")

    def run(**kw):
        return wb.closed_loop(ctrl, nav.plant, nav.x0, MIN_STEPS + 5, np.random.default_rng(0),
                              np.random.default_rng(1), **kw)

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ep = run()
    ours = [w for w in caught if issubclass(w.category, MechanismWarning)]
    assert len(ours) == 1 and ours[0].filename == __file__
    assert "Tube-MPPI: mechanism never acted: nominal_tracked = 0" in str(ours[0].message)
    assert [f.kind for f in episode_health("tube_mppi", ep)] == ["never"]
    assert all(i.stats.activity["nominal_reset"] == 1.0 for i in ep.infos)
    with warnings.catch_warnings():
        warnings.simplefilter("error", MechanismWarning)
        run(check_episode=False)
        run(keep_infos=False)


# --- what a report shows ----------------------------------------------------------------------

def test_report_lines_headline_and_console():
    first, second = pairs(b=0, c=12, a=18)
    h = study_health(*tables({50.0: {"gatekeeper": runs(first, 0.0), "mppi_crash": runs(second),
                                     "sa_rmppi": runs(first)}}), cell=("variance",))
    text = "\n".join(report_lines(h))
    assert text.startswith("## Mechanism health")
    assert "| Gatekeeper (braking backup) | variance 50 | mechanism never acted |" in text
    assert ("| Gatekeeper (braking backup) | variance 50 | less safe than MPPI (crash cost) |"
            in text)
    assert "Not checked:" in text and "BaS-MPPI, which did not run here" in text
    assert "No problem found" not in text and "Holm" in text and "0.05" in text
    assert headline(h).startswith("**Mechanism health: 2 problems found**")
    assert console_lines(h) == (
        "mechanism health: Gatekeeper (braking backup), variance 50: mechanism never acted",
        "mechanism health: Gatekeeper (braking backup), variance 50: less safe than MPPI "
        "(crash cost)")
    assert "- Safety against the wrapped method: 1 comparison, 1 with a discordant pair" in text
    assert "never acted in 1, acted on every step in 0" in text
    clean = study_health(*tables({50.0: {"bas_mppi": runs(SAFE10)}}), cell=("variance",))
    assert "No problem found" in "\n".join(report_lines(clean))
    assert headline(clean).startswith("Mechanism health: no problem found")
    assert console_lines(clean) == ("mechanism health: no problem found",)

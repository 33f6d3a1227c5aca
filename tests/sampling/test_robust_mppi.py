"""Robust MPPI's machinery: strides, nominal-state selection, fallback, the nominal update, the
applied control, K_safe that never vanishes, alpha rules, and bad input (issue: SA-RMPPI)."""

from __future__ import annotations

from dataclasses import replace

import casadi as ca
import numpy as np
import pytest

from workbench.ilqg.passes import BackwardResult
from workbench.sampling.feedback import FeedbackWeights, Gains, ILQGFeedback, shifted
from workbench.sampling.kernels.constants import SamplerConstants
from workbench.sampling.mppi import MPPI
from workbench.sampling.robust import (
    RMPPIConfig,
    RMPPIState,
    RobustMPPI,
    candidate_weights,
    strides,
)
from workbench.sampling.sampler import Sampler
from workbench.sampling.threshold import (
    AlphaRule,
    ConstantThreshold,
    ProgressThreshold,
    make_threshold,
    progress_curve,
)
from workbench.scenarios.navigation import navigation_setup
from workbench.sim import Disturbance, closed_loop


@pytest.fixture(scope="module")
def nav():
    return navigation_setup()


class Preset:
    """A threshold that returns given values at the candidates (and ``single`` elsewhere)."""

    def __init__(self, values, single=np.inf):
        self.values, self.single = np.asarray(values, float), single

    def __call__(self, X):
        X = np.atleast_2d(X)
        return self.values.copy() if len(X) == len(self.values) else np.full(len(X), self.single)


def test_strides_round_half_away_from_zero():
    np.testing.assert_array_equal(strides(3), [0, 1, 1])
    np.testing.assert_array_equal(strides(5), [0, 1, 1, 1, 1])  # 0.5 -> 1 (Python's round: 0)
    np.testing.assert_array_equal(strides(9), [0, 0, 1, 1, 1, 1, 1, 1, 1])
    W = candidate_weights(9)
    np.testing.assert_allclose(W.sum(axis=1), 1.0)
    np.testing.assert_array_equal(W[0], [1, 0, 0])
    np.testing.assert_array_equal(W[4], [0, 1, 0])
    np.testing.assert_array_equal(W[8], [0, 0, 1])


def _disturbed_state(nav, ctrl, steps=15, level=50.0):
    """A controller state after a few disturbed steps (nominal and real differ)."""
    rng_c, rng_w = np.random.default_rng(3), np.random.default_rng(4)
    state, x = ctrl.initial_state(), nav.x0.copy()
    dyn = ca.Function("plant", [nav.plant.x, nav.plant.u], [nav.plant.x_next])
    for _ in range(steps):
        state, u, _ = ctrl.step(state, x, rng_c)
        x = np.asarray(dyn(x, u)).ravel() + Disturbance(level, velocity_index=(2, 3)).sample(
            4, nav.plant.dt, rng_w)
    return state, x


@pytest.fixture(scope="module")
def sa_state(nav):
    ctrl = RobustMPPI(nav.problem, nav.goal, nav.mppi, threshold=ConstantThreshold(-np.inf))
    state, x = _disturbed_state(nav, ctrl)  # alpha = -inf: always the propagated nominal
    return state, nav.problem.model.lift(x)


@pytest.mark.parametrize("j", range(9))
def test_each_candidate_is_chosen_in_turn(nav, sa_state, j):
    state, xb = sa_state
    assert not np.allclose(state.x_nom, xb)
    alpha = np.where(np.arange(9) <= j, np.inf, -np.inf)
    ctrl = RobustMPPI(nav.problem, nav.goal, nav.mppi, threshold=Preset(alpha))
    sel = ctrl.select_nominal(state, xb, np.random.default_rng(0))
    assert sel.index == j and not sel.fallback and sel.stride == strides(9)[j]
    # the nominal update: x*_0 = the j-th candidate, u* slid by its stride
    a1 = np.asarray(nav.problem.functions()["dyn"](state.x_nom, state.U[0],
                                                    nav.problem.model.scene_value)).ravel()
    W = candidate_weights(9)[j]
    expect = nav.problem.model.lift((W @ np.stack([state.x_nom, a1, xb]))[:4])
    np.testing.assert_allclose(sel.x_nom, xb if j == 8 else expect, rtol=1e-12, atol=1e-12)
    s = sel.stride
    np.testing.assert_array_equal(sel.U[: 100 - s], state.U[s:])
    assert sel.free_energy.shape == (9,) and np.all(np.isfinite(sel.free_energy))


def test_selection_is_the_last_candidate_below_alpha(nav, sa_state):
    state, xb = sa_state
    ctrl = RobustMPPI(nav.problem, nav.goal, nav.mppi, threshold=ConstantThreshold(np.inf))
    F = ctrl.select_nominal(state, xb, np.random.default_rng(1)).free_energy
    for a in np.sort(F)[1:]:
        c = RobustMPPI(nav.problem, nav.goal, nav.mppi, threshold=ConstantThreshold(a))
        sel = c.select_nominal(state, xb, np.random.default_rng(1))
        np.testing.assert_array_equal(sel.free_energy, F)  # same seed, same estimates
        assert sel.index == int(np.flatnonzero(F < a).max())


@pytest.mark.parametrize("mode", ["propagated", "keep_previous"])
def test_fallback_when_no_candidate_qualifies(nav, sa_state, mode):
    state, xb = sa_state
    state = replace(state, index=2)
    ctrl = RobustMPPI(nav.problem, nav.goal, nav.mppi, RMPPIConfig(fallback=mode),
                      threshold=ConstantThreshold(-np.inf))
    sel = ctrl.select_nominal(state, xb, np.random.default_rng(0))
    assert sel.fallback and sel.index == (4 if mode == "propagated" else 2)


def test_first_call_takes_the_real_state(nav):
    ctrl = RobustMPPI(nav.problem, nav.goal, nav.mppi,
                      threshold=ConstantThreshold.selection_off())
    xb = nav.problem.model.lift(nav.x0)
    sel = ctrl.select_nominal(ctrl.initial_state(), xb, np.random.default_rng(0))
    assert sel.index == 8 and sel.stride == 0 and sel.free_energy.size == 0
    np.testing.assert_array_equal(sel.x_nom, xb)


def test_applied_control_is_nominal_plus_feedback(nav, sa_state):
    state, xb = sa_state
    ctrl = RobustMPPI(nav.problem, nav.goal, nav.mppi, threshold=Preset([np.inf] + [-np.inf] * 8))
    new, u, info = ctrl.step(state, xb, np.random.default_rng(5))
    assert info.candidate == 0 and info.nominal_differs
    K0 = new.gains.K[0]
    fb = K0 @ (xb - info.x_nom)
    assert np.linalg.norm(fb) > 1e-2  # the feedback term acts
    m = nav.problem.model
    np.testing.assert_allclose(u, np.clip(new.U[0] + fb, m.u_min, m.u_max), rtol=1e-12)
    # K_safe carries nonzero gains on the physical state
    assert np.abs(new.gains.K[:, :, :4]).max() > 1.0 and info.ksafe_fallback is None


def test_k_safe_on_a_nominal_rollout_that_leaves_the_safe_set(nav):
    fb = nav.feedback("bas_ilqg")
    obst = nav.scene.obstacles()[0]
    c, r = np.asarray(obst.center), obst.radius
    x0 = nav.problem.model.lift(np.array([c[0] - r - 0.3, c[1], 3.0, 0.0]))
    U = np.tile([5.0, 0.0], (100, 1))  # full throttle into the obstacle
    X, _ = fb.nominal(x0, U)
    assert np.min([nav.plant.margins(x[:4]).min() for x in X]) <= 0
    g = fb.gains(x0, U, None, 0)
    assert g.fallback is None and g.nominal_unsafe
    assert np.all(np.isfinite(g.K)) and np.abs(g.K).max() > 1.0


def test_k_safe_fallbacks_shift_the_previous_gains_and_say_why(nav, monkeypatch):
    fb = nav.feedback("bas_ilqg")
    x0 = nav.problem.model.lift(nav.x0)
    U = np.zeros((100, 2))
    prev = Gains(K=np.random.default_rng(0).standard_normal((100, 2, 5)))
    monkeypatch.setattr(fb.passes, "backward",
                        lambda *a: BackwardResult(status=1, k=None, K=None, dV=None))
    g = fb.gains(x0, U, prev, 1)
    assert g.fallback == "backward_failed"
    np.testing.assert_array_equal(g.K, shifted(prev.K, 1))
    np.testing.assert_array_equal(g.K[:-1], prev.K[1:])
    monkeypatch.undo()
    d = fb.passes.derivatives

    def poisoned(*a):
        out = dict(d(*a))
        out["A"] = out["A"] * np.nan
        return out

    monkeypatch.setattr(fb.passes, "derivatives", poisoned)
    assert fb.gains(x0, U, prev, 0).fallback == "nonfinite_derivatives"
    g0 = fb.gains(x0, U, None, 0)  # no previous gains: zeros, and the reason is reported
    assert g0.fallback == "nonfinite_derivatives" and not np.any(g0.K)


def test_plain_ilqg_feedback_has_no_gain_on_beta(nav):
    fb = nav.feedback("ilqg")
    g = fb.gains(nav.problem.model.lift(nav.x0), np.zeros((100, 2)), None, 0)
    assert g.K.shape == (100, 2, 5) and not np.any(g.K[:, :, 4])
    assert np.abs(g.K[:, :, :4]).max() > 1.0


def test_controllers_differ_on_the_paper_map_with_common_noise(nav):
    X = {}
    rule = AlphaRule(calibration_steps=300)
    for name in ("bas_mppi", "sa_rmppi", "rmppi"):
        ep = closed_loop(nav.controller(name, rule), nav.plant, nav.x0, 40,
                         np.random.default_rng(1), np.random.default_rng(2), Disturbance(10.0))
        X[name] = ep.X
    assert not np.array_equal(X["sa_rmppi"], X["bas_mppi"])
    assert not np.array_equal(X["sa_rmppi"], X["rmppi"])
    assert not np.array_equal(X["rmppi"], X["bas_mppi"])


def test_progress_threshold_follows_the_calibration_curve():
    d = np.geomspace(0.01, 10.0, 200)
    F = 20.0 + 100.0 * d + np.random.default_rng(0).normal(0, 1.0, d.size)
    X = np.column_stack([d, np.zeros_like(d)])
    log_d, vals = progress_curve(d, F)
    assert np.all(np.diff(vals) >= 0) and np.all(np.diff(log_d) > 0)
    th = make_threshold(AlphaRule(kappa=0.5), X, F, goal=[0.0, 0.0])
    assert isinstance(th, ProgressThreshold)
    for dist in (0.05, 0.5, 5.0):
        a = th(np.array([[dist, 0.0]]))[0]
        assert a == pytest.approx(1.5 * (20.0 + 100.0 * dist), rel=0.1)
    assert th(np.array([[100.0, 0.0]]))[0] == pytest.approx(1.5 * vals[-1])  # clamped
    q = make_threshold(AlphaRule(kind="quantile", quantile=0.9), X, F, goal=[0, 0])
    assert q(X[:1])[0] == pytest.approx(np.quantile(F, 0.9))
    s = make_threshold(AlphaRule(kind="start", factor=2.0), X, F, goal=[0, 0])
    assert s(X[:1])[0] == pytest.approx(2.0 * F[0])
    assert make_threshold(AlphaRule(kind="fixed", value=7.0))(X[:3]).tolist() == [7.0] * 3


@pytest.mark.parametrize(("kw", "field"), [
    ({"kind": "median"}, "AlphaRule.kind"), ({"kappa": -1.0}, "AlphaRule.kappa"),
    ({"kappa": np.nan}, "AlphaRule.kappa"), ({"quantile": 1.5}, "AlphaRule.quantile"),
    ({"value": np.nan}, "AlphaRule.value"), ({"calibration_steps": 2.5},
                                              "AlphaRule.calibration_steps"),
    ({"calibration_steps": True}, "AlphaRule.calibration_steps"),
])
def test_bad_alpha_rules_name_the_field(kw, field):
    with pytest.raises(ValueError, match=field.replace(".", r"\.")):
        AlphaRule(**kw)


@pytest.mark.parametrize(("kw", "field"), [
    ({"candidate_samples": 2.5}, "candidate_samples"), ({"candidate_samples": True},
                                                       "candidate_samples"),
    ({"n_candidates": 4}, "n_candidates"), ({"alpha": np.nan}, "alpha"),
    ({"fallback": "stay"}, "fallback"), ({"clip_in_cost": "yes"}, "clip_in_cost"),
])
def test_bad_rmppi_config_names_the_field(kw, field):
    with pytest.raises(ValueError, match=field):
        RMPPIConfig(**kw)


def test_bad_feedback_weights_name_the_field(nav):
    with pytest.raises(ValueError, match=r"FeedbackWeights\.q_beta"):
        FeedbackWeights(q_beta=np.inf)
    with pytest.raises(ValueError, match=r"FeedbackWeights\.Q"):
        ILQGFeedback(nav.problem.model, 100, 5, FeedbackWeights(Q=(1.0, 1.0)))
    assert FeedbackWeights.for_model(nav.plant).Q == (100.0,) * 4


def test_nonfinite_plan_and_q_beta_are_rejected(nav):
    from workbench.sampling.problem import navigation_costs

    ctrl = MPPI(nav.problem, nav.goal, nav.mppi)
    bad = replace(ctrl.initial_state(), U=np.full((100, 2), np.nan))
    with pytest.raises(ValueError, match=r"state\.U"):
        ctrl.step(bad, nav.x0, np.random.default_rng(0))
    for q in (np.nan, np.inf):
        with pytest.raises(ValueError, match="q_beta"):
            navigation_costs(nav.problem.model, q_beta=q)
    rob = RobustMPPI(nav.problem, nav.goal, nav.mppi, threshold=ConstantThreshold.selection_off())
    with pytest.raises(ValueError, match=r"state\.U"):
        rob.step(RMPPIState(U=np.zeros((99, 2)), x_nom=None, index=0), nav.x0,
                 np.random.default_rng(0))


@pytest.fixture(scope="module")
def sampler(nav):
    s = Sampler(nav.problem)
    c = SamplerConstants(sigma=np.array([5.0, 5.0]), lam=10.0, nu_mix=0.0,
                         u_min=nav.plant.u_min, u_max=nav.plant.u_max, crash_cost=1e6,
                         p=nav.problem.model.lift(nav.goal))
    return s, c, nav.problem.model.lift(nav.x0)


@pytest.mark.parametrize(("call", "field"), [
    ("K_shape", "K"), ("K_nan", "K"), ("U_shape", "U"), ("U_nan", "U"), ("x0_shape", "x0"),
    ("xs0_shape", "xs0"), ("N_bool", "N"), ("N_float", "N"), ("sigma_shape", "sigma"),
    ("p_shape", r"SamplerConstants\.p"), ("starts_shape", "starts"), ("stride_shape", "stride"),
])
def test_sampler_rejects_misshapen_input(sampler, call, field):
    s, c, x0 = sampler
    U, K = np.zeros((20, 2)), np.zeros((20, 2, 5))
    calls = {
        "K_shape": lambda: s.sais(x0, x0, U, np.zeros((20, 2, 4)), 64, c, 1),
        "K_nan": lambda: s.sais(x0, x0, U, K * np.nan, 64, c, 1),
        "U_shape": lambda: s.mppi(x0, np.zeros((20, 3)), 64, c, 1),
        "U_nan": lambda: s.mppi(x0, U * np.nan, 64, c, 1),
        "x0_shape": lambda: s.mppi(x0[:4], U, 64, c, 1),
        "xs0_shape": lambda: s.sais(x0, x0[:3], U, K, 64, c, 1),
        "N_bool": lambda: s.mppi(x0, U, True, c, 1),
        "N_float": lambda: s.mppi(x0, U, 64.0, c, 1),
        "sigma_shape": lambda: s.mppi(x0, U, 64, replace(c, sigma=np.ones(3)), 1),
        "p_shape": lambda: s.mppi(x0, U, 64, replace(c, p=np.ones(4)), 1),
        "starts_shape": lambda: s.candidates(np.zeros((8, 4)), U, np.zeros(8), c, 1),
        "stride_shape": lambda: s.candidates(np.zeros((8, 5)), U, np.zeros(7), c, 1),
    }
    with pytest.raises(ValueError, match=field):
        calls[call]()


# ---------------------------------------------------------------------------------------------
# RobustMPPI is never silently inert


def test_robust_mppi_without_a_threshold_that_can_bind_is_refused(nav):
    msg = (r"^threshold = None is invalid: RobustMPPI needs a selection threshold that can "
           r"bind; RMPPIConfig.alpha = inf never does.*wb\.calibrate\(.*"
           r"ConstantThreshold\(float\('inf'\)\)")
    with pytest.raises(ValueError, match=msg):
        RobustMPPI(nav.problem, nav.goal, nav.mppi)
    with pytest.raises(ValueError, match=msg):
        RobustMPPI(nav.problem, nav.goal, nav.mppi, RMPPIConfig(), nav.feedback("ilqg"))
    # a finite alpha, a threshold, or the explicit opt-out are all accepted
    assert RobustMPPI(nav.problem, nav.goal, nav.mppi, RMPPIConfig(alpha=2e4)).threshold(
        np.zeros((2, 4))).tolist() == [2e4, 2e4]
    off = ConstantThreshold.selection_off()
    assert off == ConstantThreshold(np.inf)
    assert RobustMPPI(nav.problem, nav.goal, nav.mppi, threshold=off).threshold is off


def test_step_info_says_whether_the_selection_could_bind(nav, sa_state):
    state, xb = sa_state
    off = RobustMPPI(nav.problem, nav.goal, nav.mppi, threshold=ConstantThreshold.selection_off())
    _, _, info = off.step(state, xb, np.random.default_rng(5))
    assert not info.alpha_finite and info.candidate == 8 and not info.nominal_differs
    on = RobustMPPI(nav.problem, nav.goal, nav.mppi, threshold=ConstantThreshold(2e4))
    _, _, info = on.step(state, xb, np.random.default_rng(5))
    assert info.alpha_finite
    # finite at some candidate only (the chosen one at +inf): the selection could still bind
    some = RobustMPPI(nav.problem, nav.goal, nav.mppi, threshold=Preset([1e9] + [np.inf] * 8))
    _, _, info = some.step(state, xb, np.random.default_rng(5))
    assert info.alpha_finite


def test_robust_part_acts_on_the_default_map_under_disturbance():
    """Through the public API: SA-RMPPI with a calibrated progress threshold, disturbance
    variance 100: the nominal state differs from the real one on some steps."""
    import workbench as wb

    nav = wb.navigation_setup()
    th = nav.threshold(wb.AlphaRule(kappa=0.1, calibration_steps=150))
    ctrl = nav.controller("sa_rmppi", threshold=th)
    ep = wb.closed_loop(ctrl, nav.plant, nav.x0, 80, np.random.default_rng(1),
                        np.random.default_rng(2), wb.Disturbance(100.0))
    assert all(i.alpha_finite for i in ep.infos[1:])
    assert sum(i.nominal_differs for i in ep.infos) > 0

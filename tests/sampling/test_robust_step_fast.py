"""The fast Robust MPPI step (RobustMPPI(fast=True), the compiled K_safe, the vectorised
selection and update) against its step-by-step twin (fast=False, ILQGFeedback(compiled=False)):
every returned number equal per element to 1e-12 relative, step by step over a disturbed
navigation episode (and the two controllers' own episodes visit the same states), in both
applied modes, with the selection's fallback exercised; and mutated copies of the fast step
fail the same comparison by orders of magnitude."""

from __future__ import annotations

import inspect
import types
from dataclasses import fields, replace

import casadi as ca
import numpy as np
import pytest
from twins import element_error  # tests/twins.py: the twins' harness

import workbench.sampling.kernels.robust as robust_kernels
import workbench.sampling.robust as robust_module
from workbench.codegen.fastcall import FastFunction
from workbench.sampling.feedback import Gains, ILQGFeedback
from workbench.sampling.problem import SamplingProblem
from workbench.sampling.robust import RMPPIConfig, RobustMPPI, candidate_weights
from workbench.sampling.robust_step import CandidateStarts, candidate_free_energies
from workbench.sampling.threshold import ProgressThreshold
from workbench.sampling.weights import free_energy
from workbench.scenarios.navigation import navigation_setup
from workbench.sim import Disturbance

RTOL = 1e-12
STEPS = 30


def rel_err(a, b) -> float:
    """max |a - b| / max(|a|, |b|, 1) per element (0 for equal non-finite entries)."""
    return element_error(a, b, 1.0)


@pytest.fixture(scope="module")
def nav():
    return navigation_setup()


def threshold(nav) -> ProgressThreshold:
    """A coarse copy of the navigation map's calibrated progress rule (kappa = 0.1)."""
    d = np.array([0.2, 1.0, 2.0, 3.0, 5.0, 7.4, 9.2, 12.2])
    F = np.array([22.5, 61.8, 203.7, 557.6, 1131.9, 2142.8, 3366.6, 9080.3])
    return ProgressThreshold(log_d=np.log(d), F=F, kappa=0.1, goal=np.asarray(nav.goal[:2]),
                             position=(0, 1))


def make(nav, fast: bool, robust: RMPPIConfig, mppi=None) -> RobustMPPI:
    sp, mppi = nav.problem, mppi or nav.mppi
    fb = ILQGFeedback(sp.model, mppi.horizon, sp.nx, nav.system.feedback_weights,
                      compiled=fast)
    return RobustMPPI(sp, nav.goal, mppi, robust, fb, threshold(nav), fast=fast)


def step_error(a, b) -> float:
    """Largest relative difference between two step results (state, u, info)."""
    (sa, ua, ia), (sb, ub, ib) = a, b
    errs = [rel_err(ua, ub), rel_err(sa.U, sb.U), rel_err(sa.x_nom, sb.x_nom),
            0.0 if sa.index == sb.index else np.inf,
            rel_err(sa.gains.K, sb.gains.K), rel_err(sa.gains.mu, sb.gains.mu),
            0.0 if (sa.gains.fallback, sa.gains.nominal_unsafe)
            == (sb.gains.fallback, sb.gains.nominal_unsafe) else np.inf]
    for f in fields(ia):
        if f.name in ("timing", "batch", "samples"):
            continue
        va, vb = getattr(ia, f.name), getattr(ib, f.name)
        if isinstance(va, dict) or va is None or isinstance(va, str):
            errs.append(0.0 if va == vb else np.inf)
        else:
            errs.append(rel_err(va, vb))
    for name in ("batch", "samples"):
        ba, bb = getattr(ia, name), getattr(ib, name)
        if (ba is None) != (bb is None):
            errs.append(np.inf)
        elif ba is not None:
            for f in fields(ba):
                va, vb = getattr(ba, f.name), getattr(bb, f.name)
                if isinstance(va, np.ndarray):
                    errs.append(rel_err(va, vb))
    return max(errs)


def episode(nav, ctrl: RobustMPPI, steps: int, other: RobustMPPI | None = None):
    """A disturbed episode driven by ``ctrl``; with ``other``, that controller steps from the
    same state with the same seed at every step too. (largest relative difference between the
    two at any step (0 without ``other``), the infos, the visited states and applied
    controls, (steps + 1 + steps, nx or nu) stacked)."""
    plant = nav.plant
    f = FastFunction(ca.Function("plant", [plant.x, plant.u], [plant.x_next]))
    dist = Disturbance(10.0)
    idx = dist.indices(plant)
    rng_c, rng_w = np.random.default_rng(2), np.random.default_rng(3)
    x = np.asarray(nav.x0, float)
    state = ctrl.initial_state(x)
    worst, infos, X, U = 0.0, [], [x], []
    for k in range(steps):
        seed = int(rng_c.integers(0, 2**63))
        a = ctrl.step(state, x, np.random.default_rng(seed))
        if other is not None:
            worst = max(worst, step_error(a, other.step(state, x,
                                                        np.random.default_rng(seed))))
        state, u, info = a
        infos.append(info)
        U.append(u)
        x = f(x, np.clip(u, plant.u_min, plant.u_max))[0] + dist.sample(
            plant.nx, plant.dt, rng_w, idx, k)
        X.append(x)
    return worst, infos, np.concatenate([np.ravel(X), np.ravel(U)])


def lockstep(nav, fast: RobustMPPI, ref: RobustMPPI, steps: int = STEPS):
    """The fast controller's episode with the reference stepping alongside, then the
    reference's own episode: (largest relative difference, step by step and between the two
    episodes' states and controls; the fast infos)."""
    worst, infos, X = episode(nav, fast, steps, ref)
    _, _, X_ref = episode(nav, ref, steps)
    return max(worst, rel_err(X, X_ref)), infos


CASES = [
    pytest.param(RMPPIConfig(applied="nominal_feedback"), False, {}, id="nominal_feedback"),
    pytest.param(RMPPIConfig(applied="real", fallback="keep_previous", diagnostics=True), True,
                 {}, id="real-keep_previous-diagnostics-samples"),
    pytest.param(RMPPIConfig(applied="real"), False,
                 {"iterations": 2, "smoothing": (9, 2), "n_samples": 256},
                 id="real-two_iterations-smoothing"),
]


@pytest.mark.parametrize("robust,record,mppi", CASES)
def test_fast_step_equals_reference(nav, robust, record, mppi):
    cfg = replace(nav.mppi, **mppi)
    fast, ref = make(nav, True, robust, cfg), make(nav, False, robust, cfg)
    assert fast.feedback.compiled and not ref.feedback.compiled
    if record:
        fast.record_samples(8)
        ref.record_samples(8)
    err, infos = lockstep(nav, fast, ref)
    assert err <= RTOL, err
    fb = sum(i.fallback_used for i in infos)
    admissible = len(infos) - 1 - fb  # the first step evaluates no candidate
    # the episode exercises the selection's fallback and admissible selections
    assert fb >= 3 and admissible >= 1, (fb, [i.candidate for i in infos])


def _with_globals(ctrl: RobustMPPI, **names) -> None:
    """A broken copy of ctrl's fast step: its step and selection read ``names`` instead of the
    module's functions (the reference controller keeps the module's)."""
    g = {**vars(robust_module), **names}
    for meth in ("step", "select_nominal"):
        f = inspect.unwrap(getattr(RobustMPPI, meth))  # the step itself, not its decorator
        setattr(ctrl, meth, types.MethodType(types.FunctionType(f.__code__, g, f.__name__,
                                                                f.__defaults__), ctrl))


def _mutations():
    """Broken copies of the fast step: name -> function(controller) that breaks it."""

    def free_energy_sum(ctrl):  # sum instead of mean inside the log
        orig = robust_module.candidate_free_energies
        _with_globals(ctrl, candidate_free_energies=lambda S, nc, lam: orig(S, nc, lam)
                      - lam * np.log(S.size // nc))

    def stride_ignored(ctrl):  # every candidate follows u* unshifted
        ctrl._stride_rep = np.zeros_like(ctrl._stride_rep)

    def mixing_off(ctrl):  # the propagated nominal state mixed in with too large a weight
        W = candidate_weights(ctrl.rcfg.n_candidates)
        W[1:-1, 1] += 1e-6
        ctrl._starts = CandidateStarts(ctrl.sp, W)

    def ksafe_regularised(ctrl):  # K_safe's first regularisation 10x
        fb = ctrl.feedback
        fb.w = replace(fb.w, mu=fb.w.mu * 10)

    def weights_shifted(ctrl):  # the update's weights with a wrong temperature
        orig = robust_module.importance_weights
        _with_globals(ctrl, importance_weights=lambda S, lam: orig(S, lam * (1 + 1e-6)))

    def applied_offset(ctrl):  # the applied control off by 1e-3 before clipping
        _with_globals(ctrl, np=_OffsetClipNumpy())

    return {"free_energy_sum": free_energy_sum, "stride_ignored": stride_ignored,
            "mixing_off": mixing_off, "ksafe_regularised": ksafe_regularised,
            "weights_shifted": weights_shifted, "applied_offset": applied_offset}


class _OffsetClipNumpy:
    """numpy whose clip(a, lo, hi) clips a - 1e-3 (the step clips only the applied control)."""

    def __getattr__(self, name):
        return getattr(np, name)

    @staticmethod
    def clip(a, lo, hi):
        return np.clip(np.asarray(a) - 1e-3, lo, hi)


@pytest.mark.parametrize("name", [None, *_mutations()])
def test_broken_fast_step_fails_comparison(nav, name):
    robust = RMPPIConfig()
    fast, ref = make(nav, True, robust), make(nav, False, robust)
    if name is not None:
        _mutations()[name](fast)
    err, _ = lockstep(nav, fast, ref, steps=8)
    if name is None:
        assert err <= RTOL, err
    else:
        assert err > 1e3 * RTOL, (name, err)


def test_fast_flag_selects_the_twin(nav):
    with pytest.raises(ValueError, match=r"RobustMPPI\.fast"):
        RobustMPPI(nav.problem, nav.goal, nav.mppi, threshold=threshold(nav), fast=1)
    with pytest.raises(ValueError, match=r"ILQGFeedback\.compiled"):
        ILQGFeedback(nav.problem.model, 10, nav.problem.nx, nav.system.feedback_weights,
                     compiled="yes")


def test_candidate_free_energies_equal_per_block():
    rng = np.random.default_rng(0)
    S = rng.random(9 * 64) * 1e4
    blocks = [S.copy()]
    S2 = S.copy()
    S2[3], S2[70] = np.inf, np.nan
    S2[128:192] = np.inf  # a candidate whose samples all crashed beyond the finite range
    blocks.append(S2)
    for SS in blocks:
        ref = np.array([free_energy(b, 10.0) for b in SS.reshape(9, 64)])
        got = candidate_free_energies(SS, 9, 10.0)
        np.testing.assert_array_equal(got, ref)
    assert np.isinf(candidate_free_energies(S2, 9, 10.0)[2])


@pytest.mark.parametrize("compiled", [True, False])
def test_candidate_starts_equal_mix_and_lift(nav, compiled):
    sp = nav.problem
    W = candidate_weights(9)
    cs = CandidateStarts(sp, W, compiled=compiled)
    assert cs.compiled == compiled
    dyn = FastFunction(sp.functions()["dyn"])
    lift = FastFunction(sp.model.lift_function, 9, shared=(1,))
    rng = np.random.default_rng(5)
    scene = sp.model.scene_value.copy()
    for k in range(6):
        if k == 3:  # another scene: every circle moved
            scene[0::3] += 0.5
        a0 = sp.model.lift(nav.x0 + rng.normal(0, 0.3, 4))
        xb = sp.model.lift(nav.x0 + rng.normal(0, 0.3, 4))
        u0 = rng.normal(0, 3, 2)
        a1 = dyn(a0, u0, scene)[0]
        mixed = W @ np.stack([a0, a1, xb])
        ref = lift(mixed[:, :4], scene)[0].reshape(9, sp.nx)
        ref[-1] = xb
        np.testing.assert_array_equal(cs(a0, u0, xb, scene), ref)


def test_candidate_starts_library_kept_under_the_problem_fingerprint(nav):
    """The starts library is kept per process under the problem's fingerprint (a string), so a
    second SamplingProblem of the same Problem reuses it (and no SamplingProblem is kept)."""
    sp = nav.problem
    other = SamplingProblem(sp.problem, sp.description, sp.weights)
    W = candidate_weights(9)
    a, b = CandidateStarts(sp, W), CandidateStarts(other, W)
    if not a.compiled:
        pytest.skip("no C compiler")
    assert all(isinstance(k, str) for k in robust_kernels._STARTS)
    assert sp.fingerprint() in robust_kernels._STARTS
    assert b._k is not None and a._k is not None and b._k._c is a._k._c


def _gains_pair(fb_fast, fb_ref, x, U, previous=None, stride=1):
    a = fb_fast.fast_gains(x, U, previous, stride)
    b = fb_ref.gains(x, U, previous, stride)
    return a, b


def _assert_same_gains(a: Gains, b: Gains):
    np.testing.assert_array_equal(a.K, b.K)
    assert (a.fallback, a.nominal_unsafe) == (b.fallback, b.nominal_unsafe)
    assert a.mu == b.mu or (np.isnan(a.mu) and np.isnan(b.mu))


@pytest.mark.parametrize("kind", ["bas_ilqg", "ilqg"])
def test_compiled_ksafe_equals_reference(nav, kind):
    """Random plans from random states (some starting inside an obstacle: the nominal
    rollout is unsafe), both feedback kinds (the plain one zero-padded)."""
    sp = nav.problem
    fb = nav.feedback(kind)
    ref = ILQGFeedback(fb.problem.model, nav.mppi.horizon, sp.nx, fb.w, compiled=False)
    assert fb.compiled
    rng = np.random.default_rng(7)
    unsafe = 0
    circles = sp.model.scene_value.reshape(-1, 3)
    for i in range(12):
        x = nav.x0 + rng.normal(0, 0.5, 4)
        if i % 3 == 0:  # inside a circle
            x[:2] = circles[i % len(circles), :2] + 0.1 * rng.normal(size=2)
        xb = sp.model.lift(x)  # the sampler's state; the plain law reads its physical part
        U = rng.normal(0, 4, (nav.mppi.horizon, 2))
        a, b = _gains_pair(fb, ref, xb, U)
        _assert_same_gains(a, b)
        unsafe += a.nominal_unsafe
        assert a.K.shape == (nav.mppi.horizon, 2, sp.nx)
    assert unsafe >= 1


def test_compiled_ksafe_fallbacks_equal_reference(nav):
    sp = nav.problem
    T = nav.mppi.horizon
    rng = np.random.default_rng(8)
    U = rng.normal(0, 2, (T, 2))
    xb = sp.model.lift(nav.x0)
    prev = Gains(K=rng.normal(size=(T, 2, sp.nx)))
    # no cost at all (Quu = 0) and no regularisation level above mu = 0: the pass fails
    zero = replace(nav.system.feedback_weights, Q=(0.0,) * 4, R=(0.0, 0.0), q_beta=0.0, mu=0.0)
    w = replace(zero, mu_max=1e-9)
    fast = ILQGFeedback(sp.model, T, sp.nx, w)
    ref = ILQGFeedback(sp.model, T, sp.nx, w, compiled=False)
    a, b = _gains_pair(fast, ref, xb, U, prev, 2)
    assert a.fallback == "backward_failed"
    _assert_same_gains(a, b)
    a, b = _gains_pair(fast, ref, xb, U, None, 2)
    _assert_same_gains(a, b)
    # a non-finite nominal rollout: both refuse it with the same error
    x_bad = xb.copy()
    x_bad[0] = np.nan
    fast2 = nav.feedback("bas_ilqg")
    ref2 = ILQGFeedback(sp.model, T, sp.nx, nav.system.feedback_weights, compiled=False)
    msgs = []
    for fb in (fast2, ref2):
        with pytest.raises(ValueError) as exc:
            fb.fast_gains(x_bad, U, prev, 1)
        msgs.append(str(exc.value))
    assert msgs[0] == msgs[1]
    # the retries: mu = 0 fails (Quu = 0), then mu = max(10 * 0, 1e-8) succeeds
    a, b = _gains_pair(ILQGFeedback(sp.model, T, sp.nx, zero),
                       ILQGFeedback(sp.model, T, sp.nx, zero, compiled=False), xb, U)
    assert a.fallback is None and a.mu == 1e-8
    _assert_same_gains(a, b)


def test_compiled_ksafe_in_another_scene(nav):
    sp = nav.problem
    T = nav.mppi.horizon
    fast = nav.feedback("bas_ilqg")
    ref = ILQGFeedback(sp.model, T, sp.nx, nav.system.feedback_weights, compiled=False)
    scene = sp.model.scene_value.copy()
    scene[0::3] += 0.7  # every circle moved
    fast.set_scene(scene)
    ref.set_scene(scene)
    rng = np.random.default_rng(9)
    xb = sp.model.lift(nav.x0, scene)
    U = rng.normal(0, 3, (T, 2))
    a, b = _gains_pair(fast, ref, xb, U)
    _assert_same_gains(a, b)
    c = nav.feedback("bas_ilqg").fast_gains(xb, U, None, 0)  # the model's own scene
    assert not np.array_equal(a.K, c.K)

"""ECBFFeedback.gains (QPs set up per group, row Jacobians and KKT solves batched) against its
per-step twin gains_twin (sensitivity() at each active step): equal gains (1e-12 relative,
absolute below magnitude 1), activity and fallbacks on plans that reach every branch: no active
row, hard rows, violated (soft) rows, box bounds, hard-mode infeasible steps, multipliers that
drop a bound, daqp failures (OSQP), non-finite gains and derivatives; closed-loop plans of the
navigation scene."""

from __future__ import annotations

import numpy as np
import pytest

import workbench.sampling.feedback.ecbf as ef
from workbench.filters.ecbf import ECBFOptions
from workbench.problem.models import Circle, double_integrator
from workbench.sampling.feedback.ecbf import ECBFFeedback
from workbench.sampling.mppi import MPPIConfig
from workbench.sampling.planning import physical_model
from workbench.sampling.robust import RMPPIConfig, RobustMPPI
from workbench.scenarios.methods import affine_in_controls
from workbench.scenarios.navigation import navigation_setup
from workbench.sim import Disturbance, closed_loop

T = 30
OBSTACLE = Circle((2.0, 2.0), 0.8)
STARTS = (np.array([0.0, -2.0, 1.0, 0.0]),  # far from it
          np.array([0.5, 1.3, 3.0, 0.0]),  # heads for its flank at speed
          np.array([0.5, 2.0, 3.0, 0.0]),  # straight through it
          np.array([0.5, 1.1, 3.0, 0.0]),  # grazes it
          np.array([3.5, 2.7, -3.0, 0.0]))  # heads for its other flank, the other way


def close(a, b, tol=1e-12):
    """Per-element |a - b| <= tol * max(|a|, |b|, 1)."""
    return bool(np.all(np.abs(a - b) <= tol * np.maximum(np.maximum(np.abs(a), np.abs(b)), 1)))


def assert_same(law, x0, U, previous=None, stride=0, ref_law=None):
    """gains (fast) equals gains_twin (of ref_law, default the same law)."""
    fast = law.gains(x0, U, previous, stride)
    ref = (ref_law or law).gains_twin(x0, U, previous, stride)
    assert fast.fallback == ref.fallback
    assert fast.activity == ref.activity
    assert fast.nominal_unsafe == ref.nominal_unsafe
    assert np.array_equal(fast.mu, ref.mu, equal_nan=True)
    assert fast.K.shape == ref.K.shape and close(fast.K, ref.K), np.abs(fast.K - ref.K).max()
    return fast, ref


def branches(law, x0, U) -> set[str]:
    """Branches the twin takes on a plan: per active step the kinds of its active set."""
    g = law.tracking.gains(x0, U, None, 0)
    X, Uc = law.nominal(x0, U)
    seen = set()
    for k in range(law.T):
        a, b, _, _ = law.rows(X[k])
        if not (b - a @ Uc[k] > law.opt.eps_abs).any():
            seen.add("idle")
            continue
        s = law.sensitivity(X[k], Uc[k], g.K[k])
        if s is None:
            seen.add("infeasible_hard")
            continue
        seen.update(name for name, v in (("hard", s.hard), ("soft", s.soft),
                                         ("upper", s.box_upper), ("lower", s.box_lower)) if v)
    return seen


def plans(seed=0, n=6):
    """Zero controls and random controls up to beyond the box, from each start."""
    rng = np.random.default_rng(seed)
    out = [(x0, np.zeros((T, 2))) for x0 in STARTS]
    for scale in (2.0, 8.0):
        out += [(STARTS[rng.integers(1, len(STARTS))], scale * rng.standard_normal((T, 2)))
                for _ in range(n)]
    return out


@pytest.fixture(scope="module")
def model():
    return double_integrator(obstacles=(OBSTACLE,), u_limit=5.0)


def held_log(monkeypatch, law) -> list[bool]:
    """One entry per _held call: did its active set lose a bound or row (_kkt run again)?"""
    log, kkt, held = [], [], law._held
    monkeypatch.setattr(law, "_kkt", lambda *a, f=law._kkt: kkt.append(1) or f(*a))

    def spy(*a):
        n = len(kkt)
        out = held(*a)
        log.append(len(kkt) - n > 1)
        return out

    monkeypatch.setattr(law, "_held", spy)
    return log


@pytest.mark.parametrize("mode", ["soft", "hard"])
def test_fast_gains_equal_the_twin_on_every_branch(model, mode, monkeypatch):
    """Equal on plans reaching idle steps, hard and soft rows, both box bounds and (hard mode)
    infeasible steps; the fast path leaves to the per-step drop loop (_held) exactly the steps
    where the twin drops a bound or row."""
    law = ECBFFeedback(model, T, 5, ecbf=ECBFOptions(mode=mode))
    log = held_log(monkeypatch, law)
    seen: set[str] = set()
    for x0, U in plans():
        del log[:]
        fast = law.gains(x0, U, None, 0)
        fast_log = list(log)
        del log[:]
        law.gains_twin(x0, U, None, 0)
        assert all(fast_log) and len(fast_log) == sum(log)
        assert_same(law, x0, U)
        assert fast.fallback is None
        seen |= branches(law, x0, U)
    need = {"idle", "hard", "upper", "lower"} | ({"soft"} if mode == "soft"
                                                 else {"infeasible_hard"})
    assert need <= seen, seen
    far = law.gains(STARTS[0], np.zeros((T, 2)), None, 0)  # nothing active: the tracking gain
    assert far.activity["ecbf_active"] == 0.0
    tracking = law.tracking.gains(STARTS[0], np.zeros((T, 2)), None, 0).K
    np.testing.assert_array_equal(far.K[:, :, :4], tracking)
    assert not np.any(far.K[:, :, 4])


def test_fast_gains_take_the_per_step_path_where_multipliers_drop_a_bound(model, monkeypatch):
    """daqp made to report control 0 at its upper bound where it is not: the held bound's
    multiplier is negative and dropped, in both paths (the fast one through _held)."""
    law = ECBFFeedback(model, T, 5)
    solve = ef.daqp.solve

    def spurious(*args):
        z, f, flag, info = solve(*args)
        lam = np.array(info["lam"], dtype=float)
        if lam[0] == 0.0:
            lam[0] = 1.0
        return z, f, flag, {**info, "lam": lam}

    monkeypatch.setattr(ef.daqp, "solve", spurious)
    held = []
    monkeypatch.setattr(law, "_held", lambda *a: held.append(1) or ECBFFeedback._held(law, *a))
    n = 0
    for x0, U in plans(1, 3):
        before = len(held)
        fast = law.gains(x0, U, None, 0)
        n += len(held) - before
        ref = law.gains_twin(x0, U, None, 0)
        assert fast.activity == ref.activity and close(fast.K, ref.K)
    assert n > 5  # the fast path used the per-step drop loop


def test_fast_gains_equal_the_twin_where_daqp_fails(model, monkeypatch):
    """daqp fails everywhere: both paths use the OSQP filter (warm-started: two fresh laws
    called in the same order make the same OSQP calls)."""
    monkeypatch.setattr(ef.daqp, "solve", lambda H, f, *a: (np.zeros_like(f), 0.0, -4,
                                                            {"lam": np.zeros(len(a[1]))}))
    for mode in ("soft", "hard"):
        fast_law, ref_law = (ECBFFeedback(model, T, 5, ecbf=ECBFOptions(mode=mode))
                             for _ in range(2))
        for x0, U in plans(2, 2):
            fast, _ = assert_same(fast_law, x0, U, ref_law=ref_law)
            assert fast.fallback is None


@pytest.mark.parametrize(("poison", "reason"), [(np.nan, "nonfinite_derivatives"),
                                                (1e308, "nonfinite_gains")])
def test_fast_gains_fall_back_as_the_twin(model, monkeypatch, poison, reason):
    """Row derivatives made non-finite (or so large the gains overflow) after the first active
    step: the same reason (from the rows of the step that stopped the loop), the shifted
    previous gains, and the activity counted up to that step."""
    law = ECBFFeedback(model, T, 5)
    x0, U = STARTS[1], np.zeros((T, 2))
    previous = law.gains(x0, U, None, 0)
    X, _ = law.nominal(x0, U)
    steps = [k for k in range(T)
             if (law.rows(X[k])[1] - law.rows(X[k])[0] @ U[k] > law.opt.eps_abs).any()]
    assert len(steps) > 2 and X[steps[1], 0] > X[steps[0], 0]
    threshold = 0.5 * (X[steps[0], 0] + X[steps[1], 0])  # rows after the first active step
    for name in ("_jac", "_jac_batch"):
        f = getattr(law, name)

        def poisoned(x, scene, f=f):
            a, b, da, db = f(x, scene)
            states = np.asarray(x, dtype=float).reshape(-1, 4)
            da.reshape(len(states), -1)[states[:, 0] > threshold] *= poison
            return a, b, da, db

        monkeypatch.setattr(law, name, poisoned)
    with np.errstate(all="ignore"):
        fast, ref = assert_same(law, x0, U, previous, 2)
    assert fast.fallback == reason
    np.testing.assert_array_equal(fast.K, ref.K)  # the previous gains, shifted


@pytest.fixture(scope="module")
def nav():
    return navigation_setup()


def test_fast_gains_equal_the_twin_on_closed_loop_plans(nav):
    """The nominal plans RobustMPPI feeds the law on the navigation scene (30 circles) under
    moderate and strong disturbances: many active steps, some infeasible."""
    pm = affine_in_controls(physical_model(nav.problem.model))
    H = nav.mppi.horizon
    law = ECBFFeedback(pm, H, nav.problem.nx)
    recorded = []
    gains = law.gains

    def record(x_nom, U, previous, stride):
        recorded.append((np.array(x_nom, float), np.array(U, float), previous, stride))
        return gains(x_nom, U, previous, stride)

    law.gains = record
    cfg = MPPIConfig(n_samples=64, horizon=H, sigma=nav.mppi.sigma, lam=nav.mppi.lam)
    for level in (10.0, 100.0):
        ctrl = RobustMPPI(nav.problem, nav.goal, cfg, RMPPIConfig(alpha=1e6), feedback=law)
        closed_loop(ctrl, nav.plant, nav.x0, 30, np.random.default_rng(1),
                    np.random.default_rng(2), Disturbance(level))
    del law.gains
    active = infeasible = 0.0
    for x_nom, U, previous, stride in recorded:
        fast, _ = assert_same(law, x_nom, U, previous, stride)
        active += fast.activity["ecbf_active"]
        infeasible += fast.activity["ecbf_infeasible"]
    assert len(recorded) == 60 and active > 20 and infeasible > 4, (active, infeasible)

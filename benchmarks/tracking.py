"""Benchmarks of issue 3: the ECBF filter step and AL-iLQG against IPOPT.

``records(repeats)`` returns records in the format of ``benchmarks/__main__.py``
(name, value, unit, baseline, baseline_value, ratio = baseline_value / value, params).
"""

from __future__ import annotations

import statistics
import time

import numpy as np
import qpsolvers
import scipy.sparse as sp

from workbench.al_ilqg import al_ilqg, al_problem
from workbench.ecbf import ECBFFilter
from workbench.ilqg import ilqg, make_passes
from workbench.ipopt_oracle import solve_ipopt
from workbench.models import double_integrator
from workbench.scenes import TrackingScene
from workbench.tracking import TrackingWeights, tracking_params, tracking_problem


def _record(name, value, unit, baseline, baseline_value, params) -> dict:
    ratio = baseline_value / value if value else None
    return {"name": name, "value": value, "unit": unit, "baseline": baseline,
            "baseline_value": baseline_value, "ratio": ratio, "params": params}


def _qp_stream(n_rollouts: int = 40, seed: int = 0):
    """(x, u_ref) pairs of an ECBF-filtered Monte Carlo run of the tracking scene, split into
    those that need the QP and all of them."""
    scene = TrackingScene()
    model = double_integrator(obstacles=(scene.obstacle,), u_limit=scene.u_limit)
    free = tracking_problem(double_integrator(u_limit=scene.u_limit), TrackingWeights())
    nom = ilqg(free, scene.start, np.zeros((scene.horizon, 2)),
               tracking_params(free, scene.reference(), scene.target))
    filt = ECBFFilter(model)
    noise = 10.0 * np.random.default_rng(seed).standard_normal((n_rollouts, scene.horizon, 2))
    X = np.tile(np.array(scene.start), (n_rollouts, 1))
    active, every = [], []
    for k in range(scene.horizon):
        U_ref = nom.U[k] + (X - nom.X[k]) @ nom.K[k].T + noise[:, k]
        res = filt.filter_batch(X, U_ref)
        every += list(zip(X.copy(), U_ref, strict=True))
        active += [(X[i].copy(), U_ref[i]) for i in np.flatnonzero(res.qp_solved)]
        X = np.hstack([X[:, :2] + scene.dt * X[:, 2:], X[:, 2:] + scene.dt * res.u])
    return model, active, every


def bench_ecbf_filter_step(repeats: int) -> dict:
    """Microseconds per filtered step on steps that need the QP: the filter's OSQP workspace
    (set up once, updated per step) vs a fresh ``qpsolvers.solve_qp`` (OSQP) per step on the same
    QP. Both include evaluating the ECBF rows."""
    model, active, every = _qp_stream()
    filt = ECBFFilter(model)
    o = filt.options
    nh = model.nh
    P = sp.csc_matrix(np.diag(np.r_[2.0, 2.0, 2 * o.slack_quadratic * np.ones(nh)]))
    lb, ub = np.r_[model.u_min, np.zeros(nh)], np.r_[model.u_max, np.full(nh, np.inf)]

    def fresh(x, u_ref):
        a, b = filt.rows(x)
        n = np.linalg.norm(a, axis=1)
        G = sp.csc_matrix(-np.hstack([a / n[:, None], np.eye(nh)]))
        return qpsolvers.solve_qp(P, np.r_[-2 * u_ref, o.slack_linear * np.ones(nh)],
                                  G=G, h=-b / n, lb=lb,
                                  ub=ub, solver="osqp", eps_abs=o.eps_abs, eps_rel=o.eps_rel,
                                  polishing=o.polish, max_iter=o.max_iter)[:2]

    def per_step(fn, pairs):
        t0 = time.perf_counter()
        out = [fn(x, u) for x, u in pairs]
        return 1e6 * (time.perf_counter() - t0) / len(pairs), out

    ours, theirs, stream = [], [], []
    for _ in range(repeats):
        t, u_ours = per_step(lambda x, u: filt(x, u).u, active)
        ours.append(t)
        stream.append(per_step(lambda x, u: filt(x, u).u, every)[0])
    step = max(1, len(active) // 400)  # the fresh solver is slow: a subsample
    sub = active[::step]
    for _ in range(max(1, repeats // 2)):
        t, u_fresh = per_step(fresh, sub)
        theirs.append(t)
    diff = float(np.max(np.abs(np.array(u_ours[::step]) - np.array(u_fresh))))
    return _record("ecbf_filter_step", statistics.median(ours), "us/step",
                   "fresh_qpsolvers_solve_qp_us_per_step", statistics.median(theirs), {
                       "steps_needing_qp": len(active), "fresh_subsample": len(sub),
                       "all_steps": len(every),
                       "us_per_step_all_steps_with_shortcut": statistics.median(stream),
                       "max_abs_control_difference": diff, "solver": "osqp",
                       "includes": "ECBF rows (CasADi Function buffer) + QP", "goal_ratio": 5.0})


def bench_al_ilqg_vs_ipopt(repeats: int) -> dict:
    """AL-iLQG on the tracking scene vs IPOPT (exact Hessian) with the hard constraint."""
    scene = TrackingScene()
    model = double_integrator(obstacles=(scene.obstacle,), u_limit=scene.u_limit)
    plain = tracking_problem(model, TrackingWeights())
    P = tracking_params(plain, scene.reference(), scene.target)
    alp = al_problem(model, plain.cost)
    U0 = np.zeros((scene.horizon, 2))
    x0 = np.array(scene.start)
    passes = make_passes(alp.problem, scene.horizon)  # loads the cached library once
    runs = [al_ilqg(alp, x0, U0, P, passes=passes) for _ in range(repeats)]
    res = runs[-1]
    oracle = [solve_ipopt(plain, x0, U0, P, hard_constraints=True) for _ in range(3)]
    ora = oracle[-1]
    t_al = statistics.median(r.solve_time_s for r in runs)
    t_ipopt = statistics.median(o.solve_time_s for o in oracle)
    return _record("al_ilqg_vs_ipopt_tracking", 1e3 * t_al, "ms", "ipopt_hard_constraint_ms",
                   1e3 * t_ipopt, {
                       "T": scene.horizon, "al_cost": res.cost, "ipopt_cost": ora.cost,
                       "rel_cost_difference": (res.cost - ora.cost) / abs(ora.cost),
                       "al_min_h": res.min_margin, "al_max_violation": res.max_violation,
                       "outer_iterations": len(res.history),
                       "inner_iterations": res.inner_iterations,
                       "ipopt_iterations": ora.iterations, "ipopt_status": ora.status,
                       "ipopt_time": "solve call only (exact Hessian, tol 1e-10)"})


def records(repeats: int) -> list[dict]:
    return [bench_ecbf_filter_step(repeats), bench_al_ilqg_vs_ipopt(repeats)]

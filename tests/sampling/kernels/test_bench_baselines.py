"""The benchmark's NumPy baselines compute what the kernels compute (fed the kernels' noise), and
the multiple-shooting NLP baselines (IPOPT, FATROP) solve the problem iLQG solves."""

from __future__ import annotations

import numpy as np
import pytest
from test_sampler_kernels import (
    GOAL,
    OBST,
    RTOL,
    SAIS_COSTS,
    N,
    T,
    mppi_start,
    rel_err,
    sais_branch_counts,
    sais_case,
    twin_sais,
)

from benchmarks.numpy_baseline import VectorisedNavigation, mppi_baseline, sais_baseline
from workbench.problem.barrier import embed_barrier
from workbench.problem.models import double_integrator
from workbench.sampling.kernels.constants import SamplerConstants
from workbench.sampling.problem import navigation_costs
from workbench.sampling.sampler import Sampler


def _setup(barrier: bool):
    model = double_integrator(obstacles=OBST, u_limit=5.0)
    model = embed_barrier(model) if barrier else model
    sp = navigation_costs(model) if barrier else navigation_costs(model, S=(10, 10, 1, 1))
    c = SamplerConstants(sigma=np.array([3.0, 2.4]), lam=1.3, nu_mix=0.1, u_min=model.u_min,
                         u_max=model.u_max, crash_cost=1e6, p=model.lift(GOAL))
    return model, sp, Sampler(sp, backend="compiled"), c


def test_vectorised_sais_equals_the_kernel():
    """On the kernel tests' branch-rich SAIS case (crashes real only / nominal only, clipping at
    both bounds, feedback incl. the beta column, alpha binding on some samples)."""
    model, sp, sampler, c = _setup(True)
    case = sais_case(model, sampler, c)
    counts = sais_branch_counts(case, twin_sais(sp, case))
    assert counts["real_only"] > 0 and counts["nom_only"] > 0 and counts["S_hat>alpha"] > 0
    batch = sampler.sais(case.x0, case.xs0, case.U, case.K, N, case.c, case.seed)
    Z = sampler.lib.normals(N, T, 2, case.seed)
    out = sais_baseline(VectorisedNavigation(sp), case.x0, case.xs0, case.U, case.K, Z, case.c)
    for name in (*SAIS_COSTS, "v_nom", "v_real"):
        assert rel_err(getattr(batch, name), out[name]) <= RTOL, name
    for name in ("crashed_real", "crashed_nom"):
        np.testing.assert_array_equal(getattr(batch, name), out[name])


@pytest.mark.parametrize("barrier", [True, False])
def test_vectorised_mppi_equals_the_kernel(barrier):
    model, sp, sampler, c = _setup(barrier)
    x0 = mppi_start(model)
    U = np.random.default_rng(11).normal(0, 2.0, (T, 2))
    batch = sampler.mppi(x0, U, N, c, seed=123)
    out = mppi_baseline(VectorisedNavigation(sp), x0, U, sampler.lib.normals(N, T, 2, 123), c)
    assert 0 < out["crashed"].sum() < N
    np.testing.assert_array_equal(batch.crashed, out["crashed"])
    assert rel_err(batch.S, out["S"]) <= RTOL
    assert rel_err(batch.v, out["v"]) <= RTOL


def test_multiple_shooting_nlps_reach_the_ddp_optimum(scene):
    """IPOPT and FATROP on the multiple-shooting NLP of the BaS tracking problem end where full
    DDP ends (the benchmark asserts the same at 1e-6 relative)."""
    from conftest import bas_tracking_problem

    from workbench.ilqg import ILQGOptions, ilqg
    from workbench.ilqg.oracle import MultipleShootingNLP

    problem, P = bas_tracking_problem(scene)
    U0 = np.zeros((scene.horizon, 2))
    ddp = ilqg(problem, scene.start, U0, P, ILQGOptions(second_order=True))
    for solver in ("ipopt", "fatrop"):
        nlp = MultipleShootingNLP(problem, scene.horizon, solver, tol=1e-7)
        res = nlp.solve(scene.start, U0, P)
        assert res.success, (solver, res.status)
        assert abs(res.cost - ddp.cost) / ddp.cost < 1e-6, solver
        np.testing.assert_allclose(res.X[0], problem.check_initial_state(scene.start))
        # the NLP's states are its controls' rollout (gaps closed)
        np.testing.assert_allclose(res.X, problem.rollout(res.X[0], res.U), atol=1e-6)
        # interior-point solvers relax bounds slightly (FATROP: ~1.4e-7 here)
        assert np.all(np.abs(res.U) <= scene.u_limit * (1 + 1e-6))


def test_multiple_shooting_hard_constraints_match_single_shooting(scene):
    from workbench.ilqg.bas import TrackingWeights, tracking_params, tracking_problem
    from workbench.ilqg.oracle import MultipleShootingNLP, solve_ipopt

    model = double_integrator(obstacles=(scene.obstacle,), u_limit=scene.u_limit)
    plain = tracking_problem(model, TrackingWeights())
    P = tracking_params(plain, scene.reference(), scene.target)
    U0 = np.zeros((scene.horizon, 2))
    single = solve_ipopt(plain, scene.start, U0, P, hard_constraints=True)
    for solver in ("ipopt", "fatrop"):
        res = MultipleShootingNLP(plain, scene.horizon, solver, hard_constraints=True,
                                  tol=1e-7).solve(scene.start, U0, P)
        assert abs(res.cost - single.cost) / single.cost < 1e-6, solver
        assert min(model.margins(x).min() for x in res.X) > -1e-6


def test_pytorch_mppi_benchmark_is_skipped_with_a_reason_without_torch(monkeypatch):
    import importlib.util

    from benchmarks import torch_mppi

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "torch" else real(name, *a))
    r = torch_mppi.record(1)
    assert r["ratio"] is None and "not installed" in r["skipped"]

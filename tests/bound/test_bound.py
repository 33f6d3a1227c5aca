"""Lemma-1 estimators (assumptions §11.2-11.3): closed forms, the diagnostic kernels against
the NumPy/CasADi twins, T1 on the navigation map, and bad input."""

from __future__ import annotations

import re
from dataclasses import replace

import numpy as np
import pytest

from workbench.bound import (
    BoundConfig,
    BoundEstimator,
    BoundRecorder,
    BoundStep,
    CostGradients,
    LipschitzGrid,
    bootstrap_free_energy,
    d_f,
    disturbance_bound,
    episode_checks,
    first_batch,
    free_energy_estimate,
    free_energy_lse,
    independent_batch,
    step_checks,
    summarize,
    transition_checks,
    tube_radius,
)
from workbench.bound.free_energy import FreeEnergy
from workbench.bound.lipschitz import Lipschitz
from workbench.bound.step import check_batch
from workbench.bound.tube import Tube
from workbench.problem.barrier import embed_barrier
from workbench.problem.models import double_integrator
from workbench.problem.obstacles import Circle
from workbench.sampling.kernels.constants import SamplerConstants
from workbench.sampling.mppi import MPPIConfig
from workbench.sampling.problem import navigation_costs
from workbench.sampling.robust import RMPPIConfig, RobustMPPI
from workbench.sampling.sampler import SAISDiagBatch, Sampler
from workbench.sampling.twin import sais_twin
from workbench.scenarios.navigation import navigation_setup
from workbench.sim import Disturbance, closed_loop

# ----------------------------------------------------------------------------------------------
# Free energy: a linear-Gaussian system with quadratic cost
# ----------------------------------------------------------------------------------------------


def linear_gaussian(T=10, dt=0.1, lam=1.0, sigma=3.0, u=0.5, x0=(1.0, 0.0), Q=(1.0, 0.1),
                    Qf=(5.0, 1.0)):
    """Closed-form free energy of a linear-Gaussian system with quadratic cost, and a sampler.

    System: x_{k+1} = A x_k + B (u_k + ε_k), ε_k ~ N(0, σ²) i.i.d. (a double integrator, one
    input), cost S = Σ_{k=1}^T x_kᵀ Q x_k + x_Tᵀ Q_f x_T + λ Σ_k (½ u_kᵀ Σ⁻¹ u_k + u_kᵀ Σ⁻¹ ε_k)
    (state cost + the likelihood ratio of assumptions §11.2 item 2), F = −λ log E[exp(−S/λ)].

    Stack e = (ε_0..ε_{T−1}) ~ N(0, Σ̄), Σ̄ = σ² I. Then x_k = a_k + G_k e (a_k the noise-free
    rollout, G_k = [A^{k−1}B, ..., B, 0...]), so S(e) = ½ eᵀ H e + gᵀ e + c with
    H = 2 Σ_k G_kᵀ W_k G_k, g = 2 Σ_k G_kᵀ W_k a_k + λ Σ̄⁻¹ ū, c = Σ_k a_kᵀ W_k a_k + ½ λ ūᵀ Σ̄⁻¹ ū,
    W_k = Q (+ Q_f at k = T). The Gaussian integral
      E[exp(−S/λ)] = det(I + Σ̄ H/λ)^{−½} exp(½ (g/λ)ᵀ (Σ̄⁻¹ + H/λ)⁻¹ (g/λ) − c/λ)
    (complete the square in e) gives
      F = c + (λ/2) log det(I + Σ̄ H/λ) − (1/(2λ)) gᵀ (Σ̄⁻¹ + H/λ)⁻¹ g.
    Returns (F, sample(N, rng) -> costs (N,)).
    """
    A = np.array([[1.0, dt], [0.0, 1.0]])
    B = np.array([0.0, dt])
    Q, Qf = np.diag(Q), np.diag(Qf)
    ub = np.full(T, u)
    a, G = [np.asarray(x0, float)], [np.zeros((2, T))]
    for k in range(T):
        Gk = A @ G[-1]
        Gk[:, k] += B
        a.append(A @ a[-1] + B * ub[k])
        G.append(Gk)
    H, g, c = np.zeros((T, T)), np.zeros(T), 0.0
    for k in range(1, T + 1):
        W = Q + (Qf if k == T else 0.0)
        H += 2 * G[k].T @ W @ G[k]
        g += 2 * G[k].T @ W @ a[k]
        c += a[k] @ W @ a[k]
    Sinv = np.eye(T) / sigma**2
    g = g + lam * Sinv @ ub
    c += 0.5 * lam * ub @ Sinv @ ub
    F = (c + 0.5 * lam * np.linalg.slogdet(np.eye(T) + sigma**2 * H / lam)[1]
         - 0.5 / lam * g @ np.linalg.solve(Sinv + H / lam, g))

    def sample(N, rng):
        e = rng.normal(0.0, sigma, (N, T))
        return 0.5 * np.einsum("ni,ij,nj->n", e, H, e) + e @ g + c

    return float(F), sample


def coverage(sample, F, lam, N, reps, rng, z=3.0) -> float:
    hits = []
    for _ in range(reps):
        est = free_energy_estimate(sample(N, rng), lam, z)
        hits.append(abs(est.value - F) <= est.E)
    return float(np.mean(hits))


def test_closed_form_free_energy_matches_a_large_batch():
    F, sample = linear_gaussian()
    est = free_energy_estimate(sample(400_000, np.random.default_rng(0)), 1.0)
    assert abs(est.value - F) <= est.E
    assert abs(est.value - F) < 1e-2 * abs(F)


def test_delta_method_interval_covers_the_closed_form():
    """>= 95 % of repeated batches (N = 1024, z = 3) contain F; not vacuous: with N = 4 the
    interval misses F in a large share of batches, and z = 1 covers clearly less than 95 %."""
    F, sample = linear_gaussian()
    rng = np.random.default_rng(1)
    assert coverage(sample, F, 1.0, 1024, 300, rng) >= 0.95
    assert coverage(sample, F, 1.0, 4, 300, rng) < 0.8
    assert coverage(sample, F, 1.0, 1024, 300, rng, z=1.0) < 0.9


def test_bootstrap_agrees_with_delta_method_within_factor_two():
    _, sample = linear_gaussian()
    rng = np.random.default_rng(2)
    ratios = []
    for _ in range(20):
        S = sample(1024, rng)
        d, b = free_energy_estimate(S, 1.0), bootstrap_free_energy(S, 1.0, rng, 200)
        assert b.value == pytest.approx(d.value, rel=1e-12)
        ratios.append(b.E / d.E)
    assert 0.5 <= min(ratios) and max(ratios) <= 2.0
    assert 0.8 <= np.median(ratios) <= 1.25


def test_mppig_variant_and_log_sum_exp_by_hand():
    S, lam = np.array([1.0, 2.0, 4.0]), 2.0
    w = np.exp(-(S - 1.0) / lam)
    var = lam * (np.mean(w * w) - np.mean(w) ** 2)
    t = var / (np.mean(w) * np.sqrt(3))
    e = free_energy_estimate(S, lam, method="mppig")
    assert e.E == pytest.approx(lam * (t + t * t / 2), rel=1e-14)
    assert e.value == pytest.approx(-lam * np.log(np.mean(np.exp(-S / lam))), rel=1e-14)
    # huge costs: no overflow, shift-invariant
    assert free_energy_lse(S + 1e12, lam) == pytest.approx(1e12 + free_energy_lse(S, lam),
                                                          rel=1e-15)


# ----------------------------------------------------------------------------------------------
# Lipschitz constants, tube radius, D
# ----------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def quadratic():
    """A double integrator without obstacles: q = |p - g|²_Qp + |v|²_Qv, φ = |x - g|²_S."""
    sp = navigation_costs(double_integrator(obstacles=(), u_limit=5.0), Qp=(1.0, 3.0),
                          Qv=(0.1, 0.4), S=(10.0, 20.0, 1.0, 2.0))
    return sp, CostGradients(sp, backend="compiled"), np.array([4.0, 3.0, 0.0, 0.0])


def test_lipschitz_constants_of_a_quadratic_cost_equal_the_analytic_ones(quadratic):
    _, grads, g = quadratic
    rng = np.random.default_rng(3)
    T, N = 20, 101
    X = rng.normal(0.0, 2.0, (T + 1, 4, N))
    Xs = X + rng.normal(0.0, 0.3, X.shape)
    L = grads.local(X, Xs, g)
    Wq, Wp = 2 * np.array([1.0, 3.0, 0.1, 0.4]), 2 * np.array([10.0, 20.0, 1.0, 2.0])
    gq = [np.linalg.norm(Wq[None, :, None] * (Xs[1:] + s * (X[1:] - Xs[1:]) - g[None, :, None]),
                         axis=1).max() for s in (0, .25, .5, .75, 1)]
    gp = [np.linalg.norm(Wp[:, None] * (Xs[-1] + s * (X[-1] - Xs[-1]) - g[:, None]),
                         axis=0).max() for s in (0, .25, .5, .75, 1)]
    assert L.L_q == pytest.approx(max(gq), rel=1e-12)
    assert L.L_phi == pytest.approx(max(gp), rel=1e-12)
    assert (L.points_q, L.points_phi, L.excluded_q) == (5 * T * N, 5 * N, 0)
    # assumptions §11.2's analytic bound for the quadratic part: 2 |Q| (max_k |x* - g| + R)
    R = tube_radius(X, Xs, 4).R
    bound = Wq.max() * (np.linalg.norm(Xs[1:] - g[None, :, None], axis=1).max() + R)
    assert L.L_q <= bound * (1 + 1e-12)
    # global: the grid's corners are the farthest points from the goal
    grid = LipschitzGrid(x_range=(0.0, 10.0), y_range=(-1.0, 8.0), spacing=0.5, v_max=3.0)
    G = grads.global_constant(grid, g)
    corners = np.array([[x, y, v, v] for x in (0.0, 10.0) for y in (-1.0, 8.0)
                        for v in (-3.0, 3.0)]) - g
    assert G.L_q == pytest.approx(np.linalg.norm(Wq * corners, axis=1).max(), rel=1e-12)
    assert G.L_phi == pytest.approx(np.linalg.norm(Wp * corners, axis=1).max(), rel=1e-12)


def test_secant_never_exceeds_the_gradient_estimate(quadratic):
    _, grads, g = quadratic
    rng = np.random.default_rng(4)
    for scale in (0.01, 0.3, 3.0):
        X = rng.normal(0.0, 3.0, (11, 4, 64))
        L = grads.local(X + rng.normal(0.0, scale, X.shape), X, g)
        assert 0 < L.secant_q <= L.L_q and 0 < L.secant_phi <= L.L_phi
        assert L.secant_ok


def test_tube_radius_by_hand():
    X = np.zeros((3, 5, 2))
    Xs = np.zeros_like(X)
    X[1, :, 0] = [3.0, 4.0, 0.0, 0.0, 7.0]  # beta (index 4) is not part of the physical norm
    X[2, :, 1] = [0.0, 0.0, 1.0, 0.0, 0.0]
    t = tube_radius(X, Xs, physical=4, quantile=1.0)
    assert (t.R, t.R99, t.R_position) == (5.0, 5.0, 5.0)
    assert t.per_sample.tolist() == [5.0, 1.0]
    # about the mean nominal (all zero here): the same
    assert t.R_mean_nominal == 5.0


def test_disturbance_bound_and_d_f():
    dt, var = 0.02, 10.0
    D = disturbance_bound(Disturbance(var), dt)
    assert D == pytest.approx(3.717 * dt * np.sqrt(var), rel=1e-3)
    assert D == pytest.approx(dt * np.sqrt(var) * np.sqrt(-2 * np.log(1e-3)), rel=1e-12)
    assert d_f([0, 0, 0, 0, 9], [3, 4, 0, 0, 1], [0, 0, 1, 0, 5], D, 4) == pytest.approx(6 + D)


def _step(F_real, F_nom, E, R, Lq, Lphi, gap, alpha=10.0, D_F=2.0, n_q=3,
          sampled=(0.1, 0.2, 0.15)) -> BoundStep:
    fe = [FreeEnergy(value=v, E=E, sd=0.0, bias=0.0, ess=1.0, n=2, method="delta", z=3.0)
          for v in (F_real, F_nom)]
    L = Lipschitz(L_q=Lq, L_phi=Lphi, secant_q=0.0, secant_phi=0.0, points_q=0, points_phi=0,
                  excluded_q=0, excluded_phi=0)
    return BoundStep(lam=1.0, alpha=alpha, F_real=fe[0], F_nom=fe[1], F_real_code=F_real,
                     F_nom_code=F_nom, E=E, E_bootstrap=np.nan,
                     tube=Tube(R=R, R99=R, R_position=R, R_mean_nominal=R, per_sample=np.zeros(1)),
                     local=L, global_=replace(L, L_q=10 * Lq), n_q=n_q, D=0.1, D_F=D_F,
                     t1_gap=gap, t1_gap_safe=gap, n_samples=4, n_crashed_real=0, n_crashed_nom=0,
                     fallback_used=False, nominal_differs=True, delta_sampled=sampled[0],
                     delta_sampled_max=sampled[1], delta_sampled_max_safe=sampled[2])


def test_checks_follow_spec_11_3():
    s0 = _step(F_real=5.5, F_nom=4.0, E=0.5, R=0.1, Lq=2.0, Lphi=4.0, gap=-0.5)
    s1 = _step(F_real=8.0, F_nom=7.0, E=0.25, R=0.2, Lq=1.0, Lphi=1.0, gap=0.0, alpha=9.0)
    d0, d1 = (4.0 + 3 * 2.0) * 0.1, (1.0 + 3 * 1.0) * 0.2
    c = {(x.test, x.constants): x for x in step_checks(s0) + transition_checks(s0, s1)}
    assert c["T1", "local"].slack == pytest.approx(d0 - 0.5)
    assert c["T2", "local"].slack == pytest.approx(4.0 + d0 - 5.5)
    assert c["T3", "local"].rhs == pytest.approx(10 - 4 + 1.0 + d0 * 2.0)
    assert c["T3", "local"].lhs == pytest.approx(2.5)
    assert c["T3b", "local"].rhs == pytest.approx(10 - 4 + 1.0 + d0)
    assert c["T3c", "local"].rhs == pytest.approx(10 - 7 + 1.0 + d0 * 2.0)
    assert c["T3d", "local"].rhs == pytest.approx(9.0 + d1 + 1.0)
    assert c["T3d", "local"].holds and not c["T2", "local"].holds
    dg = (4.0 + 3 * 20.0) * 0.1
    assert c["T1", "global"].rhs == pytest.approx(dg)
    assert len(episode_checks([s0, s1, s0])[0]) == 3 * 7
    # the sampled-tube bound: max_n δ_n in T1, its safe-pair maximum in T1s, δ_λ elsewhere
    assert c["T1", "sampled"].rhs == pytest.approx(0.2)
    assert c["T1s", "sampled"].rhs == pytest.approx(0.15)
    assert c["T2", "sampled"].rhs == pytest.approx(4.0 + 0.1)
    assert c["T3", "sampled"].rhs == pytest.approx(10 - 4 + 1.0 + 0.1 * 2.0)
    assert c["T3d", "sampled"].rhs == pytest.approx(9.0 + 0.1 + 1.0)


def test_summary_counts_fractions_and_ratios():
    s0 = _step(F_real=5.5, F_nom=4.0, E=0.5, R=0.1, Lq=2.0, Lphi=4.0, gap=-0.5)
    s1 = _step(F_real=7.5, F_nom=7.0, E=0.25, R=0.2, Lq=1.0, Lphi=1.0, gap=0.0, alpha=9.0)
    s1 = replace(s1, fallback_used=True, n_crashed_real=3)
    rows = {(r.test, r.constants, r.stratum): r for r in summarize([s0, s1])}
    t2 = rows["T2", "local", "all"]  # fails at s0 (slack -0.5), holds at s1 (slack 0.3)
    assert (t2.n_steps, t2.n_holding, t2.fraction_holding) == (2, 1, 0.5)
    assert t2.interval[0] < 0.5 < t2.interval[1]
    assert rows["T2", "local", "fallback"].n_steps == 1
    assert rows["T3", "local", "all"].n_steps == 1  # one transition
    assert ("T1", "local", "nominal_is_real") not in rows  # both steps: nominal differs
    g = rows["T1", "global", "all"]  # global L_q = 10 x local (see _step)
    assert g.term_ratio == pytest.approx(np.median([(4 + 3 * 20) / (4 + 3 * 2),
                                                    (1 + 3 * 10) / (1 + 3 * 1)]))
    assert np.isnan(rows["T1", "local", "all"].term_ratio)
    assert g.as_dict()["interval"] == list(g.interval)
    with pytest.raises(ValueError, match="strata = "):
        summarize([s0], strata=("bogus",))


# ----------------------------------------------------------------------------------------------
# Diagnostic kernels against the twins
# ----------------------------------------------------------------------------------------------

OBST = (Circle((2.0, 2.0), 0.8), Circle((3.5, 1.0), 0.5), Circle((1.0, 3.2), 0.6))
RTOL, FLOOR = 1e-10, 1.0  # as the sampler-kernel tests: relative, absolute below 1


def rel_err(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    assert a.shape == b.shape and np.all(np.isfinite(a)) and np.all(np.isfinite(b))
    return float(np.max(np.abs(a - b) / np.maximum(np.maximum(np.abs(a), np.abs(b)), FLOOR)))


@pytest.fixture(scope="module")
def scene():
    """Starts 0.9 m off the line through the first obstacle, heading along it at 2 m/s: over
    T = 30 steps most samples pass, some crash; real and nominal starts differ; gains random
    with a beta column; N = 125 is not a multiple of the lane count."""
    model = embed_barrier(double_integrator(obstacles=OBST, u_limit=5.0))
    sp = navigation_costs(model)
    sampler = Sampler(sp, backend="compiled")
    rng = np.random.default_rng(2026)
    side, head = np.array([-1.0, 1.0]) / np.sqrt(2.0), np.array([1.0, 1.0]) * np.sqrt(2.0)
    x0 = model.lift([*(np.array([1.0, 1.0]) + 0.9 * side), *head])
    xs0 = model.lift([*(np.array([0.95, 0.95]) + 0.9 * side), *(head + np.array([0.1, -0.1]))])
    T = 30
    U = rng.normal(0.0, 2.0, (T, 2))
    K = np.zeros((T, 2, 5))
    K[:, 0, 0] = K[:, 1, 1] = -2.0
    K[:, 0, 2] = K[:, 1, 3] = -1.5
    K += rng.normal(0.0, 0.5, K.shape)
    K[:, :, 4] = rng.normal(0.0, 0.3, (T, 2))
    c = SamplerConstants(sigma=np.array([3.0, 2.4]), lam=1.3, nu_mix=0.1, u_min=model.u_min,
                         u_max=model.u_max, crash_cost=1e6, p=model.lift((4.0, 4.0, 0.0, 0.0)),
                         alpha=300.0)
    return sp, sampler, x0, xs0, U, K, c


def test_diagnostic_kernel_matches_the_twin_and_the_plain_kernel(scene):
    sp, sampler, x0, xs0, U, K, c = scene
    N, seed = 125, 11
    b = sampler.sais(x0, xs0, U, K, N, c, seed, diagnostics=True)
    plain = sampler.sais(x0, xs0, U, K, N, c, seed)
    assert isinstance(b, SAISDiagBatch) and type(plain) is not SAISDiagBatch
    for f in ("S_nom", "S_real", "S_state_nom", "S_hat", "LR", "crashed_real", "crashed_nom",
              "v_nom", "v_real"):
        assert np.array_equal(getattr(b, f), getattr(plain, f)), f  # bitwise
    Z = np.transpose(sampler.lib.normals(N, U.shape[0], 2, seed), (2, 0, 1))
    ref = sais_twin(sp, np.tile(x0, (N, 1)), np.tile(xs0, (N, 1)), U, K, Z, c,
                    pure_costs=True)
    lm = lambda a: np.transpose(a, (1, 2, 0))  # noqa: E731
    assert rel_err(b.X, lm(ref["X"])) <= RTOL
    assert rel_err(b.X_nom, lm(ref["X_nom"])) <= RTOL
    assert rel_err(b.Sx_real, ref["Sx_real"]) <= RTOL
    assert rel_err(b.Sx_nom, ref["Sx_nom"]) <= RTOL
    # the scene reaches the branches: crashes of real-only and nominal-only samples
    assert 0 < b.crashed_real.sum() < N and np.any(b.crashed_real != b.crashed_nom)
    # pure state costs exclude the crash cost: S_state_nom - Sx_nom is C_crash x crashed steps
    extra = (b.S_state_nom - b.Sx_nom) / c.crash_cost
    assert np.allclose(extra, np.round(extra), atol=1e-6)
    assert np.all((extra > 0.5) == b.crashed_nom)
    # the reading of workbench.bound.lipschitz: on every sample beta_k = B(h(p_k)) exactly
    # (gamma = 0), so the state costs are functions of the physical state
    lift = sp.model.lift_function.map("lift", "serial", N * (U.shape[0] + 1), [1], [])
    for Xb in (b.X, b.X_nom):
        Y = np.transpose(Xb, (0, 2, 1)).reshape(-1, sp.nx)
        assert np.array_equal(np.asarray(lift(Y[:, :4].T, sp.model.scene_value)).T, Y)
    # the NumPy backend's diagnostic batch has the same shapes and pure costs (its own noise)
    nb = Sampler(sp, backend="numpy").sais(x0, xs0, U, K, 7, c, seed, diagnostics=True)
    assert nb.X.shape == (U.shape[0] + 1, sp.nx, 7) and nb.Sx_real.shape == (7,)


def test_gradient_kernel_matches_the_casadi_twin(scene):
    sp, sampler, x0, xs0, U, K, c = scene
    b = sampler.sais(x0, xs0, U, K, 61, c, 5, diagnostics=True)
    Lk = CostGradients(sp, backend="compiled").local(b.X, b.X_nom, c.p)
    Lr = CostGradients(sp, backend="numpy").local(b.X, b.X_nom, c.p)
    for f in ("L_q", "L_phi", "secant_q", "secant_phi"):
        assert rel_err(getattr(Lk, f), getattr(Lr, f)) <= RTOL, f
    assert Lk.excluded_q == Lr.excluded_q > 0 and Lk.points_q == Lr.points_q
    # the barrier term makes the local constant large near obstacles
    assert Lk.L_q > 1e3


def test_augmented_space_constants_are_the_analytic_ones(scene):
    """With beta as a coordinate q is quadratic in x̄ = [p, v, beta]: no barrier term in ∇q."""
    sp, sampler, x0, xs0, U, K, c = scene
    b = sampler.sais(x0, xs0, U, K, 61, c, 5, diagnostics=True)
    La = CostGradients(sp, backend="compiled", space="augmented").local(b.X, b.X_nom, c.p)
    Lr = CostGradients(sp, backend="numpy", space="augmented").local(b.X, b.X_nom, c.p)
    for f in ("L_q", "L_phi", "secant_q", "secant_phi"):
        assert rel_err(getattr(La, f), getattr(Lr, f)) <= RTOL, f
    w = sp.weights
    Wq = 2 * np.array([*w["Qp"], *w["Qv"], w["q_beta"]])
    best = 0.0
    for s in (0, .25, .5, .75, 1):
        P = b.X_nom[1:] + s * (b.X[1:] - b.X_nom[1:])  # (T, 5, N)
        h = np.min([(P[:, 0] - o.center[0]) ** 2 + (P[:, 1] - o.center[1]) ** 2 - o.radius ** 2
                    for o in OBST], axis=0)
        g = np.linalg.norm(Wq[None, :, None] * (P - c.p[None, :, None]), axis=1)
        best = max(best, float(np.where(h > 0, g, 0.0).max()))
    assert La.L_q == pytest.approx(best, rel=1e-12)
    assert La.secant_ok
    # R in the augmented norm includes the beta differences
    assert tube_radius(b.X, b.X_nom, sp.nx).R >= tube_radius(b.X, b.X_nom, 4).R


# ----------------------------------------------------------------------------------------------
# SA-RMPPI on the navigation map
# ----------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def nav_small():
    """The assumptions §3.2 map with a smaller batch (N = 256, T = 50, sigma = 2) so that real
    samples stay safe on some steps; alpha = 0 makes every selection fall back to the propagated
    nominal, so the nominal state differs from the real one after the first step."""
    nav = navigation_setup()
    nav = replace(nav, mppi=MPPIConfig(n_samples=256, horizon=50, sigma=(2.0, 2.0), lam=10.0))
    ctrl = RobustMPPI(nav.problem, nav.goal, nav.mppi, RMPPIConfig(alpha=0.0),
                      nav.feedback("bas_ilqg"))
    return nav, ctrl


def test_diagnostics_leave_the_controller_unchanged(nav_small):
    nav, ctrl = nav_small
    diag = RobustMPPI(nav.problem, nav.goal, nav.mppi, RMPPIConfig(alpha=0.0, diagnostics=True),
                      nav.feedback("bas_ilqg"))
    args = (nav.plant, nav.x0, 4, np.random.default_rng(0))
    a = closed_loop(ctrl, *args, np.random.default_rng(1), Disturbance(10.0))
    b = closed_loop(diag, nav.plant, nav.x0, 4, np.random.default_rng(0),
                    np.random.default_rng(1), Disturbance(10.0))
    assert np.array_equal(a.X, b.X) and np.array_equal(a.U, b.U)
    assert all(i.batch is None for i in a.infos)
    assert all(isinstance(i.batch, SAISDiagBatch) for i in b.infos)
    # first_batch replays a step without advancing the caller's generator
    state = ctrl.initial_state(nav.x0)
    rng = np.random.default_rng(9)
    before = rng.bit_generator.state
    batch, _, u, _ = first_batch(ctrl, state, nav.x0, rng)
    assert rng.bit_generator.state == before
    _, u2, info2 = diag.step(state, nav.x0, rng)
    assert np.array_equal(u, u2) and np.array_equal(batch.Sx_real, info2.batch.Sx_real)


def test_t1_holds_on_navigation_steps_where_all_real_samples_stay_safe(nav_small):
    """T1 with local and global constants on SA-RMPPI steps (variance 10) where every real
    sample stayed safe and the nominal state differed from the real one. Steps where some real
    samples crash can fail T1: a crashed sample carries beta_max = 1e6 in its state cost, its
    segment crosses an obstacle (those points are excluded), so no Lipschitz step applies;
    T1 over the samples that stayed safe (T1s) holds there. Both readings of the norm."""
    nav, ctrl = nav_small
    est = BoundEstimator(ctrl, Disturbance(10.0))
    rec = BoundRecorder(est)
    closed_loop(rec, nav.plant, nav.x0, 6, np.random.default_rng(0), np.random.default_rng(1),
                Disturbance(10.0), keep_infos=False)
    # the same steps in the augmented reading (beta a coordinate): replay on the same seeds
    aug = BoundRecorder(BoundEstimator(ctrl, Disturbance(10.0), BoundConfig(space="augmented")))
    closed_loop(aug, nav.plant, nav.x0, 6, np.random.default_rng(0), np.random.default_rng(1),
                Disturbance(10.0), keep_infos=False)
    assert est.global_.L_q >= max(s.local.L_q for s in rec.records)
    checked = 0
    for s, sa in zip(rec.records, aug.records, strict=True):
        assert sa.t1_gap == s.t1_gap and sa.tube.R >= s.tube.R
        for r in (s, sa):
            c = {(x.test, x.constants): x for x in step_checks(r)}
            assert c["T1s", "local"].holds and c["T1s", "global"].holds
            if r.all_real_safe and r.nominal_differs:
                assert r.tube.R > 0 and r.delta() > 0
                assert c["T1", "local"].holds and c["T1", "global"].holds
                assert c["T1", "global"].rhs >= c["T1", "local"].rhs
                checked += 1
    assert checked >= 2


def test_independent_batch_gives_t2e(nav_small):
    """A second batch of the same step (same inputs, other seed) feeds T2E; same seed refused."""
    nav, ctrl = nav_small
    unit = Lipschitz(L_q=1.0, L_phi=1.0, secant_q=0.0, secant_phi=0.0, points_q=0, points_phi=0,
                     excluded_q=0, excluded_phi=0)  # skip the global grid
    est = BoundEstimator(ctrl, Disturbance(10.0), BoundConfig(bootstrap=200),
                         global_constant=unit)
    state = ctrl.initial_state(nav.x0)
    batch, info, u, _ = first_batch(ctrl, state, nav.x0, np.random.default_rng(3))
    other = independent_batch(ctrl, batch, batch.seed + 1)
    assert np.array_equal(other.U, batch.U) and not np.array_equal(other.Sx_real, batch.Sx_real)
    with pytest.raises(ValueError, match="seed = "):
        independent_batch(ctrl, batch, batch.seed)
    with pytest.raises(ValueError, match="rng = "):
        est.step(batch, info, nav.x0, u)
    s = est.step(batch, info, nav.x0, u, np.random.default_rng(4), independent=other)
    assert np.isfinite(s.E_bootstrap) and s.E_bootstrap > 0
    c = {(x.test, x.constants): x for x in step_checks(s)}
    assert ("T2E", "local") in c and np.isfinite(s.F_nom_ind)
    assert c["T2E", "local"].rhs == pytest.approx(s.F_nom_ind + s.delta() + 2 * max(s.E, s.E_ind))
    assert ("T2E", "local") not in {(x.test, x.constants) for x in step_checks(replace(
        s, F_nom_ind=np.nan))}


# ----------------------------------------------------------------------------------------------
# Bad input
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("S, word", [
    (np.zeros(0), "empty"),
    (np.array([1.0, np.inf, 2.0]), "non-finite"),
    (np.array([1.0, np.nan]), "non-finite"),
    (np.zeros((2, 3)), "1-D"),
    (np.array([1.0]), "at least 2"),
])
def test_free_energy_rejects_bad_costs(S, word):
    with pytest.raises(ValueError, match=r"^S = .*" + word):
        free_energy_estimate(S, 1.0)


def test_estimators_reject_bad_shapes_and_values(quadratic, scene):
    _, grads, g = quadratic
    X = np.zeros((5, 4, 3))
    with pytest.raises(ValueError, match=r"X_nom .* must match X"):
        tube_radius(X, np.zeros((5, 4, 2)), 4)
    with pytest.raises(ValueError, match=r"X = .*empty"):
        tube_radius(np.zeros((5, 4, 0)), np.zeros((5, 4, 0)), 4)
    with pytest.raises(ValueError, match=r"X = .*trajectories must be finite"):
        tube_radius(np.full((5, 4, 3), np.nan), X, 4)
    with pytest.raises(ValueError, match=r"X = .*expected \(T\+1, 4, N\)"):
        grads.local(np.zeros((5, 5, 3)), np.zeros((5, 5, 3)), g)
    with pytest.raises(ValueError, match="p = "):
        grads.local(X, X, g[:2])
    with pytest.raises(ValueError, match="lam = "):
        free_energy_lse([1.0, 2.0], 0.0)
    with pytest.raises(ValueError, match="n_resamples = "):
        bootstrap_free_energy([1.0, 2.0], 1.0, np.random.default_rng(0), 1)
    with pytest.raises(ValueError, match=r"LipschitzGrid.spacing = "):
        LipschitzGrid(spacing=0.0)
    _, sampler, x0, xs0, U, K, c = scene
    b = sampler.sais(x0, xs0, U, K, 8, c, 1, diagnostics=True)
    with pytest.raises(ValueError, match=r"batch.Sx_real = .*expected \(8,\)"):
        check_batch(replace(b, Sx_real=b.Sx_real[:5]))
    with pytest.raises(ValueError, match=r"batch.LR = .*non-finite"):
        check_batch(replace(b, LR=np.where(np.arange(8) == 3, np.nan, b.LR)))
    with pytest.raises(ValueError, match=r"batch = .*SAISDiagBatch"):
        check_batch(sampler.sais(x0, xs0, U, K, 8, c, 1))


@pytest.mark.parametrize(("make", "message"), [
    (lambda: BoundConfig(bootstrap=True), "BoundConfig.bootstrap = True is invalid: must be an "
                                          "integer"),
    (lambda: BoundConfig(z=True), "BoundConfig.z = True is invalid: must be a finite number > 0"),
    (lambda: LipschitzGrid(n_v=True), "LipschitzGrid.n_v = True is invalid: must be an integer"),
    (lambda: LipschitzGrid(spacing=True), "LipschitzGrid.spacing = True is invalid: must be a "
                                          "finite number > 0"),
    (lambda: tube_radius(np.zeros((3, 4, 2)), np.zeros((3, 4, 2)), True),
     "physical = True is invalid: must be an integer in [1, 4]"),
])
def test_bool_is_neither_an_integer_nor_a_real(make, message):
    with pytest.raises(ValueError, match="^" + re.escape(message)):
        make()

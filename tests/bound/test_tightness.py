"""Tightness of Lemma 1's checks and the sampled-tube bound (assumptions §11.4).

The closed-form case: a double integrator without obstacles and an isotropic quadratic cost
q = w |x − g|², φ = s |x − g|², every nominal sample at the goal and every real sample at
distance r_n from it at every step. Then G^q_nk = 2 w r_n, G^φ_n = 2 s r_n, the local constants
are L_q = 2 w R, L_φ = 2 s R (R = max r_n), S_n − S*_n = c r_n² with c = T w + s, and so
δ = (L_φ + T L_q) R = 2 c R² (T1's ratio is exactly 2), δ_n = 2 c r_n², and with equal
nominal costs F̂_real = −λ log mean exp(−c r_n²/λ), δ_λ = −λ log mean exp(−2 c r_n²/λ).
"""

from __future__ import annotations

import numpy as np
import pytest

from workbench.bound import CostGradients, LipschitzGrid, step_checks, tube_radius
from workbench.bound.free_energy import free_energy_estimate
from workbench.bound.step import BoundStep, sampled_deltas
from workbench.bound.tightness import (
    QUANTILES,
    THRESHOLDS,
    Comparison,
    Tightness,
    informative,
    median_interval,
    ratios,
)
from workbench.problem.models import double_integrator
from workbench.sampling.problem import navigation_costs

W, S_T, LAM, T, N = 0.5, 3.0, 10.0, 12, 64
G = np.array([4.0, 3.0, 0.0, 0.0])
RTOL = 1e-9


@pytest.fixture(scope="module")
def isotropic():
    sp = navigation_costs(double_integrator(obstacles=(), u_limit=5.0), Qp=(W, W), Qv=(W, W),
                          S=(S_T,) * 4)
    return CostGradients(sp, backend="compiled")


def _batch(rng: np.random.Generator, scale: float):
    """Nominal samples at the goal; real samples at distance r_n (random directions)."""
    r = scale * rng.uniform(0.2, 1.0, N)
    u = rng.normal(size=(T + 1, 4, N))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    Xn = np.repeat(G[None, :, None], N, axis=2).repeat(T + 1, axis=0)
    return Xn + r[None, None, :] * u, Xn, r


def _costs(grads: CostGradients, X) -> np.ndarray:
    """S^x_n = Σ_{k=1..T} q(x_k) + φ(x_T), from the problem's own cost function."""
    Y = np.transpose(X, (0, 2, 1)).reshape(-1, 4)
    v = grads.at_points(Y, G)
    q, phi = v["q"].reshape(T + 1, N), v["phi"].reshape(T + 1, N)
    return q[1:].sum(axis=0) + phi[-1]


def _record(grads: CostGradients, X, Xn, global_, n_q: int = T) -> BoundStep:
    seg = grads.segments(X, Xn, G)
    Sr, Sn = _costs(grads, X), _costs(grads, Xn)
    soft, dmax, dmax_s = sampled_deltas(seg, Sn, LAM)
    Fr, Fn = (free_energy_estimate(S, LAM) for S in (Sr, Sn))
    local = seg.lipschitz()
    return BoundStep(
        lam=LAM, alpha=0.0, F_real=Fr, F_nom=Fn, F_real_code=Fr.value, F_nom_code=Fn.value,
        E=0.0, E_bootstrap=np.nan, tube=tube_radius(X, Xn, 4), local=local, global_=global_,
        n_q=n_q, D=0.0, D_F=1.0, t1_gap=float(np.min(Sn - Sr)), t1_gap_safe=float(np.min(Sn - Sr)),
        n_samples=N, n_crashed_real=0, n_crashed_nom=0, fallback_used=False,
        nominal_differs=True, delta_sampled=soft, delta_sampled_max=dmax,
        delta_sampled_max_safe=dmax_s)


def _sides(records, test, constants):
    cs = [next(c for c in step_checks(s) if (c.test, c.constants) == (test, constants))
          for s in records]
    return np.array([c.lhs for c in cs]), np.array([c.rhs for c in cs])


def _closed_form(rs, grid_L=None):
    """Per step: T1 and T2 ratios, local and sampled (and global T1 given (L_q, L_φ))."""
    c = T * W + S_T
    out = {}
    R = np.array([r.max() for r in rs])
    Fr = np.array([-LAM * np.log(np.mean(np.exp(-c * r**2 / LAM))) for r in rs])
    soft = np.array([-LAM * np.log(np.mean(np.exp(-2 * c * r**2 / LAM))) for r in rs])
    out["T1", "local"] = out["T1", "sampled"] = np.full(len(rs), 2.0)
    out["T2", "local"] = 2 * c * R**2 / Fr
    out["T2", "sampled"] = soft / Fr
    if grid_L is not None:
        out["T1", "global"] = (grid_L[1] + T * grid_L[0]) * R / (c * R**2)
    return out


def _agrees(got, want) -> bool:
    got, want = np.asarray(got, float), np.asarray(want, float)
    return got.shape == want.shape and bool(np.all(np.abs(got - want) <= RTOL * np.abs(want)))


def test_tightness_ratios_equal_the_closed_form_of_a_quadratic_cost(isotropic):
    rng = np.random.default_rng(11)
    grid = LipschitzGrid(x_range=(0.0, 10.0), y_range=(-1.0, 8.0), spacing=0.5, v_max=3.0)
    glob = isotropic.global_constant(grid, G)
    corners = np.array([[x, y, v, v] for x in (0.0, 10.0) for y in (-1.0, 8.0)
                        for v in (-3.0, 3.0)]) - G
    far = np.linalg.norm(corners, axis=1).max()
    assert _agrees([glob.L_q, glob.L_phi], [2 * W * far, 2 * S_T * far])
    batches = [_batch(rng, s) for s in (0.05, 0.3, 1.0, 2.0)]
    recs = [_record(isotropic, X, Xn, glob) for X, Xn, _ in batches]
    want = _closed_form([r for *_, r in batches], (glob.L_q, glob.L_phi))
    for (test, c), w in want.items():
        lhs, rhs = _sides(recs, test, c)
        got = ratios(lhs, rhs)
        assert _agrees(got, w), (test, c)
        t = Tightness.of(lhs, rhs, np.ones(len(lhs)))
        assert _agrees(t.ratio_quantiles, [np.quantile(w, q) for q in QUANTILES])
        assert t.n == len(w) and t.n_holding == len(w) and t.n_lhs_nonpositive == 0
        # (T1's ratio is 2 to rounding: count with the computed ratios at the thresholds)
        assert t.n_informative == tuple(int(np.sum((got >= 1) & (got <= x))) for x in THRESHOLDS)
    # the sampled-tube bound is never looser than the paper's form, here strictly tighter in T2
    assert np.all(want["T2", "sampled"] < want["T2", "local"])
    # a broken copy (the paper's T − 1 running terms in δ) does not reproduce the closed form
    broken = [_record(isotropic, X, Xn, glob, n_q=T - 1) for X, Xn, _ in batches]
    lhs, rhs = _sides(broken, "T1", "local")
    assert not _agrees(ratios(lhs, rhs), want["T1", "local"])


def test_segments_give_the_local_constants_and_per_sample_products(isotropic):
    rng = np.random.default_rng(5)
    X, Xn, _ = _batch(rng, 0.7)
    Xn = Xn + rng.normal(0.0, 0.2, Xn.shape)  # nominal samples off the goal too
    seg = isotropic.segments(X, Xn, G)
    assert seg.lipschitz() == isotropic.local(X, Xn, G)
    twin = CostGradients(isotropic.sp, backend="numpy").segments(X, Xn, G)
    for name in ("grad_q", "grad_phi", "secant_q", "secant_phi", "excluded", "distance"):
        a, b = getattr(seg, name), getattr(twin, name)
        assert np.all(np.abs(a - b) <= 1e-10 * np.maximum(np.abs(b), 1.0)), name
    # per sample: Σ_k G_nk ‖e_nk‖ <= the paper's δ, and S_n − S*_n <= δ_n (quadratic: exact sup)
    seg_d = seg.products()
    L = seg.lipschitz()
    R = tube_radius(X, Xn, 4).R
    assert np.all(seg_d <= (L.L_phi + T * L.L_q) * R * (1 + 1e-12))
    gap = _costs(isotropic, X) - _costs(isotropic, Xn)
    assert np.all(gap <= seg_d * (1 + 1e-12))


def test_ratios_set_nonpositive_left_sides_apart():
    lhs = np.array([2.0, 0.0, -1.0, 1.0, 4.0])
    rhs = np.array([3.0, 5.0, 1.0, 50.0, 2.0])
    r = ratios(lhs, rhs)
    assert np.isnan(r[1]) and np.isnan(r[2])
    assert _agrees(r[[0, 3, 4]], [1.5, 50.0, 0.5])
    # informative at c: holds and within a factor c; a failing bound (ratio 0.5) is not
    assert informative(lhs, rhs, 10.0).tolist() == [True, False, False, False, False]
    t = Tightness.of(lhs, rhs, np.array([1.0, 1.0, 1.0, 1.0, 0.0]))  # last step: R = 0
    assert (t.n, t.n_lhs_nonpositive, t.n_holding) == (4, 2, 4)
    assert t.n_informative == (1, 1, 2) and t.share(100.0) == 0.5
    assert t.ratio_median == pytest.approx(np.median([1.5, 50.0]), rel=1e-12)
    with pytest.raises(ValueError, match="R = "):
        Tightness.of(lhs, rhs, -np.ones(5))
    with pytest.raises(ValueError, match="c = "):
        t.share(3.0)


def test_median_interval_is_the_sign_test_interval_and_covers():
    lo_hi = median_interval(np.arange(100.0))
    assert lo_hi == (49.5, 39.0, 60.0)  # P(Bin(100, ½) <= 39) = 0.018 <= 0.025 < P(<= 40)
    assert median_interval(np.ones(5))[1:] == (-np.inf, np.inf)
    rng = np.random.default_rng(7)
    hits = 0
    for _ in range(2000):
        _, lo, hi = median_interval(rng.exponential(1.0, 25))
        hits += lo <= np.log(2.0) <= hi
    assert hits / 2000 >= 0.95 - 3 * np.sqrt(0.05 * 0.95 / 2000)


def test_comparison_decides_by_the_paired_interval():
    n = 400
    lhs, R = np.ones(n), np.ones(n)
    tight, loose = np.full(n, 3.0), np.full(n, 1e6)
    better = Comparison.of(lhs, tight, loose, R)
    assert better.verdict == "better" and better.only_a == n and better.low > 0
    assert better.rhs_ratio == pytest.approx(1e6 / 3.0, rel=1e-12)
    assert Comparison.of(lhs, loose, tight, R).verdict == "worse"
    same = Comparison.of(lhs, tight, tight * 1.5, R)
    assert same.verdict == "equivalent" and same.difference == 0.0
    few = Comparison.of(lhs[:6], np.r_[tight[:3], loose[:3]], loose[:6], R[:6])
    assert few.verdict == "undecided"
    with pytest.raises(ValueError, match="R = "):
        Comparison.of(lhs, tight, loose, np.zeros(n))
    with pytest.raises(ValueError, match="margin = "):
        Comparison.of(lhs, tight, loose, R, margin=2.0)


def test_sampled_deltas_weights_and_order():
    """δ_λ = −λ log Σ w*_n e^{−δ_n/λ} <= Σ w*_n δ_n <= max δ_n, by hand on three samples."""

    class Seg:
        def products(self):
            return np.array([1.0, 4.0, 9.0])

    S = np.array([0.0, 1.0, 3.0])
    w = np.exp(-S / 2.0) / np.exp(-S / 2.0).sum()
    soft, dmax, dsafe = sampled_deltas(Seg(), S, 2.0, safe=[True, True, False])
    assert soft == pytest.approx(-2.0 * np.log(np.sum(w * np.exp(-np.array([1, 4, 9]) / 2.0))),
                                 rel=1e-12)
    assert soft <= float(np.sum(w * [1, 4, 9])) <= dmax == 9.0 and dsafe == 4.0
    with pytest.raises(ValueError, match="safe = "):
        sampled_deltas(Seg(), S, 2.0, safe=[True])

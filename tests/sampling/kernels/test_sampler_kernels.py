"""Generated sampler kernels against the NumPy twin fed the same noise.

Every output is compared element by element with a relative tolerance (:data:`RTOL`), on scenes
where most samples stay safe, some crash (real only, nominal only, both), controls clip at both
bounds, the SAIS feedback gains are nonzero (barrier-state column included) and alpha binds on
some samples only. The tests count that their inputs reach each of these branches, and a
mutation check shows the comparison fails when the twin drops the feedback term, a
likelihood-ratio term or the alpha clamp of Algorithm 1 (assumptions §10.1).

Kernels are called through :class:`workbench.sampling.sampler.Sampler` only; the twin gets the
kernel's noise from ``lib.normals`` (the kernel draws it from the same seed).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pytest
from scipy import stats

from workbench.problem.barrier import embed_barrier
from workbench.problem.models import double_integrator
from workbench.problem.obstacles import Circle
from workbench.sampling.kernels.constants import SamplerConstants
from workbench.sampling.problem import navigation_costs
from workbench.sampling.sampler import Sampler
from workbench.sampling.twin import mppi_twin, sais_twin
from workbench.sampling.twin_model import NumpyModelTwin, model_twin

OBST = (Circle((2.0, 2.0), 0.8), Circle((3.5, 1.0), 0.5), Circle((1.0, 3.2), 0.6))
N, T = 125, 30  # N not a multiple of the lane count (4): padding is exercised
GOAL = (4.0, 4.0, 0.0, 0.0)
# Per element: |a - b| <= RTOL * max(|a|, |b|, FLOOR). Kernel and twin evaluate the same
# formulas in a different order (and gcc may contract a*b + c into FMAs), so they differ by
# rounding only: measured <= 3e-14 relative against the plain-NumPy model (it sums the inverse
# barrier 1/h_i in another order than the kernel's pairwise form, and the beta column of K
# carries that into the controls), <= 2e-15 against the CasADi-VM model. FLOOR = 1 makes the
# test absolute, at 1e-10 (cost units; m/s^2 for controls), for values below 1 in magnitude:
# LR and S_real are sums of T terms of size up to ~10 that can cancel, and controls pass near
# 0, so their rounding error scales with the terms (~1e-14), not with the result. The smallest
# effect of a mutated twin below is ~1e-3 relative on costs of ~1e3.
RTOL, FLOOR = 1e-10, 1.0
SAIS_COSTS = ("S_nom", "S_real", "S_state_nom", "S_hat", "LR")
SAIS_FLAGS = ("crashed_real", "crashed_nom")
SAIS_LANES = ("v_nom", "v_real")


def rel_err(a, b) -> float:
    """Largest per-element mismatch |a - b| / max(|a|, |b|, FLOOR); 0 for identical arrays."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    assert a.shape == b.shape
    assert np.all(np.isfinite(a)) and np.all(np.isfinite(b))
    return float(np.max(np.abs(a - b) / np.maximum(np.maximum(np.abs(a), np.abs(b)), FLOOR)))


def lane_major(v) -> np.ndarray:
    """Twin arrays (N, T, nu) in the kernels' lane-major layout (T, nu, N)."""
    return np.transpose(v, (1, 2, 0))


@pytest.fixture(scope="module")
def setup():
    model = embed_barrier(double_integrator(obstacles=OBST, u_limit=5.0))
    sp = navigation_costs(model)
    sampler = Sampler(sp, backend="compiled")
    consts = SamplerConstants(sigma=np.array([3.0, 2.4]), lam=1.3, nu_mix=0.1,
                              u_min=model.u_min, u_max=model.u_max, crash_cost=1e6,
                              p=model.lift(GOAL))
    return model, sp, sampler, consts


def kernel_noise(sampler: Sampler, N: int, T: int, seed: int) -> np.ndarray:
    """The standard normals the kernels draw for ``seed``, sample-major (N, T, nu) for the twin."""
    return np.transpose(sampler.lib.normals(N, T, sampler.sp.nu, seed), (2, 0, 1))


# ----------------------------------------------------------------------------------------------
# SAIS (Algorithm 1)
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SAISCase:
    x0: np.ndarray
    xs0: np.ndarray
    U: np.ndarray
    K: np.ndarray
    Z: np.ndarray
    seed: int
    c: SamplerConstants


def sais_case(model, sampler, consts) -> SAISCase:
    """Real and nominal starts about 0.9 m off the line through the first obstacle's centre,
    both heading along it at 2 m/s: over T = 30 steps (0.6 s) most samples pass the obstacle,
    some hit it. The nominal start is slightly off the real one (position, velocity and so
    barrier state), so the feedback K_k (x - x*) acts from the first step; gains are a
    PD-like law with random entries and a random barrier-state column. U ~ N(0, 2^2) with
    sigma = (3, 2.4) puts some controls on each bound of |u| <= 5."""
    rng = np.random.default_rng(2026)
    side = np.array([-1.0, 1.0]) / np.sqrt(2.0)  # unit normal to the diagonal
    heading = np.array([1.0, 1.0]) * np.sqrt(2.0)  # 2 m/s along the diagonal
    x0 = model.lift([*(np.array([1.0, 1.0]) + 0.9 * side), *heading])
    xs0 = model.lift([*(np.array([0.95, 0.95]) + 0.9 * side), *(heading + np.array([0.1, -0.1]))])
    U = rng.normal(0.0, 2.0, (T, 2))
    K = np.zeros((T, 2, 5))
    K[:, 0, 0] = K[:, 1, 1] = -2.0
    K[:, 0, 2] = K[:, 1, 3] = -1.5
    K += rng.normal(0.0, 0.5, K.shape)
    K[:, :, 4] = rng.normal(0.0, 0.3, (T, 2))  # feedback on the barrier state beta
    seed = 7
    Z = kernel_noise(sampler, N, T, seed)
    # alpha: halfway between the two middle S_hat of the samples whose real and nominal
    # rollouts are both safe (S_hat does not depend on alpha), so the clamp binds on about
    # half of them and no sample sits on alpha
    free = sais_twin(sampler.sp, np.tile(x0, (N, 1)), np.tile(xs0, (N, 1)), U, K, Z, consts)
    Sh = np.sort(free["S_hat"][~free["crashed_real"] & ~free["crashed_nom"]])
    c = replace(consts, alpha=float(0.5 * (Sh[Sh.size // 2 - 1] + Sh[Sh.size // 2])))
    return SAISCase(x0, xs0, U, K, Z, seed, c)


def run_sais(sampler, case: SAISCase, c: SamplerConstants | None = None):
    return sampler.sais(case.x0, case.xs0, case.U, case.K, N, c or case.c, case.seed)


def twin_sais(sp, case: SAISCase, c: SamplerConstants | None = None, model_backend="numpy",
              fn=sais_twin):
    return fn(sp, np.tile(case.x0, (N, 1)), np.tile(case.xs0, (N, 1)), case.U, case.K, case.Z,
              c or case.c, model_backend)


def sais_mismatch(batch, ref) -> dict[str, float]:
    """Per-output mismatch of a kernel batch and a twin result (flags: fraction that differ)."""
    out = {name: rel_err(getattr(batch, name), ref[name]) for name in SAIS_COSTS}
    out |= {name: float(np.mean(getattr(batch, name) != ref[name])) for name in SAIS_FLAGS}
    out |= {name: rel_err(getattr(batch, name), lane_major(ref[name])) for name in SAIS_LANES}
    return out


def agrees(err: dict[str, float]) -> bool:
    """The comparison's verdict: equal crash flags, every other output within RTOL."""
    return all(err[name] == 0.0 for name in SAIS_FLAGS) and max(err.values()) <= RTOL


def sais_branch_counts(case: SAISCase, ref) -> dict[str, int]:
    """How many samples (or sample-steps) take each branch of Algorithm 1 on this case."""
    c = case.c
    cr, cn = ref["crashed_real"], ref["crashed_nom"]
    Sh, S = ref["S_hat"], ref["S_state_nom"]
    clamped = np.minimum(Sh, c.alpha)
    safe = ~cr & ~cn
    kfb_eff = ref["v_real"] - ref["v_nom"]  # the feedback left after clipping
    dbeta = ref["X"][:, :-1, 4] - ref["X_nom"][:, :-1, 4]
    kfb_beta = case.K[None, :, :, 4] * dbeta[:, :, None]  # its barrier-state part
    out = {"crashed_real": cr.sum(), "crashed_nom": cn.sum(), "real_only": (cr & ~cn).sum(),
           "nom_only": (cn & ~cr).sum(), "both_safe": (~cr & ~cn).sum(),
           "S_hat>alpha": (Sh > c.alpha).sum(), "S_hat<alpha": (Sh < c.alpha).sum(),
           "min(S_hat,alpha)<S": (clamped < S).sum(), "min(S_hat,alpha)>S": (clamped > S).sum(),
           # the four cases of line 11 with both samples safe
           "S<alpha<S_hat": (safe & (S < c.alpha) & (c.alpha < Sh)).sum(),
           "alpha<S<S_hat": (safe & (c.alpha < S) & (S < Sh)).sum(),
           "S<S_hat<alpha": (safe & (S < Sh) & (Sh < c.alpha)).sum(),
           "S_hat<S,S_hat<alpha": (safe & (Sh < S) & (Sh < c.alpha)).sum(),
           # sample-steps of safe samples where the feedback, after clipping, moves the real
           # control by more than 0.1, and where its barrier-state part alone exceeds 0.01
           "feedback>0.1": (np.abs(kfb_eff) > 0.1).any(axis=2)[safe].sum(),
           "beta_feedback>0.01": (np.abs(kfb_beta) > 0.01).any(axis=2)[safe].sum()}
    for name in SAIS_LANES:
        v = ref[name]
        out[f"{name}@u_min"] = (v <= c.u_min).sum()
        out[f"{name}@u_max"] = (v >= c.u_max).sum()
        out[f"{name} inside"] = ((v > c.u_min) & (v < c.u_max)).sum()
    return {k: int(v) for k, v in out.items()}


@pytest.fixture(scope="module")
def sais_setup(setup):
    model, sp, sampler, consts = setup
    case = sais_case(model, sampler, consts)
    return sp, sampler, case, run_sais(sampler, case), twin_sais(sp, case)


def test_sais_case_reaches_every_branch(sais_setup):
    _, _, case, batch, ref = sais_setup
    n = sais_branch_counts(case, ref)
    # the kernel takes the same branches of line 11 as the twin
    alpha = case.c.alpha
    np.testing.assert_array_equal(batch.S_hat > alpha, ref["S_hat"] > alpha)
    np.testing.assert_array_equal(np.minimum(batch.S_hat, alpha) < batch.S_state_nom,
                                  np.minimum(ref["S_hat"], alpha) < ref["S_state_nom"])
    assert n["both_safe"] >= 0.6 * N  # most samples stay safe ...
    for key in ("crashed_real", "crashed_nom", "real_only", "nom_only"):  # ... some crash
        assert n[key] > 0, key
    for key in ("S_hat>alpha", "S_hat<alpha", "min(S_hat,alpha)<S", "min(S_hat,alpha)>S",
                "S<alpha<S_hat", "alpha<S<S_hat", "S<S_hat<alpha", "S_hat<S,S_hat<alpha"):
        assert n[key] > 0, key  # line 11: the clamp and the max each bind on some samples only
    for name in SAIS_LANES:  # lines 6-7: clipping at each bound, and unclipped controls
        assert min(n[f"{name}@u_min"], n[f"{name}@u_max"]) > 0.02 * T * N * 2, name
        assert n[f"{name} inside"] > 0.5 * T * N * 2, name
    steps = T * n["both_safe"]
    assert n["feedback>0.1"] > 0.5 * steps  # line 5: the feedback matters on safe samples ...
    assert n["beta_feedback>0.01"] > 0.5 * steps  # ... its barrier-state column too
    assert np.median(np.abs(ref["LR"])) > 5.0  # line 12 is not negligible


@pytest.mark.parametrize(("model_backend", "clip_in_cost"),
                         [("numpy", True), ("casadi", True), ("numpy", False)])
def test_sais_kernel_equals_twin_per_element(sais_setup, model_backend, clip_in_cost):
    sp, sampler, case, batch, ref = sais_setup
    if (model_backend, clip_in_cost) != ("numpy", True):
        c = replace(case.c, clip_in_cost=clip_in_cost)
        batch, ref = run_sais(sampler, case, c), twin_sais(sp, case, c, model_backend)
    err = sais_mismatch(batch, ref)
    assert agrees(err), err


# --- mutation check: a test copy of the twin with one term of Algorithm 1 left out -------------

MUTANTS = {
    "feedback": "line 5: no feedback, K_k (x - x*) = 0",
    "feedback_cost": "line 8: no lambda/2 k_fb' Sigma^-1 k_fb in S_hat",
    "feedback_in_lr": "line 9: (u + k_fb)' Sigma^-1 (u + 2 eps + k_fb) without k_fb",
    "lr_real": "line 9: no likelihood-ratio term in S_real",
    "lr_nominal": "line 12: no likelihood-ratio term in S_nom",
    "alpha_clamp": "line 11: max(S_hat, S) instead of max(min(S_hat, alpha), S)",
}


def sais_twin_copy(sp, X0, Xs0, U, K, Z, c, model_backend="auto", drop=frozenset()):
    """:func:`sais_twin`, line for line, with the terms named in ``drop`` left out.
    Without ``drop`` it equals the twin bit for bit (tested below)."""
    assert set(drop) <= set(MUTANTS)
    N, T = Z.shape[0], Z.shape[1]
    m = model_twin(sp, N, c.scene, model_backend)
    inv = 1.0 / (c.sigma**2)
    half = 0.5 * c.lam * (1.0 - c.nu_mix)
    X = np.empty((N, T + 1, sp.nx))
    Xs = np.empty((N, T + 1, sp.nx))
    X[:, 0], Xs[:, 0] = X0, Xs0
    S_state_nom, S_hat, S_real, LR = (np.zeros(N) for _ in range(4))
    cr, cn = np.zeros(N, bool), np.zeros(N, bool)
    Vn, Vr = np.empty((N, T, sp.nu)), np.empty((N, T, sp.nu))
    for t in range(T):
        u = U[t]
        eps = c.sigma * Z[:, t]
        kfb = (X[:, t] - Xs[:, t]) @ K[t].T
        if "feedback" in drop:
            kfb = 0.0 * kfb
        vr = np.clip(u + eps + kfb, c.u_min, c.u_max)
        vn = np.clip(u + eps, c.u_min, c.u_max)
        eps_eff = vn - u if c.clip_in_cost else eps
        kfb_eff = vr - u - (vn - u) if c.clip_in_cost else kfb
        X[:, t + 1], Xs[:, t + 1] = m.step(X[:, t], vr), m.step(Xs[:, t], vn)
        cr |= m.crashed(X[:, t + 1], sp.eps_h)
        cn |= m.crashed(Xs[:, t + 1], sp.eps_h)
        qr = m.cost(m.q, X[:, t + 1], c.p) + c.crash_cost * cr
        qn = m.cost(m.q, Xs[:, t + 1], c.p) + c.crash_cost * cn
        k8 = 0.0 * kfb_eff if "feedback_cost" in drop else kfb_eff
        S_hat += qr + half * np.sum(k8 * inv * k8, axis=1)
        S_state_nom += qn
        k9 = 0.0 * kfb_eff if "feedback_in_lr" in drop else kfb_eff
        lr9 = half * np.sum((u + k9) * inv * (u + 2 * eps_eff + k9), axis=1)
        S_real += qr + (0.0 * lr9 if "lr_real" in drop else lr9)
        lr12 = half * (u @ (inv * u) + 2.0 * (eps_eff @ (inv * u)))
        LR += 0.0 * lr12 if "lr_nominal" in drop else lr12
        Vn[:, t], Vr[:, t] = vn, vr
    phi_r, phi_n = m.cost(m.phi, X[:, T], c.p), m.cost(m.phi, Xs[:, T], c.p)
    S_hat += phi_r
    S_state_nom += phi_n
    S_real += phi_r
    clamped = S_hat if "alpha_clamp" in drop else np.minimum(S_hat, c.alpha)
    S_nom = 0.5 * S_state_nom + 0.5 * np.maximum(clamped, S_state_nom) + LR
    return {"S_nom": S_nom, "S_real": S_real, "S_state_nom": S_state_nom, "S_hat": S_hat,
            "LR": LR, "crashed_real": cr, "crashed_nom": cn, "v_nom": Vn, "v_real": Vr,
            "X": X, "X_nom": Xs}


@pytest.mark.parametrize("clip_in_cost", [True, False])
def test_unmutated_twin_copy_is_the_twin(sais_setup, clip_in_cost):
    sp, _, case, _, _ = sais_setup
    c = replace(case.c, clip_in_cost=clip_in_cost)
    copy, twin = twin_sais(sp, case, c, fn=sais_twin_copy), twin_sais(sp, case, c)
    assert copy.keys() == twin.keys()
    for name in twin:
        np.testing.assert_array_equal(copy[name], twin[name], err_msg=name)


def mutant_mismatch(sais_setup, mutant: str) -> dict[str, float]:
    sp, _, case, batch, _ = sais_setup

    def mutated(*args):
        return sais_twin_copy(*args, drop={mutant})

    return sais_mismatch(batch, twin_sais(sp, case, fn=mutated))


@pytest.mark.parametrize("mutant", list(MUTANTS))
def test_kernel_comparison_detects_a_mutated_twin(sais_setup, mutant):
    err = mutant_mismatch(sais_setup, mutant)
    assert not agrees(err), MUTANTS[mutant]
    # by orders of magnitude: the smallest mutant mismatch is ~1e-3 relative, RTOL is 1e-10
    assert max(err.values()) > 1e4 * RTOL, (MUTANTS[mutant], err)


def test_kernel_comparison_detects_raw_noise_in_the_cost(sais_setup):
    """clip_in_cost (assumptions §10.1 lines 6-7): a twin using the raw noise and feedback in
    lines 8, 9 and 12 instead of the clipped ones disagrees with the kernel on S_hat, S_real and
    LR."""
    sp, _, case, batch, _ = sais_setup
    err = sais_mismatch(batch, twin_sais(sp, case, replace(case.c, clip_in_cost=False)))
    assert not agrees(err)
    assert min(err["S_hat"], err["S_real"], err["LR"]) > 1e4 * RTOL, err


def test_zero_gains_reduce_sais_to_the_sampler_without_feedback(setup):
    """K = 0 and x0 = x*0: real and nominal samples coincide, S_real is the MPPI cost of the
    same noise, S_hat = S_state_nom and so S_nom = S_state_nom + LR whatever alpha is."""
    model, _, sampler, c = setup
    x0 = mppi_start(model)
    U = np.random.default_rng(3).normal(0, 2.0, (T, 2))
    c = replace(c, alpha=1e3)
    sais = sampler.sais(x0, x0, U, np.zeros((T, 2, 5)), N, c, seed=77)
    mppi = sampler.mppi(x0, U, N, c, seed=77)
    assert 0 < mppi.crashed.sum() < N // 2
    assert np.any(sais.S_hat > c.alpha) and np.any(sais.S_hat < c.alpha)
    np.testing.assert_array_equal(sais.v_nom, sais.v_real)
    np.testing.assert_array_equal(sais.v_nom, mppi.v)
    np.testing.assert_array_equal(sais.crashed_real, mppi.crashed)
    np.testing.assert_array_equal(sais.crashed_nom, mppi.crashed)
    np.testing.assert_array_equal(sais.S_hat, sais.S_state_nom)
    # the same numbers summed in a different order: equal up to rounding
    assert rel_err(sais.S_real, mppi.S) <= RTOL
    assert rel_err(sais.S_state_nom + sais.LR, mppi.S) <= RTOL
    assert rel_err(sais.S_nom, sais.S_state_nom + sais.LR) <= RTOL


# ----------------------------------------------------------------------------------------------
# MPPI and candidate evaluation
# ----------------------------------------------------------------------------------------------


def mppi_counts(ref, c) -> dict[str, int]:
    v = ref["v"]
    return {"crashed": int(ref["crashed"].sum()), "u_min": int((v <= c.u_min).sum()),
            "u_max": int((v >= c.u_max).sum()),
            "inside": int(((v > c.u_min) & (v < c.u_max)).sum())}


def assert_mppi_case_is_useful(ref, c):
    n = mppi_counts(ref, c)
    assert 0 < n["crashed"] < 0.4 * N, n  # most samples safe, some crash
    assert min(n["u_min"], n["u_max"]) > 0.02 * ref["v"].size, n  # clipping at both bounds
    assert n["inside"] > 0.5 * ref["v"].size, n


def mppi_start(model):
    """0.9 m off the line through the first obstacle's centre, heading along it at 2 m/s."""
    return model.lift([1.0 - 0.9 / np.sqrt(2.0), 1.0 + 0.9 / np.sqrt(2.0), np.sqrt(2.0),
                       np.sqrt(2.0)])


@pytest.mark.parametrize("model_backend", ["numpy", "casadi"])
def test_mppi_kernel_equals_twin_per_element(setup, model_backend):
    model, sp, sampler, c = setup
    x0 = mppi_start(model)
    U = np.random.default_rng(11).normal(0, 2.0, (T, 2))
    batch = sampler.mppi(x0, U, N, c, seed=123)
    ref = mppi_twin(sp, np.tile(x0, (N, 1)), U, kernel_noise(sampler, N, T, 123), c,
                    model_backend)
    assert_mppi_case_is_useful(ref, c)
    np.testing.assert_array_equal(batch.crashed, ref["crashed"])
    assert rel_err(batch.S, ref["S"]) <= RTOL
    assert rel_err(batch.v, lane_major(ref["v"])) <= RTOL


def test_plain_model_mppi_kernel_equals_twin_per_element():
    """Plain MPPI (no barrier state): crash costs still come from the margins."""
    model = double_integrator(obstacles=OBST, u_limit=5.0)
    sp = navigation_costs(model, S=(10.0, 10.0, 1.0, 1.0))
    sampler = Sampler(sp, backend="compiled")
    c = SamplerConstants(sigma=np.array([3.0, 2.4]), lam=1.0, nu_mix=0.0, u_min=model.u_min,
                         u_max=model.u_max, crash_cost=1e6, p=np.array(GOAL))
    x0 = mppi_start(model)
    U = np.random.default_rng(5).normal(0, 2.0, (T, 2))
    batch = sampler.mppi(x0, U, N, c, seed=5)
    Z = kernel_noise(sampler, N, T, 5)
    for backend in ("numpy", "casadi"):
        ref = mppi_twin(sp, np.tile(x0, (N, 1)), U, Z, c, backend)
        assert_mppi_case_is_useful(ref, c)
        np.testing.assert_array_equal(batch.crashed, ref["crashed"])
        assert rel_err(batch.S, ref["S"]) <= RTOL
        assert rel_err(batch.v, lane_major(ref["v"])) <= RTOL


def test_candidate_kernel_equals_twin_per_element(setup):
    model, sp, sampler, c = setup
    rng = np.random.default_rng(17)
    base = mppi_start(model)[:4]
    starts = np.stack([model.lift(base + np.r_[rng.normal(0, 0.1, 2), rng.normal(0, 0.3, 2)])
                       for _ in range(N)])
    U = rng.normal(0, 2.0, (T, 2))
    stride = rng.integers(0, 2, N).astype(float)
    S = sampler.candidates(starts, U, stride, c, seed=11)
    U_next = np.vstack([U[1:], U[-1:]])
    U_lane = np.where(stride[:, None, None] > 0, U_next[None], U[None])
    ref = mppi_twin(sp, starts, U_lane, kernel_noise(sampler, N, T, 11), c, delay=stride)
    assert_mppi_case_is_useful(ref, c)
    assert 0 < stride.sum() < N
    assert 0 < ref["crashed"][stride == 1].sum() and 0 < ref["crashed"][stride == 0].sum()
    assert rel_err(S, ref["S"]) <= RTOL
    shifted = ref["v"][stride == 1, 0]  # u_1 at t = 0, no noise
    np.testing.assert_array_equal(shifted, np.broadcast_to(U[1], shifted.shape))


# ----------------------------------------------------------------------------------------------
# noise and threads
# ----------------------------------------------------------------------------------------------


def test_numpy_twin_is_used_for_the_navigation_problem(setup):
    _, sp, _, _ = setup
    assert isinstance(model_twin(sp, 4, sp.model.scene_value), NumpyModelTwin)
    assert not isinstance(model_twin(sp, 4, sp.model.scene_value, "casadi"), NumpyModelTwin)


def test_kernel_noise_is_standard_normal_and_deterministic(setup):
    lib = setup[2].lib
    z = lib.normals(4096, 25, 2, seed=2026)
    assert stats.kstest(z.ravel(), "norm").pvalue > 1e-3
    assert abs(z.mean()) < 0.01 and abs(z.var() - 1) < 0.01
    np.testing.assert_array_equal(z, lib.normals(4096, 25, 2, seed=2026))
    assert not np.array_equal(z, lib.normals(4096, 25, 2, seed=2027))
    # each sample's stream depends only on (seed, sample index)
    np.testing.assert_array_equal(lib.normals(100, 25, 2, seed=2026), z[:, :, :100])


def test_kernel_draws_the_published_noise(setup):
    """In-kernel noise (vectorised per lane block) equals lib.normals, sample by sample: with
    U = 0 and limits that never bind, the applied controls are exactly sigma * z."""
    model, _, sampler, c = setup
    c = replace(c, u_min=np.full(2, -1e300), u_max=np.full(2, 1e300))
    x0 = model.lift([0.5, 0.5, 0.0, 0.0])
    batch = sampler.mppi(x0, np.zeros((T, 2)), N, c, seed=99)
    z = sampler.lib.normals(N, T, 2, seed=99)
    np.testing.assert_array_equal(batch.v, c.sigma[None, :, None] * z)


def test_results_do_not_depend_on_thread_count(sais_setup):
    _, sampler, case, _, _ = sais_setup
    runs = []
    for threads in (1, 2):
        sampler.lib.set_threads(threads)
        runs.append(sampler.sais(case.x0, case.xs0, case.U, case.K, 256, case.c, seed=5))
    sampler.lib.set_threads(2)
    for name in (*SAIS_COSTS, *SAIS_FLAGS, *SAIS_LANES):
        np.testing.assert_array_equal(getattr(runs[0], name), getattr(runs[1], name), name)

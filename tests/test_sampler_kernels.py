"""Generated sampler kernels against the NumPy twin fed the same noise (issue: sampling core)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from workbench.barrier import embed_barrier
from workbench.models import double_integrator
from workbench.obstacles import Circle
from workbench.sampling.constants import SamplerConstants
from workbench.sampling.kernels import sampler_library
from workbench.sampling.problem import navigation_costs
from workbench.sampling.reference import mppi_reference, sais_reference

OBST = (Circle((2.0, 2.0), 0.8), Circle((3.5, 1.0), 0.5), Circle((1.0, 3.2), 0.6))
N, T = 37, 40  # N not a multiple of the lane count: padding is exercised


@pytest.fixture(scope="module")
def setup():
    model = embed_barrier(double_integrator(obstacles=OBST, u_limit=5.0))
    sp = navigation_costs(model)
    lib = sampler_library(sp)
    consts = SamplerConstants(sigma=np.array([6.0, 4.0]), lam=1.3, nu_mix=0.1,
                              u_min=model.u_min, u_max=model.u_max, crash_cost=1e6,
                              p=model.lift([4.0, 4.0, 0.0, 0.0]), alpha=5e4)
    return model, sp, lib, consts


def _close(a, b, rtol=1e-9):
    np.testing.assert_allclose(a, b, rtol=rtol, atol=1e-9 * max(1.0, float(np.max(np.abs(b)))))


@pytest.mark.parametrize("model_backend", ["numpy", "casadi"])
def test_mppi_kernel_equals_reference_including_crashes(setup, rng, model_backend):
    model, sp, lib, c = setup
    x0 = model.lift([0.5, 0.5, 1.5, 1.5])  # heading at the first obstacle: some samples crash
    U = rng.normal(0, 1.5, (T, 2))
    out = lib.mppi(np.tile(np.r_[x0, 0, 0], (N, 1)), consts=c.kernel_consts(),
                   time_in={"u": U}, seed=123, keep_noise=True)
    Z = np.transpose(out.noise, (2, 0, 1))
    ref = mppi_reference(sp, np.tile(x0, (N, 1)), U, Z, c, model_backend)
    crashed = out.result[:, 1].astype(bool)
    np.testing.assert_array_equal(crashed, ref["crashed"])
    assert 0 < crashed.sum() < N
    _close(out.result[:, 0], ref["S"])
    _close(np.transpose(out.lane_out[0], (2, 0, 1)), ref["v"], rtol=1e-12)


@pytest.mark.parametrize(("model_backend", "clip_in_cost"),
                         [("numpy", True), ("casadi", True), ("numpy", False)])
def test_sais_kernel_equals_reference(setup, rng, model_backend, clip_in_cost):
    from dataclasses import replace

    model, sp, lib, c = setup
    c = replace(c, clip_in_cost=clip_in_cost)
    x0 = model.lift([1.0, 1.0, 2.0, 2.0])
    xs0 = model.lift([0.9, 1.1, 1.8, 2.1])
    U = rng.normal(0, 1.5, (T, 2))
    K = rng.normal(0, 2.0, (T, 2, 5))
    K[:, :, 4] = rng.normal(0, 1e-3, (T, 2))
    carry = np.tile(np.r_[x0, xs0, np.zeros(6)], (N, 1))
    out = lib.sais(carry, consts=c.kernel_consts(), time_in={"u": U, "K": K.reshape(T, 10)},
                   seed=9, keep_noise=True)
    Z = np.transpose(out.noise, (2, 0, 1))
    ref = sais_reference(sp, np.tile(x0, (N, 1)), np.tile(xs0, (N, 1)), U, K, Z, c,
                         model_backend)
    names = ("S_nom", "S_real", "S_state_nom", "S_hat", "LR", "crashed_real", "crashed_nom")
    for j, name in enumerate(names):
        _close(out.result[:, j], ref[name].astype(float))
    assert ref["crashed_real"].any() and ref["crashed_nom"].any()
    _close(np.transpose(out.lane_out[0], (2, 0, 1)), ref["v_nom"], rtol=1e-12)
    _close(np.transpose(out.lane_out[1], (2, 0, 1)), ref["v_real"], rtol=1e-12)


def test_candidate_kernel_equals_reference(setup, rng):
    model, sp, lib, c = setup
    starts = np.stack([model.lift([1.0 + 0.1 * i, 1.0, 1.0, 1.0]) for i in range(N)])
    U = rng.normal(0, 1.0, (T, 2))
    U_next = np.vstack([U[1:], U[-1:]])
    stride = rng.integers(0, 2, N).astype(float)
    carry = np.column_stack([starts, np.zeros((N, 2)), stride, stride])
    out = lib.candidates(carry, consts=c.kernel_consts(), time_in={"u": U, "u_next": U_next},
                         seed=11, keep_noise=True)
    Z = np.transpose(out.noise, (2, 0, 1))
    U_lane = np.where(stride[:, None, None] > 0, U_next[None], U[None])
    ref = mppi_reference(sp, starts, U_lane, Z, c, delay=stride)
    _close(out.result[:, 0], ref["S"])
    _close(np.transpose(out.lane_out[0], (2, 0, 1)), ref["v"], rtol=1e-12)
    shifted = ref["v"][stride == 1, 0]  # u_1 at t = 0, no noise
    np.testing.assert_array_equal(shifted, np.broadcast_to(U[1], shifted.shape))
    assert 0 < stride.sum() < N


def test_zero_gains_reduce_sais_to_the_sampler_without_feedback(setup, rng):
    """K = 0: real and nominal samples coincide and S_real is the MPPI cost of the same noise."""
    model, _, lib, c = setup
    x0 = model.lift([0.5, 0.5, 1.0, 0.5])
    U = rng.normal(0, 1.0, (T, 2))
    carry = np.tile(np.r_[x0, x0, np.zeros(6)], (N, 1))
    sais = lib.sais(carry, consts=c.kernel_consts(), time_in={"u": U, "K": np.zeros((T, 10))},
                    seed=77)
    mppi = lib.mppi(np.tile(np.r_[x0, 0, 0], (N, 1)), consts=c.kernel_consts(),
                    time_in={"u": U}, seed=77)
    S_mppi = mppi.result[:, 0]
    # the same numbers summed in a different order: equal up to rounding
    np.testing.assert_allclose(sais.result[:, 1], S_mppi, rtol=1e-14)  # S_real
    np.testing.assert_allclose(sais.result[:, 3], sais.result[:, 2], rtol=1e-14)  # S_hat
    np.testing.assert_allclose(sais.result[:, 2] + sais.result[:, 4], S_mppi, rtol=1e-14)
    np.testing.assert_array_equal(sais.lane_out[0], sais.lane_out[1])
    np.testing.assert_array_equal(sais.lane_out[0], mppi.lane_out[0])


def test_numpy_twin_is_used_for_the_navigation_problem(setup):
    from workbench.sampling.reference import _model, _NumpyModel

    _, sp, _, _ = setup
    assert isinstance(_model(sp, 4), _NumpyModel)
    assert not isinstance(_model(sp, 4, "casadi"), _NumpyModel)


def test_kernel_noise_is_standard_normal_and_deterministic(setup):
    _, _, lib, _ = setup
    z = lib.normals(4096, 25, 2, seed=2026)
    assert stats.kstest(z.ravel(), "norm").pvalue > 1e-3
    assert abs(z.mean()) < 0.01 and abs(z.var() - 1) < 0.01
    np.testing.assert_array_equal(z, lib.normals(4096, 25, 2, seed=2026))
    assert not np.array_equal(z, lib.normals(4096, 25, 2, seed=2027))
    # each sample's stream depends only on (seed, sample index)
    np.testing.assert_array_equal(lib.normals(100, 25, 2, seed=2026), z[:, :, :100])


def test_results_do_not_depend_on_thread_count(setup, rng):
    model, _, lib, c = setup
    x0 = model.lift([1.0, 1.0, 2.0, 2.0])
    U = rng.normal(0, 1.5, (T, 2))
    carry = np.tile(np.r_[x0, x0, np.zeros(6)], (256, 1))
    K = rng.normal(0, 1, (T, 10))
    runs = []
    for threads in (1, 2):
        lib.set_threads(threads)
        runs.append(lib.sais(carry, consts=c.kernel_consts(), time_in={"u": U, "K": K},
                             seed=5, keep_noise=True))
    lib.set_threads(2)
    np.testing.assert_array_equal(runs[0].result, runs[1].result)
    np.testing.assert_array_equal(runs[0].noise, runs[1].noise)


def test_kernel_draws_the_published_noise(setup):
    """In-kernel noise (vectorised per lane block) equals wb_normals, sample by sample."""
    model, _, lib, c = setup
    x0 = model.lift([0.5, 0.5, 0.0, 0.0])
    out = lib.mppi(np.tile(np.r_[x0, 0, 0], (N, 1)), consts=c.kernel_consts(),
                   time_in={"u": np.zeros((T, 2))}, seed=99, keep_noise=True)
    np.testing.assert_array_equal(out.noise, lib.normals(N, T, 2, seed=99))


def test_plain_model_mppi_kernel_equals_reference(rng):
    """Plain MPPI (no barrier state): crash costs still come from the margins."""
    model = double_integrator(obstacles=OBST, u_limit=5.0)
    sp = navigation_costs(model, S=(10.0, 10.0, 1.0, 1.0))
    lib = sampler_library(sp)
    c = SamplerConstants(sigma=np.array([6.0, 4.0]), lam=1.0, nu_mix=0.0, u_min=model.u_min,
                         u_max=model.u_max, crash_cost=1e6, p=np.array([4.0, 4.0, 0.0, 0.0]))
    x0 = np.array([0.5, 0.5, 1.2, 1.2])  # grazes obstacle 0: some samples crash
    U = rng.normal(0, 1.5, (T, 2))
    out = lib.mppi(np.tile(np.r_[x0, 0, 0], (N, 1)), consts=c.kernel_consts(),
                   time_in={"u": U}, seed=5, keep_noise=True)
    Z = np.transpose(out.noise, (2, 0, 1))
    for backend in ("numpy", "casadi"):
        ref = mppi_reference(sp, np.tile(x0, (N, 1)), U, Z, c, backend)
        np.testing.assert_array_equal(out.result[:, 1].astype(bool), ref["crashed"])
        _close(out.result[:, 0], ref["S"])
    assert 0 < ref["crashed"].sum() < N

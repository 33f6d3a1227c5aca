"""Loading the sampler kernels: the NumPy twin when the C back end cannot compile a problem,
and every loaded library checked against CasADi before first use."""

from __future__ import annotations

import ctypes

import numpy as np
import pytest
from conftest import swap_library

from workbench.problem.models import double_integrator


def _erfinv_sampling_problem():
    import casadi as ca

    from workbench.problem.models import Model
    from workbench.sampling.problem import SamplingProblem

    x, u, g = ca.SX.sym("x", 2), ca.SX.sym("u", 2), ca.SX.sym("g", 2)
    x_next = x + 0.05 * (u + 0.1 * ca.erfinv(0.5 * ca.tanh(x)))
    model = Model.from_expressions("wbrel_erfinv_plane", x, u, x_next, dt=0.05,
                                   u_min=[-2, -2], u_max=[2, 2], h=ca.vertcat(4.0 - x[0]))
    e = x - g
    return SamplingProblem.from_costs(model, ca.dot(e, e), 10 * ca.dot(e, e), g)


def test_class4_sampler_falls_back_to_the_twin_with_one_warning(monkeypatch):
    import warnings

    from workbench.sampling.kernels import library as kernels
    from workbench.sampling.kernels.constants import SamplerConstants
    from workbench.sampling.sampler import Sampler
    from workbench.sampling.twin import mppi_twin

    monkeypatch.setattr(kernels, "_LIBS", {})
    sp = _erfinv_sampling_problem()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        first, second = Sampler(sp), Sampler(sp)
    msgs = [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]
    assert len(msgs) == 1 and "erfinv" in msgs[0] and "NumPy/CasADi" in msgs[0]
    assert first.backend == second.backend == "numpy"
    c = SamplerConstants(sigma=np.ones(2), lam=1.0, nu_mix=0.0, u_min=-2 * np.ones(2),
                         u_max=2 * np.ones(2), crash_cost=1e3, p=np.array([1.0, 1.0]))
    U = np.full((4, 2), 0.5)
    out = first.mppi(np.zeros(2), U, 6, c, seed=3)
    ref = mppi_twin(sp, np.zeros((6, 2)), U,
                    np.random.default_rng(3).standard_normal((6, 4, 2)), c)
    np.testing.assert_allclose(out.S, ref["S"], rtol=1e-12)
    assert np.all(np.isfinite(out.S))

# ---------------------------------------------------------------------------------------------
# every loaded library is checked against CasADi's evaluation before first use


def _small_navigation(center, dt: float = 0.02):
    """Obstacles are kernel inputs, so two problems with different kernels differ in dt."""
    from workbench.problem.barrier import embed_barrier
    from workbench.problem.obstacles import Circle
    from workbench.sampling.problem import navigation_costs

    return navigation_costs(embed_barrier(double_integrator(
        obstacles=(Circle(center, 0.5),), u_limit=5.0, dt=dt)))




def test_class5_swapped_sampler_library_is_detected_and_rebuilt(tmp_path, monkeypatch):
    """A sampler library swapped with another problem's (hash updated in
    the manifest) is detected and rebuilt; the rebuilt kernels equal the twin."""
    import shutil

    from workbench.codegen import build_library
    from workbench.sampling.kernels import library as kernels
    from workbench.sampling.kernels.constants import SamplerConstants
    from workbench.sampling.kernels.flags import KERNEL_FLAGS
    from workbench.sampling.twin import mppi_twin

    sp_a, sp_b = _small_navigation((2.0, 2.0)), _small_navigation((1.0, 3.0), 0.05)
    built, cache = {}, tmp_path / "cache"
    for name, sp in (("a", sp_a), ("b", sp_b)):
        stem, _, source = kernels.library_sources(sp)
        lib = build_library(stem, [], source, extra_flags=KERNEL_FLAGS,
                            root=tmp_path / "build")
        # the cache under test holds copies this process has never loaded (as a cache left
        # by an earlier run would)
        shutil.copytree(lib.path.parent, cache / lib.path.parent.name)
        built[name] = type(lib)(path=cache / lib.path.parent.name / lib.path.name,
                                key=lib.key, cdll=lib.cdll, functions={}, cache_hit=True)
    assert built["a"].path != built["b"].path and built["a"].path.name == built["b"].path.name
    swap_library(built["a"], built["b"])
    monkeypatch.setenv("WORKBENCH_CACHE_DIR", str(cache))
    monkeypatch.setattr(kernels, "_LIBS", {})
    with pytest.warns(RuntimeWarning, match=r"wb_mppi: .*differs.*rebuilding"):
        lib = kernels.sampler_library(sp_a)
    assert built["a"].path.read_bytes() != built["b"].path.read_bytes()
    m = sp_a.model
    c = SamplerConstants(sigma=np.array([2.0, 2.0]), lam=1.0, nu_mix=0.0, u_min=m.u_min,
                         u_max=m.u_max, crash_cost=1e6, p=m.lift([3.0, 3.0, 0.0, 0.0]),
                         scene=m.scene_value)
    x0 = m.lift([0.5, 0.5, 1.0, 1.0])
    U = np.full((6, 2), 0.5)
    out = lib.mppi(np.tile(np.r_[x0, 0, 0], (9, 1)), consts=c.kernel_consts(),
                   time_in={"u": U}, seed=5, keep_noise=True)
    ref = mppi_twin(sp_a, np.tile(x0, (9, 1)), U, np.transpose(out.noise, (2, 0, 1)), c)
    np.testing.assert_allclose(out.result[:, 0], ref["S"], rtol=1e-9)


def test_class5_kernel_check_rejects_another_problems_kernel():
    from workbench.sampling.kernels.compiled import CompiledKernel
    from workbench.sampling.kernels.library import sampler_library
    from workbench.sampling.kernels.specs import mppi_spec
    from workbench.sampling.kernels.verify import KernelMismatch, verify_kernel

    lib_b = sampler_library(_small_navigation((1.0, 3.0), 0.05))
    spec_a = mppi_spec(_small_navigation((2.0, 2.0)))
    verify_kernel(lib_b.mppi)  # its own spec: fine
    with pytest.raises(KernelMismatch, match="wb_mppi"):
        verify_kernel(CompiledKernel(spec_a, lib_b.cdll))


def test_set_threads_reaches_every_kernel_library_loaded_before_and_after():
    """set_threads is global: the sampler, the safe-MPPI and the diagnostics libraries all
    follow it, whether they were loaded before the call or after it."""
    from workbench.problem.barrier import embed_barrier
    from workbench.problem.obstacles import Circle
    from workbench.sampling.kernels.diagnostics import diagnostics_library
    from workbench.sampling.kernels.library import get_threads, sampler_library, set_threads
    from workbench.sampling.kernels.safe import safe_library
    from workbench.sampling.problem import navigation_costs

    old = get_threads()
    plain = double_integrator(obstacles=(Circle((2.0, 2.0), 0.5),))
    sp = navigation_costs(embed_barrier(plain))
    try:
        safe = safe_library(navigation_costs(plain, S=(10.0, 10.0, 1.0, 1.0)))  # before
        if safe is None:
            pytest.skip("no C compiler")
        safe.cdll.wb_get_threads.restype = ctypes.c_int
        for n in (1, 2):
            set_threads(n)
            diag = diagnostics_library(sp)  # loaded after the first call
            diag.cdll.wb_get_threads.restype = ctypes.c_int
            assert safe.cdll.wb_get_threads() == n
            assert diag.cdll.wb_get_threads() == n
            assert sampler_library(sp).cdll.wb_get_threads() == n
    finally:
        set_threads(old or 2)

"""Block width, the counter-based generator and the reusable call path of the sampler kernels.

* Draws are a function of (seed, sample, step, row) only: ``lib.normals`` (blocks of samples,
  AVX-512 gathers where the target has them), ``lib.normals_at`` (one sample at a time) and the
  kernels' own draws are the same numbers for 4 and 8 float64 samples per block (8 and 16
  float32) and 1 or 2 threads, slow paths of the ziggurat (wedges, the tail beyond r) included.
* SAIS batches are bitwise equal across block widths and thread counts, in both precisions.
* Calls reuse their buffers (:class:`~workbench.sampling.kernels.compiled.OutputPool`) only when
  nothing refers to them: results a caller keeps are never overwritten by later calls (a pool
  that reuses regardless is shown to corrupt them), dropped ones are reused; const pointers
  follow new constants; time inputs of the wrong size are refused.
"""

from __future__ import annotations

import itertools
import math
import weakref
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from workbench.problem.barrier import embed_barrier
from workbench.problem.models import double_integrator
from workbench.problem.obstacles import Circle
from workbench.sampling.kernels.compiled import OutputPool
from workbench.sampling.kernels.constants import SamplerConstants
from workbench.sampling.kernels.emit import EmitError, KernelSpec, ziggurat_tables
from workbench.sampling.kernels.flags import VECTOR_BITS_ENV, lane_count
from workbench.sampling.kernels.library import load_sampler_library
from workbench.sampling.kernels.specs import mppi_spec
from workbench.sampling.kernels.threads import using
from workbench.sampling.problem import navigation_costs
from workbench.sampling.sampler import Sampler, check_batch

OBST = (Circle((2.0, 2.0), 0.8), Circle((3.5, 1.0), 0.5), Circle((1.0, 3.2), 0.6))
N, T = 125, 30  # not a multiple of any block width: padding and the scalar tail are exercised
GOAL = (4.0, 4.0, 0.0, 0.0)
FIELDS = ("S_nom", "S_real", "S_state_nom", "S_hat", "LR", "crashed_real", "crashed_nom",
          "v_nom", "v_real")


@pytest.fixture(scope="module")
def setup():
    model = embed_barrier(double_integrator(obstacles=OBST, u_limit=5.0))
    sp = navigation_costs(model)
    c = SamplerConstants(sigma=np.array([3.0, 2.4]), lam=1.3, nu_mix=0.1, u_min=model.u_min,
                         u_max=model.u_max, crash_cost=1e6, p=model.lift(GOAL), alpha=50.0)
    _, c = check_batch(sp, N, np.zeros((T, 2)), c)  # the model's scene filled in
    rng = np.random.default_rng(7)
    # towards the first obstacle: about a quarter of the samples crash within T steps
    x0 = model.lift([0.5, 0.7, 1.6, 1.4])
    xs0 = model.lift([0.55, 0.65, 1.5, 1.5])
    U = rng.normal(0.0, 2.0, (T, 2))
    K = rng.normal(0.0, 0.5, (T, 2, 5))
    return model, sp, c, (x0, xs0, U, K)


@pytest.fixture(scope="module")
def libs(setup):
    """float64 libraries of 4 and 8 samples per block, float32 of 8 and 16."""
    sp = setup[1]
    out = {(p, L): load_sampler_library(sp, precision=p, lanes=L)
           for p, L in (("float64", 4), ("float64", 8), ("float32", 8), ("float32", 16))}
    if any(v is None for v in out.values()):
        pytest.skip("no C compiler")
    return out


def _sampler(sp, lib64, lib32=None) -> Sampler:
    s = Sampler(sp, "compiled", "float32" if lib32 is not None else "float64")
    s.lib, s.lib32 = lib64, lib32
    return s


def _batch(s: Sampler, case, c, seed: int, n: int = N):
    x0, xs0, U, K = case
    b = s.sais(x0, xs0, U, K, n, c, seed)
    return {f: np.array(getattr(b, f)) for f in FIELDS}


def test_ziggurat_tables_match_marsaglia_tsang():
    """The bisection for r reproduces the published 128- and 256-layer edges; the tables are a
    ziggurat: decreasing edges, equal layer areas, rectangle ratios in [0, 1)."""
    assert ziggurat_tables(128)[3] == pytest.approx(3.442619855899, abs=1e-9)
    assert ziggurat_tables(256)[3] == pytest.approx(3.6541528853610088, abs=1e-9)
    x, ratio, f, r = ziggurat_tables(1024)
    assert len(x) == 1025 and x[1] == r and x[-1] == 0.0
    assert all(a > b for a, b in itertools.pairwise(x))
    assert all(0.0 <= q < 1.0 for q in ratio)
    v = x[0] * math.exp(-0.5 * r * r)
    areas = [x[i] * (f[i + 1] - f[i]) for i in range(1, 1023)]
    assert max(abs(a / v - 1.0) for a in areas) < 1e-9
    assert np.mean(ratio) > 0.995  # the inline acceptance the kernels rely on


def test_draws_do_not_depend_on_block_width(libs):
    """Block draws (4 and 8 lanes) equal one-sample-at-a-time draws, the ziggurat's slow paths
    included (about 0.4% of draws; the tail beyond r about 5e-5), and are standard normal."""
    n, steps, seed = 4099, 60, 2027
    z4 = libs["float64", 4].normals(n, steps, 2, seed)
    z8 = libs["float64", 8].normals(n, steps, 2, seed)
    np.testing.assert_array_equal(z4, z8)
    idx = np.array([0, 3, 7, 8, 1000, 4097, 4098])
    np.testing.assert_array_equal(libs["float64", 8].normals_at(idx, steps, 2, seed), z8[..., idx])
    np.testing.assert_array_equal(libs["float64", 4].normals_at(np.arange(n), steps, 2, seed), z4)
    r = ziggurat_tables()[3]
    assert np.sum(np.abs(z8) > r) >= 5  # the tail path ran
    assert abs(z8.mean()) < 0.005 and abs(z8.var() - 1.0) < 0.005
    assert not np.array_equal(z8, libs["float64", 8].normals(n, steps, 2, seed + 1))


def test_batches_do_not_depend_on_block_width_or_threads(setup, libs):
    _model, sp, c, case = setup
    runs = {}
    for (p, L), lib in libs.items():
        for threads in (1, 2):
            with using(threads):
                s = (_sampler(sp, lib) if p == "float64"
                     else _sampler(sp, libs["float64", 8], lib))
                runs[p, L, threads] = _batch(s, case, c, seed=11)
    for p in ("float64", "float32"):
        ref = runs[p, lane_count(p), 1]
        for key, got in runs.items():
            if key[0] == p:
                for f in FIELDS:
                    np.testing.assert_array_equal(got[f], ref[f], err_msg=f"{key} {f}")
    crashed = runs["float64", 8, 1]["crashed_real"]
    assert 0 < crashed.sum() < N  # the crash branches ran
    assert not np.array_equal(runs["float64", 8, 1]["S_real"], runs["float32", 16, 1]["S_real"])


def test_seeded_kernel_draws_lib_normals(setup, libs):
    """A kernel drawing its noise (8 lanes, AVX-512 path where available) equals the same kernel
    given lib.normals (4 lanes) as input."""
    _model, _sp, c, (x0, xs0, U, K) = setup
    k = libs["float64", 8].sais
    common = {"consts": c.kernel_consts(), "time_in": {"u": U, "K": K.reshape(T, -1)}}
    carry = k.carry.pack(1, x=x0, x_nom=xs0)
    a = k(carry, n=N, seed=5, keep_noise=True, **common)
    z = libs["float64", 4].normals(N, T, 2, 5)
    np.testing.assert_array_equal(a.noise, z)
    b = k(k.carry.pack(N, x=x0, x_nom=xs0), noise=z, **common)  # N rows, given noise
    np.testing.assert_array_equal(a.result, b.result)
    for u, v in zip(a.lane_out, b.lane_out, strict=True):
        np.testing.assert_array_equal(u, v)


def test_kept_results_are_never_overwritten(setup, libs, monkeypatch):
    """Batches the caller keeps survive later calls; a pool that reuses buffers regardless of
    references corrupts them (the check is sharp)."""
    _model, sp, c, case = setup

    def kept_after_more_calls(s: Sampler) -> bool:
        x0, xs0, U, K = case
        first = s.sais(x0, xs0, U, K, N, c, 1)
        copy = {f: np.array(getattr(first, f)) for f in FIELDS}
        for seed in range(2, 6):
            s.sais(x0, xs0, U, K, N, c, seed)
        return all(np.array_equal(getattr(first, f), copy[f]) for f in FIELDS)

    assert kept_after_more_calls(_sampler(sp, libs["float64", 8]))
    assert kept_after_more_calls(_sampler(sp, libs["float64", 8], libs["float32", 16]))
    monkeypatch.setattr(OutputPool, "get", lambda self: self._groups[0] if self._groups
                        else self._groups.append(self._make()) or self._groups[0])
    assert not kept_after_more_calls(_sampler(sp, libs["float64", 8]))


def test_dropped_results_are_reused(setup, libs):
    """Once a call's outputs are dropped, the next call of that shape writes the same buffers
    (no new allocation, no page faults)."""
    _model, _sp, c, (x0, xs0, U, K) = setup
    k = libs["float64", 8].sais
    common = {"consts": c.kernel_consts(), "time_in": {"u": U, "K": K.reshape(T, -1)}}
    carry = k.carry.pack(1, x=x0, x_nom=xs0)
    out = k(carry, n=N, seed=3, **common)
    bases = [weakref.ref(o.base) for o in out.lane_out]
    del out
    out = k(carry, n=N, seed=4, **common)
    assert all(o.base is w() for o, w in zip(out.lane_out, bases, strict=True))
    kept = k(carry, n=N, seed=5, **common)  # `out` is alive: a different group
    assert not any(np.shares_memory(a, b) for a in out.lane_out for b in kept.lane_out)


def test_new_constants_reach_the_kernel(setup, libs):
    """The call path caches const pointers per set of arrays: switching constants back and
    forth gives each its own batch (as on a call path without the cache)."""
    model, sp, c, case = setup
    c2 = SamplerConstants(sigma=np.array([1.0, 4.0]), lam=0.7, nu_mix=0.0, u_min=model.u_min,
                          u_max=model.u_max, crash_cost=1e3, p=model.lift(GOAL), alpha=80.0)
    s = _sampler(sp, libs["float64", 8])
    a1, b1, a2 = (_batch(s, case, cc, seed=9) for cc in (c, c2, c))
    libs["float64", 8].sais._plans.clear()
    b2 = _batch(s, case, c2, seed=9)
    for f in FIELDS:
        np.testing.assert_array_equal(a1[f], a2[f])
        np.testing.assert_array_equal(b1[f], b2[f])
    assert not np.array_equal(a1["S_real"], b1["S_real"])


def test_concurrent_calls_from_threads(setup, libs):
    """Python threads calling one kernel at once (the GIL is released in C) each get their own
    buffers: results equal sequential calls."""
    _model, sp, c, case = setup
    s = _sampler(sp, libs["float64", 8])
    seeds = list(range(20, 32))
    ref = {seed: _batch(s, case, c, seed) for seed in seeds}
    with ThreadPoolExecutor(2) as ex:
        got = dict(zip(seeds, ex.map(lambda sd: _batch(s, case, c, sd), seeds), strict=True))
    for seed in seeds:
        for f in FIELDS:
            np.testing.assert_array_equal(got[seed][f], ref[seed][f])


def test_call_checks_time_inputs_and_carry_rows(setup, libs):
    _model, _sp, c, (x0, xs0, U, K) = setup
    k = libs["float64", 8].sais
    carry = k.carry.pack(1, x=x0, x_nom=xs0)
    with pytest.raises(ValueError, match="time input 'K'"):
        k(carry, n=N, seed=1, consts=c.kernel_consts(), time_in={"u": U, "K": K[:, :1]})
    with pytest.raises(ValueError, match="rows"):
        k(np.vstack([carry, carry]), n=N, seed=1, consts=c.kernel_consts(),
          time_in={"u": U, "K": K.reshape(T, -1)})
    with pytest.raises(ValueError, match="const input 'sigma'"):
        k(carry, n=N, seed=1, consts={**c.kernel_consts(), "sigma": np.ones(3)},
          time_in={"u": U, "K": K.reshape(T, -1)})


def test_vector_bits_setting(monkeypatch, setup):
    monkeypatch.setenv(VECTOR_BITS_ENV, "256")
    assert (lane_count("float64"), lane_count("float32")) == (4, 8)
    monkeypatch.setenv(VECTOR_BITS_ENV, "512")
    assert (lane_count("float64"), lane_count("float32")) == (8, 16)
    assert mppi_spec(setup[1]).lanes == 8
    monkeypatch.setenv(VECTOR_BITS_ENV, "384")
    with pytest.raises(ValueError, match=VECTOR_BITS_ENV):
        lane_count("float64")
    spec = mppi_spec(setup[1])
    with pytest.raises(EmitError, match="block"):
        KernelSpec(name="x", step=spec.step, final=spec.final, roles=spec.roles, block=-1)

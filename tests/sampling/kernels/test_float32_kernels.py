"""Float32 sampler kernels (``Sampler(sp, precision="float32")``) against the float64 NumPy twin
fed the same noise, and the guards that keep float32 outcomes float64's.

Tolerance: float32 rollouts differ from double by rounding that the barrier 1/h amplifies near
the obstacles: measured relative error ~1e-6 / h_min (h_min the smallest margin a sample reaches
before it crashes, m^2): 1.5e-5 at h_min >= 0.05, 7.5e-5 at 0.01. Samples that keep
h_min >= :data:`H_OK` in both systems must agree per element to :data:`RTOL32` relative
(|a - b| <= RTOL32 max(|a|, |b|, 1)), a factor 5 above the measured worst; crash flags must
agree on every sample outside the guard band; the sampler's result (guards applied) must agree
on every crash flag. The mutated twins change outputs by orders of magnitude more.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from workbench.problem.barrier import embed_barrier
from workbench.problem.models import double_integrator
from workbench.problem.obstacles import Circle
from workbench.sampling.kernels import vector_math as vm
from workbench.sampling.kernels.compiled import CompiledKernel
from workbench.sampling.kernels.constants import GUARD_BAND, SamplerConstants
from workbench.sampling.kernels.flags import kernel_flags
from workbench.sampling.kernels.specs import mppi_spec
from workbench.sampling.kernels.verify import KernelMismatch, reference_rollout, verify_kernel
from workbench.sampling.problem import navigation_costs
from workbench.sampling.sampler import Sampler
from workbench.sampling.twin import mppi_twin, sais_twin

OBST = (Circle((2.0, 2.0), 0.8), Circle((3.5, 1.0), 0.5), Circle((1.0, 3.2), 0.6))
N, T = 1001, 30  # N not a multiple of the float32 lane count (8): padding is exercised
RTOL32 = 1e-4
H_OK = 0.05  # m^2: samples at least this far (in margin) from every obstacle
COSTS = ("S_nom", "S_real", "S_state_nom", "S_hat", "LR")


def rel(a, b) -> np.ndarray:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return np.abs(a - b) / np.maximum(np.maximum(np.abs(a), np.abs(b)), 1.0)


@pytest.fixture(scope="module")
def setup():
    model = embed_barrier(double_integrator(obstacles=OBST, u_limit=5.0))
    sp = navigation_costs(model)
    s32 = Sampler(sp, "compiled", "float32")
    s64 = Sampler(sp, "compiled")
    c = SamplerConstants(sigma=np.array([3.0, 2.4]), lam=1.3, nu_mix=0.1, u_min=model.u_min,
                         u_max=model.u_max, crash_cost=1e6, p=model.lift((4.0, 4.0, 0.0, 0.0)),
                         scene=model.scene_value, alpha=3000.0)
    return model, sp, s32, s64, c


def _min_margin_before_crash(sp, X, crashed) -> np.ndarray:
    """Smallest margin of each twin trajectory (N, T+1, nx) up to and including its crash."""
    n, t1 = X.shape[0], X.shape[1]
    H = np.asarray(sp.functions()["margins"].map(n * t1)(X.reshape(-1, sp.nx).T,
                                                         sp.model.scene_value)).T
    H = H.reshape(n, t1, -1).min(axis=2)[:, 1:]
    stop = np.where(crashed, np.argmax(H <= sp.eps_h, axis=1), H.shape[1] - 1)
    return np.array([H[i, : stop[i] + 1].min() for i in range(n)])


@pytest.fixture(scope="module")
def sais_case(setup):
    """Real and nominal starts 0.9 m off the line through the first obstacle, heading along
    it at 2 m/s (as in test_sampler_kernels): most samples pass, some hit it or graze it."""
    model, sp, s32, s64, c = setup
    rng = np.random.default_rng(2026)
    side = np.array([-1.0, 1.0]) / np.sqrt(2.0)
    heading = np.array([1.0, 1.0]) * np.sqrt(2.0)
    x0 = model.lift([*(np.array([1.0, 1.0]) + 0.9 * side), *heading])
    xs0 = model.lift([*(np.array([0.95, 0.95]) + 0.9 * side), *(heading + np.array([0.1, -0.1]))])
    U = rng.normal(0.0, 2.0, (T, 2))
    K = np.zeros((T, 2, 5))
    K[:, 0, 0] = K[:, 1, 1] = -2.0
    K[:, 0, 2] = K[:, 1, 3] = -1.5
    K += rng.normal(0.0, 0.5, K.shape)
    K[:, :, 4] = rng.normal(0.0, 0.3, (T, 2))
    seed = 7
    Z = np.transpose(s64.lib.normals(N, T, 2, seed), (2, 0, 1))
    # alpha between the two middle S_hat of the samples safe in both systems: the clamp binds
    # on about half of them
    free = twin(sp, x0, xs0, U, K, Z, replace(c, alpha=np.inf))
    Sh = np.sort(free["S_hat"][~free["crashed_real"] & ~free["crashed_nom"]])
    c = replace(c, alpha=float(0.5 * (Sh[Sh.size // 2 - 1] + Sh[Sh.size // 2])))
    k = s32.lib32.sais
    carry, consts = local(s32, {"x": x0, "x_nom": xs0}, c)
    raw = k(k.carry.pack(N, **carry), consts=consts, time_in={"u": U, "K": K.reshape(T, -1)},
            seed=seed, keep_noise=True)
    ref = twin(sp, x0, xs0, U, K, Z, c)
    h = np.minimum(_min_margin_before_crash(sp, ref["X"], ref["crashed_real"]),
                   _min_margin_before_crash(sp, ref["X_nom"], ref["crashed_nom"]))
    return {"x0": x0, "xs0": xs0, "U": U, "K": K, "seed": seed, "Z": Z, "raw": raw, "c": c,
            "r": k.result.unpack(raw.result), "ref": ref, "h_min": h}


def local(s32, carry: dict, c) -> tuple[dict, dict]:
    """A float32 kernel call's carry and constants in the sampler's local frame (the
    frame's origin the first start's position), as the sampler passes them."""
    fr, consts = s32.frame, c.kernel_consts()
    o = fr.origin(carry)
    return fr.carry(carry, o), fr.consts(consts, o)


def twin(sp, x0, xs0, U, K, Z, c, drop: str | None = None):
    """The float64 twin; ``drop`` a deliberately broken copy: "feedback" (K = 0),
    "alpha_clamp" (alpha = inf), "likelihood_ratio" (lambda (1 - nu_mix) = 0)."""
    if drop == "feedback":
        K = np.zeros_like(K)
    elif drop == "alpha_clamp":
        c = replace(c, alpha=np.inf)
    elif drop == "likelihood_ratio":
        c = replace(c, nu_mix=1.0)
    n = Z.shape[0]
    return sais_twin(sp, np.tile(x0, (n, 1)), np.tile(xs0, (n, 1)), U, K, Z, c, "numpy")


def mismatch(r, lane_out, ref, ok) -> dict[str, float]:
    """Largest per-element error over the samples ``ok`` of a kernel result and a twin."""
    out = {name: float(rel(r[name], ref[name])[ok].max()) for name in COSTS}
    for j, name in enumerate(("v_nom", "v_real")):
        out[name] = float(rel(lane_out[j], np.transpose(ref[name], (1, 2, 0)))[..., ok].max())
    return out


def test_float32_kernel_draws_the_float64_normals(setup, sais_case):
    s64 = setup[3]
    assert np.array_equal(sais_case["raw"].noise, s64.lib.normals(N, T, 2, sais_case["seed"]))
    idx = np.array([0, 5, 999, 1000])
    assert np.array_equal(s64.lib.normals_at(idx, T, 2, sais_case["seed"]),
                          sais_case["raw"].noise[..., idx])


def test_well_conditioned_samples_equal_the_twin_to_float32_tolerance(sais_case):
    ok = sais_case["h_min"] >= H_OK
    assert ok.sum() >= 0.5 * N
    err = mismatch(sais_case["r"], sais_case["raw"].lane_out, sais_case["ref"], ok)
    assert max(err.values()) <= RTOL32, err
    assert max(err.values()) > 1e-9, err  # really float32 (float64 agrees to ~1e-14)


@pytest.mark.parametrize("drop", ["feedback", "alpha_clamp", "likelihood_ratio"])
def test_a_broken_twin_fails_the_float32_comparison(setup, sais_case, drop):
    sp, s = setup[1], sais_case
    c = s["c"]
    ok = s["h_min"] >= H_OK
    broken = twin(sp, s["x0"], s["xs0"], s["U"], s["K"], s["Z"], c, drop)
    assert max(mismatch(s["r"], s["raw"].lane_out, broken, ok).values()) > 100 * RTOL32


def test_crash_flags_agree_outside_the_guard_band(setup, sais_case):
    sp, c = setup[1], sais_case["c"]
    r, ref, h = sais_case["r"], sais_case["ref"], sais_case["h_min"]
    guard = r["guard"] > 0
    assert 0 < guard.sum() < 0.1 * N
    for name in ("crashed_real", "crashed_nom"):
        assert 0 < ref[name].sum() < N
        assert np.array_equal((r[name] > 0)[~guard], ref[name][~guard]), name
    # every sample whose margin came within half the band of eps_h (float64) is flagged
    assert np.all(guard[np.abs(h - sp.eps_h) <= 0.5 * c.guard_band])


def test_sampler_recomputes_guarded_samples_in_float64(setup, sais_case):
    _, _, s32, s64, _ = setup
    s = sais_case
    c = s["c"]
    before = s32.guard.rechecked
    b32 = s32.sais(s["x0"], s["xs0"], s["U"], s["K"], N, c, s["seed"])
    b64 = s64.sais(s["x0"], s["xs0"], s["U"], s["K"], N, c, s["seed"])
    guard = s["r"]["guard"] > 0
    assert s32.guard.rechecked - before == guard.sum()
    for name in ("crashed_real", "crashed_nom"):
        assert np.array_equal(getattr(b32, name), s["ref"][name]), name
    for name in (*COSTS, "crashed_real", "crashed_nom"):
        assert np.array_equal(getattr(b32, name)[guard], getattr(b64, name)[guard]), name
    for name in ("v_nom", "v_real"):
        assert np.array_equal(getattr(b32, name)[..., guard], getattr(b64, name)[..., guard])
    assert np.array_equal(b32.S_nom[~guard], s["r"]["S_nom"][~guard])


def test_mppi_and_candidates_equal_the_twin(setup, sais_case):
    model, sp, s32, s64, c = setup
    x0, U, seed = sais_case["x0"], sais_case["U"], 11
    b = s32.mppi(x0, U, N, c, seed)
    Z = np.transpose(s64.lib.normals(N, T, 2, seed), (2, 0, 1))
    ref = mppi_twin(sp, np.tile(x0, (N, 1)), U, Z, c, "numpy")
    assert np.array_equal(b.crashed, ref["crashed"])
    ok = _min_margin_before_crash(sp, ref["X"], ref["crashed"]) >= H_OK
    assert ok.sum() >= 0.3 * N  # (a crashed sample's margin reaches eps_h: never "ok")
    assert rel(b.S, ref["S"])[ok].max() <= RTOL32
    assert rel(b.v, np.transpose(ref["v"], (1, 2, 0)))[..., ok].max() <= RTOL32
    # candidates: per-sample starts and strides
    starts = np.tile(x0, (N, 1))
    starts[:, 1] += np.linspace(-0.3, 0.3, N)
    starts = np.array([model.lift(s[:4]) for s in starts])
    stride = (np.arange(N) % 2).astype(float)
    S32 = s32.candidates(starts, U, stride, c, seed)
    S64 = s64.candidates(starts, U, stride, c, seed)
    Un = np.vstack([U[1:], U[-1:]])
    ref = mppi_twin(sp, starts, np.where(stride[:, None, None] > 0, Un[None], U[None]), Z,
                    c, "numpy", delay=stride)
    ok = _min_margin_before_crash(sp, ref["X"], ref["crashed"]) >= H_OK
    assert rel(S32, ref["S"])[ok].max() <= RTOL32
    assert 0 < rel(S32, S64)[ok].max()  # float32 ran
    k = s32.lib32.candidates  # the samples the guard sent to float64: exactly float64's
    carry, consts = local(s32, {"x": starts, "delay": stride, "stride": stride}, c)
    raw = k(k.carry.pack(N, **carry), consts=consts, time_in={"u": U, "u_next": Un}, seed=seed)
    guard = k.result.unpack(raw.result)["guard"] > 0
    assert guard.sum() > 0
    assert np.array_equal(S32[guard], S64[guard])


def test_no_crash_free_sample_reruns_the_batch_in_float64(setup):
    """5 cm from the first obstacle, heading into it at 5 m/s: every sample crashes at the
    first step (its position does not depend on the first control), so float32's crashed
    costs (of order beta_max^2) would decide the weights; the batch is float64's."""
    model, _, s32, s64, c = setup
    x0 = model.lift([2.0 - 0.85 / np.sqrt(2), 2.0 - 0.85 / np.sqrt(2), 3.5, 3.5])
    U = np.zeros((T, 2))
    before = s32.guard.reruns
    b32, b64 = s32.mppi(x0, U, 64, c, 3), s64.mppi(x0, U, 64, c, 3)
    assert b64.crashed.all()
    assert s32.guard.reruns == before + 1
    assert np.array_equal(b32.S, b64.S) and np.array_equal(b32.v, b64.v)


def test_float32_verification_rejects_another_kernel(setup):
    """Load-time verification at float32 tolerance: the library's own kernels pass (on
    well-conditioned points up to 10 in magnitude); a spec with other costs, run on the
    library's kernel, is refused; the float32 kernel is not float64 (it fails 1e-9)."""
    _, sp, s32, _, _ = setup
    verify_kernel(s32.lib32.mppi)
    other = mppi_spec(navigation_costs(sp.model, q_beta=3.0), precision="float32")
    with pytest.raises(KernelMismatch, match="wb_mppi_f32"):
        verify_kernel(CompiledKernel(other, s32.lib32.cdll))
    spec = s32.lib32.mppi.spec
    rng = np.random.default_rng(1)
    carry0 = rng.uniform(-0.5, 0.5, (9, spec.n_carry))
    consts = {n: rng.uniform(0.5, 1.5, spec.step.numel_in(n)) for n in spec.inputs("const")}
    time_in = {"u": rng.uniform(-1, 1, (3, 2))}
    noise = rng.standard_normal((3, 2, 9))
    got = s32.lib32.mppi(carry0, consts=consts, time_in=time_in, noise=noise)
    _, res = reference_rollout(spec, carry0, time_in, {}, consts, noise)
    assert np.max(rel(got.result, res)) > 1e-9


def test_float32_constants_and_precision_are_validated(setup):
    model, sp, s32, _, c = setup
    with pytest.raises(ValueError, match="precision"):
        Sampler(sp, precision="float16")
    with pytest.raises(ValueError, match=r"SamplerConstants\.sigma\[1\]"):
        replace(c, sigma=np.array([1.0, 1e-160]))  # sigma^2 underflows float64
    with pytest.raises(ValueError, match=r"SamplerConstants\.lam"):
        replace(c, lam=0.0)
    tiny = replace(c, sigma=np.array([1.0, 1e-20]))  # fine in float64, not in float32
    s64 = Sampler(sp, "compiled")
    s64.mppi(model.lift((0.5, 0.5, 0, 0)), np.zeros((T, 2)), 8, tiny, 1)
    with pytest.raises(ValueError, match=r"SamplerConstants\.sigma\[1\].*float32"):
        s32.mppi(model.lift((0.5, 0.5, 0, 0)), np.zeros((T, 2)), 8, tiny, 1)
    with pytest.raises(ValueError, match=r"SamplerConstants\.crash_cost.*float32"):
        s32.mppi(model.lift((0.5, 0.5, 0, 0)), np.zeros((T, 2)), 8,
                 replace(c, crash_cost=1e39), 1)
    with pytest.raises(ValueError, match=r"SamplerConstants\.guard_band"):
        replace(c, guard_band=-1.0)
    assert c.guard_band == GUARD_BAND


def test_float_vector_math_uses_simd_float_functions():
    """The float32 kernels' trigonometry calls libmvec's float variants (sinf...), which the
    probe finds within MAX_ULP float ulps of double libm rounded to float (else the kernels
    keep scalar calls); a unicycle's float32 kernels call them and pass the load-time check."""
    from pathlib import Path

    from benchmarks.trig import problem, unicycle
    from workbench.sampling.kernels.library import load_sampler_library
    from workbench.scenarios.scenes import NavigationScene

    assert vm.ulp_distance32(np.float32(1.0), np.nextafter(np.float32(1.0),
                                                           np.float32(2.0))) == 1.0
    decl = vm.declarations(["sin", "atan2"], "float32")
    assert "float sinf(float);" in decl and "float atan2f(float, float);" in decl
    why = vm.unavailable(kernel_flags("float32"), 8, "float32")
    if why is not None:
        pytest.skip(f"no float libmvec: {why}")
    lib = load_sampler_library(problem(unicycle(NavigationScene().obstacles())),
                               precision="float32")  # verified at load
    assert vm.simd_variants(Path(lib.cdll._name).read_bytes(), "float32") >= {"sin", "cos"}


def test_mppi_config_precision_reaches_the_sampler_and_is_validated(setup):
    """MPPIConfig(precision=...) selects the Sampler's kernels; bad values and float32-unsafe
    scales are refused naming the field."""
    from workbench.sampling.mppi import MPPI, MPPIConfig

    model, sp = setup[0], setup[1]
    goal = model.lift((4.0, 4.0, 0.0, 0.0))
    cfg = MPPIConfig(sigma=(2.0, 2.0), lam=1.0, n_samples=64, horizon=20, precision="float32")
    ctrl = MPPI(sp, goal, cfg)
    if ctrl.sampler.lib is not None:  # float64 only without a compiler
        assert ctrl.sampler.precision == "float32"
    assert MPPI(sp, goal, MPPIConfig(n_samples=64, horizon=20)).sampler.precision == "float64"
    with pytest.raises(ValueError, match=r"MPPIConfig\.precision"):
        MPPIConfig(precision="float16")
    with pytest.raises(ValueError, match=r"MPPIConfig.sigma\[0\]"):
        MPPIConfig(sigma=(1e-30, 1.0), precision="float32")  # sigma^2 underflows float32
    with pytest.raises(ValueError, match=r"MPPIConfig\.crash_cost"):
        MPPIConfig(crash_cost=1e39, precision="float32")

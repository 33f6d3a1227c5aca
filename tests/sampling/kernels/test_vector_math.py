"""Vector trigonometry in the generated kernels (workbench/sampling/kernels/vector_math.py).

The oracle is CasADi's own evaluation of the same Function (scalar glibc libm): the libmvec
kernels must be within MAX_ULP ulp of it for every function over wide argument ranges, must really
call the SIMD variants (a scalar build fails), and the scalar fallback must stay bitwise equal.
"""

from __future__ import annotations

from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from workbench.codegen import build_library
from workbench.sampling.kernels import vector_math as vm
from workbench.sampling.kernels.compiled import CompiledKernel
from workbench.sampling.kernels.emit import emit_kernel, rng_source
from workbench.sampling.kernels.flags import KERNEL_FLAGS, LANES
from workbench.sampling.kernels.library import load_sampler_library
from workbench.sampling.kernels.verify import reference_rollout

NAMES = [n for n, _ in vm.VECTOR_FUNCTIONS.values()]
AVAILABLE = vm.unavailable(KERNEL_FLAGS, LANES)
needs_libmvec = pytest.mark.skipif(AVAILABLE is not None, reason=f"no libmvec: {AVAILABLE}")


def _simd_calls(path) -> set[str]:
    return vm.simd_variants(path.read_bytes())


def test_ulp_distance_on_known_pairs():
    one = np.nextafter(1.0, 2.0)
    tiny = np.nextafter(0.0, 1.0)
    a = np.array([1.0, 1.0, 0.0, tiny, np.nan, np.nan, -1.0, 2.0, np.inf])
    b = np.array([1.0, one, -0.0, -tiny, np.nan, 1.0, np.nextafter(-1.0, 0.0), 1.0, np.inf])
    d = vm.ulp_distance(a, b)
    assert d[:6].tolist() == [0.0, 1.0, 0.0, 2.0, 0.0, np.inf]
    assert d[6] == 1.0 and d[7] == 2.0**52 and d[8] == 0.0


def test_environment_switch_is_validated(monkeypatch):
    monkeypatch.setenv(vm.ENV, "maybe")
    with pytest.raises(ValueError, match=r"^WORKBENCH_VECTOR_MATH = 'maybe' is invalid: "
                                         r"allowed values are 1, true, yes, on"):
        vm.enabled()
    x = ca.SX.sym("x")
    with pytest.raises(ValueError, match="WORKBENCH_VECTOR_MATH"):  # also without trigonometry
        vm.prelude([ca.Function("f", [x], [x * x])], KERNEL_FLAGS, LANES)
    monkeypatch.setenv(vm.ENV, "0")
    assert not vm.enabled()
    monkeypatch.delenv(vm.ENV)
    assert vm.enabled()


def test_models_without_trigonometry_get_no_declarations():
    x = ca.SX.sym("x", 2)
    f = ca.Function("f", [x], [ca.sqrt(x[0]) / x[1] + ca.exp(x[0])])
    assert vm.used([f]) == ()
    assert vm.prelude([f], KERNEL_FLAGS, LANES, True) == ""
    g = ca.Function("g", [x], [ca.atan2(x[0], x[1]) + ca.sin(x[0])])
    assert vm.used([f, g]) == ("atan2", "sin")


def _probe_kernel(tmp_path, declarations: str):
    spec = vm.probe_spec()
    lib = build_library("wbtest_vm", [], rng_source() + "\n" + declarations + emit_kernel(spec),
                        root=tmp_path, extra_flags=KERNEL_FLAGS)
    inp = vm.probe_inputs()
    lane_in = {k: inp[k][None, None, :] for k in ("x", "u", "y")}
    carry0 = np.full((inp["x"].size, 1), 0.25)
    time_in = {"w": np.full((1, 1), 0.5)}
    out = CompiledKernel(spec, lib.cdll)(carry0, consts={}, time_in=time_in, lane_in=lane_in)
    ref_lane, ref_res = reference_rollout(spec, carry0, time_in, lane_in, {}, None)
    return lib, out, ref_lane[0][0], ref_res


@needs_libmvec
def test_simd_variants_are_called_and_within_max_ulp_of_casadi(tmp_path):
    lib, out, ref, ref_res = _probe_kernel(tmp_path, vm.declarations(NAMES))
    assert _simd_calls(lib.path) == set(NAMES)
    got = out.lane_out[0][0]
    for j, name in enumerate(NAMES):
        d = vm.ulp_distance(got[j], ref[j])
        assert d.max() <= vm.MAX_ULP, (name, d.max())
    # the carry 0.25 + 0.5 sin(x): absolute error of MAX_ULP ulp of sin, plus rounding
    fin = np.isfinite(ref_res)
    assert np.array_equal(fin, np.isfinite(out.result))
    assert np.abs(out.result - ref_res)[fin].max() <= (0.5 * vm.MAX_ULP + 1) * np.spacing(0.75)
    # not vacuous: the variants differ from scalar libm somewhere for every function
    assert all((vm.ulp_distance(got[j], ref[j]) > 0).any() for j in range(len(NAMES)))


def test_scalar_calls_are_bitwise_casadi_and_not_simd(tmp_path):
    lib, out, ref, _ = _probe_kernel(tmp_path, "")
    assert _simd_calls(lib.path) == set()
    assert np.array_equal(out.lane_out[0][0], ref, equal_nan=True)


def _unicycle_problem():
    from benchmarks.trig import problem, unicycle
    from workbench.scenarios.scenes import NavigationScene

    return problem(unicycle(NavigationScene().obstacles()))


@needs_libmvec
@pytest.mark.parametrize("kernel", ["mppi", "sais", "candidates"])
def test_unicycle_kernels_use_simd_and_equal_casadi(kernel):
    sp = _unicycle_problem()
    vec, sca = load_sampler_library(sp, True), load_sampler_library(sp, False)
    assert _simd_calls(Path(vec.cdll._name)) >= {"sin", "cos"}  # the loaded file
    assert _simd_calls(Path(sca.cdll._name)) == set()
    k_vec, k_sca = getattr(vec, kernel), getattr(sca, kernel)
    rng = np.random.default_rng(5)
    N, T = 9, 30  # a padded partial block of lanes
    spec = k_vec.spec
    carry = spec.inputs("carry")[0]
    carry0 = np.zeros((N, spec.step.numel_in(carry)))
    carry0[:, :5] = sp.model.lift(np.array([0.5, 0.5, 0.7, 1.0]))
    carry0[:, :4] += rng.uniform(-0.2, 0.2, (N, 4))
    if kernel == "sais":
        carry0[:, 5:10] = carry0[:, :5]
    time_in = {n: rng.uniform(-1.0, 1.0, (T, spec.step.numel_in(n)))
               for n in spec.inputs("time")}
    consts = {n: rng.uniform(0.5, 1.5, spec.step.numel_in(n)) for n in spec.inputs("const")}
    noise = rng.standard_normal((T, spec.n_noise, N))
    ref_lane, ref_res = reference_rollout(spec, carry0, time_in, {}, consts, noise)
    got_v = k_vec(carry0, consts=consts, time_in=time_in, noise=noise)
    got_s = k_sca(carry0, consts=consts, time_in=time_in, noise=noise)
    assert np.array_equal(got_s.result, ref_res)  # scalar libm: bitwise CasADi
    scale = np.maximum(np.abs(ref_res), 1.0)
    assert np.all(np.abs(got_v.result - ref_res) <= 1e-12 * scale)
    for g, r in zip(got_v.lane_out, ref_lane, strict=True):
        assert np.all(np.abs(g - r) <= 1e-12 * np.maximum(np.abs(r), 1.0))


def test_libm_calls_are_emitted_right_after_their_inputs():
    """Fewer values live across a SIMD call (it clobbers every vector register); the order of
    everything else is kept, and the result is unchanged (the kernel tests above)."""
    from workbench.sampling.kernels.emit import straight_line

    a, b = ca.SX.sym("a"), ca.SX.sym("b")
    late = ((a * b + b) * (a - b) + 3.0 * a) * ca.cos(ca.sin(b) + a)
    f = ca.Function("f", [a, b], [late])
    body = straight_line(f, lambda i, nz: f"in{i}", lambda o, nz, e: f"out = {e};", "s")
    calls = [j for j, s in enumerate(body) if "sin(" in s or "cos(" in s]
    loads = {s.split()[2]: j for j, s in enumerate(body) if "= in" in s}
    first_b = min(j for name, j in loads.items() if body[j].endswith("in1;"))
    assert calls[0] == first_b + 1  # sin(b) right after b is loaded
    assert body[-1].startswith("out = ")

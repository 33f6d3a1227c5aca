"""The kernel emitter: libm operations written as CasADi evaluates them, unsupported ones
named."""

from __future__ import annotations

import numpy as np
import pytest


def _tiny_spec(expr_of):
    """A one-state kernel whose step applies ``expr_of(x)`` (SX) to the carry."""
    import casadi as ca

    from workbench.sampling.kernels.emit import KernelSpec

    c, z, w, s = (ca.SX.sym(n, 1) for n in ("carry", "z", "w", "s"))
    step = ca.Function("wbrel_k_step", [c, z, w, s],
                       [ca.vertcat(expr_of(0.3 * c + 0.1 * z + w)), s * c],
                       ["carry", "z", "w", "s"], ["carry_next", "y"])
    final = ca.Function("wbrel_k_final", [c, s], [c * s], ["carry", "s"], ["result"])
    return KernelSpec(name="wbrel_k", step=step, final=final,
                      roles={"carry": "carry", "z": "noise", "w": "time", "s": "const"})


_LIBM_OPS = {
    "asin": lambda v: __import__("casadi").asin(v), "acos": lambda v: __import__("casadi").acos(v),
    "sinh": lambda v: __import__("casadi").sinh(v), "cosh": lambda v: __import__("casadi").cosh(v),
    "erf": lambda v: __import__("casadi").erf(v), "asinh": lambda v: __import__("casadi").asinh(v),
    "acosh": lambda v: __import__("casadi").acosh(1.5 + v * v),
    "atanh": lambda v: __import__("casadi").atanh(0.5 * v),
    "remainder": lambda v: __import__("casadi").remainder(3.0 * v, 0.7),
}


@pytest.mark.parametrize("op", sorted(_LIBM_OPS))
def test_class4_emitter_writes_libm_operations_equal_to_casadi(op, tmp_path):
    from workbench.codegen import build_library
    from workbench.sampling.kernels.compiled import CompiledKernel
    from workbench.sampling.kernels.emit import emit_kernel, rng_source

    spec = _tiny_spec(_LIBM_OPS[op])
    lib = build_library("wbrel_ops", [], rng_source() + emit_kernel(spec), root=tmp_path,
                        extra_flags=("-fopenmp",))
    rng = np.random.default_rng(1)
    N, T = 6, 3
    carry0, w = rng.uniform(-0.5, 0.5, (N, 1)), rng.uniform(-0.5, 0.5, (T, 1))
    s, noise = np.array([0.7]), rng.standard_normal((T, 1, N))
    out = CompiledKernel(spec, lib.cdll)(carry0, consts={"s": s}, time_in={"w": w}, noise=noise)
    for n in range(N):  # CasADi's evaluation of the same step, sample by sample
        c = carry0[n]
        for t in range(T):
            c_next, y = (float(v) for v in spec.step(c, noise[t, 0, n], w[t], s))
            assert out.lane_out[0][t, 0, n] == pytest.approx(y, rel=1e-13, abs=1e-300)
            c = c_next
        assert out.result[n, 0] == pytest.approx(float(spec.final(c, s)), rel=1e-13)
    assert np.isfinite(out.result).all()


def test_class4_unsupported_operation_is_named_with_the_supported_list():
    import casadi as ca

    from workbench.sampling.kernels.emit import EmitError, emit_kernel

    with pytest.raises(EmitError, match=r"operation erfinv, which .* supported: acos, acosh"):
        emit_kernel(_tiny_spec(lambda v: ca.erfinv(0.5 * ca.tanh(v))))

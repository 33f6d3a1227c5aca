"""FastFunction (buffer interface) against the ordinary CasADi call."""

from __future__ import annotations

import casadi as ca
import numpy as np

from workbench.codegen.fastcall import FastFunction


def test_fast_function_equals_casadi_call(rng):
    x, u = ca.SX.sym("x", 3), ca.SX.sym("u", 2)
    f = ca.Function("f", [x, u], [ca.vertcat(ca.sin(x[0]) * u[1], 0, x[2] / u[0]), x[1] ** 2])
    fast = FastFunction(f)
    for _ in range(5):
        a, b = rng.normal(size=3), rng.normal(size=2)
        got = fast(a, b)
        ref = [np.asarray(r, float).ravel() for r in f(a, b)]
        for g, r in zip(got, ref, strict=True):
            np.testing.assert_array_equal(g, r)  # the same VM evaluation, bitwise


def test_mapped_fast_function_is_one_column_per_row(rng):
    x = ca.SX.sym("x", 2)
    f = ca.Function("g", [x], [ca.vertcat(x[0] * x[1], x[0] - x[1], 1.0 / x[1])])
    fast = FastFunction(f, 7)
    X = rng.normal(size=(7, 2))
    out = fast(X)[0].reshape(7, 3)
    np.testing.assert_array_equal(out, np.stack([np.asarray(f(r)).ravel() for r in X]))

"""Issue 9 (reliability): every bad input gets a clear error naming the field, no fault
corrupts a result, generated code is verified before it runs. One section per defect class."""

from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import pytest

from workbench.ecbf import ECBFFilter, ECBFOptions
from workbench.models import double_integrator
from workbench.obstacles import Circle

ECBF_OBSTACLES = (Circle((0.0, 0.1), 1.5), Circle((0.5, 2.0), 0.7))
X_ACTIVE = np.array([-1.7, 0.1, 3.0, 0.0])  # near the first obstacle, moving towards it
U_TOWARDS = np.array([10.0, 0.0])


def _filter(**options) -> ECBFFilter:
    return ECBFFilter(double_integrator(obstacles=ECBF_OBSTACLES, u_limit=15.0),
                      ECBFOptions(**options))


# ---------------------------------------------------------------------------------------------
# class 1: an interrupt inside the QP solve must propagate, not become a fallback step


def _endless(filt: ECBFFilter) -> ECBFFilter:
    """Make every OSQP solve run until interrupted (no termination checks, huge max_iter)."""
    filt._solver.update_settings(max_iter=10**9, check_termination=0)
    return filt


def _sigint_after(seconds: float) -> threading.Timer:
    timer = threading.Timer(seconds, lambda: os.kill(os.getpid(), signal.SIGINT))
    timer.start()
    return timer


@pytest.mark.parametrize("call", ["single", "batch"])
def test_class1_sigint_inside_osqp_raises_keyboard_interrupt_promptly(call):
    filt = _endless(_filter())
    t0 = time.perf_counter()
    timer = _sigint_after(0.3)
    try:
        with pytest.raises(KeyboardInterrupt):
            if call == "single":
                filt(X_ACTIVE, U_TOWARDS)
            else:
                filt.filter_batch(np.array([X_ACTIVE, X_ACTIVE]), np.array([U_TOWARDS] * 2))
    finally:
        timer.cancel()
    assert time.perf_counter() - t0 < 5.0


def test_class1_filter_is_usable_after_an_interrupt():
    filt = _endless(_filter())
    timer = _sigint_after(0.3)
    try:
        with pytest.raises(KeyboardInterrupt):
            filt(X_ACTIVE, U_TOWARDS)
    finally:
        timer.cancel()
    res = filt(X_ACTIVE, U_TOWARDS)  # the workspace was set up afresh (normal settings)
    assert res.status == "solved" and not res.fallback_used
    np.testing.assert_allclose(res.u, _filter()(X_ACTIVE, U_TOWARDS).u, atol=1e-9)


def test_class1_interrupted_status_is_never_a_fallback(monkeypatch):
    """The status OSQP returns after catching SIGINT maps to KeyboardInterrupt (no signal)."""
    import osqp

    filt = _filter()
    real = filt._solver

    class Interrupted:
        def update(self, **kw):
            real.update(**kw)

        def solve(self, raise_error=False):
            res = real.solve(raise_error=False)
            res.info.status, res.info.status_val = "interrupted", osqp.SolverStatus.OSQP_SIGINT
            return res

    filt._solver = Interrupted()
    with pytest.raises(KeyboardInterrupt):
        filt(X_ACTIVE, U_TOWARDS)


# ---------------------------------------------------------------------------------------------
# class 2: a NaN state must not poison the OSQP workspace


@pytest.mark.parametrize("bad", [
    [np.nan, 0.1, 3.0, 0.0], [-1.7, np.inf, 3.0, 0.0], [-1.7, 0.1, 3.0, -np.inf]])
def test_class2_non_finite_state_is_rejected_before_the_solver(bad):
    filt = _filter()
    with pytest.raises(ValueError, match=r"^x = .* finite"):
        filt(np.array(bad), U_TOWARDS)
    res = filt(X_ACTIVE, U_TOWARDS)  # the next normal step is solved, not a fallback
    assert res.status == "solved" and not res.fallback_used


def test_class2_non_finite_batch_state_names_the_row():
    X = np.array([X_ACTIVE, [np.nan, 0.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match=r"(?s)^X = .*row 1"):
        _filter().filter_batch(X, np.array([U_TOWARDS] * 2))


@pytest.mark.parametrize("field", ["a", "b"])
def test_class2_non_finite_rows_are_rejected(field):
    filt = _filter()
    a, b = filt.rows(X_ACTIVE)
    (a if field == "a" else b)[0] = np.nan
    with pytest.raises(ValueError, match=rf"(?s)^{field} = .*finite"):
        filt.solve_rows(a, b, U_TOWARDS)
    assert filt(X_ACTIVE, U_TOWARDS).status == "solved"


def test_class2_broken_workspace_is_reset_and_the_step_solved(capfd):
    """A workspace left broken (non-quasidefinite KKT after NaN data reached OSQP) is set up
    afresh on the error status: the step is solved, and so are the later ones."""
    filt = _filter()
    expected = _filter()(X_ACTIVE, U_TOWARDS).u
    filt._solver.update(Ax=np.full_like(filt._Ax, np.nan))
    for _ in range(3):
        res = filt(X_ACTIVE, U_TOWARDS)
        assert res.status == "solved" and not res.fallback_used
        np.testing.assert_allclose(res.u, expected, atol=1e-9)
    capfd.readouterr()


# class 7 (ECBF part): a state of the wrong length names the state, not numpy broadcasting


@pytest.mark.parametrize("x", [[1.0, 2.0], [1.0, 2.0, 3.0, 4.0, 5.0], [[-1.7, 0.1, 3.0, 0.0]]])
def test_class7_ecbf_state_of_wrong_shape_names_x(x):
    with pytest.raises(ValueError, match=r"^x = .*shape \(4,\)"):
        _filter()(x, U_TOWARDS)


def test_class7_ecbf_batch_of_wrong_width_names_X():
    with pytest.raises(ValueError, match=r"(?s)^X = .*shape \(N, 4\)"):
        _filter().filter_batch(np.zeros((3, 2)), np.zeros((3, 2)))


# ---------------------------------------------------------------------------------------------
# class 6: environment overrides that break or weaken the build


def _tiny_function():
    import casadi as ca

    x = ca.SX.sym("x", 2)
    return ca.Function("wbrel_tiny", [x], [ca.vertcat(x[0] * x[1], ca.exp(x[0]))], ["x"], ["y"])


def test_class6_extra_cflags_are_appended_to_the_required_ones(monkeypatch, tmp_path):
    from workbench.codegen import build_library, find_toolchain
    from workbench.codegen.toolchain import DEFAULT_FLAGS

    monkeypatch.setenv("WORKBENCH_CFLAGS", "-O2")
    tc = find_toolchain()
    assert tc.flags == (*DEFAULT_FLAGS, "-O2")
    assert {"-shared", "-fPIC"} <= set(tc.flags)
    lib = build_library("wbrel_cflags", [_tiny_function()], root=tmp_path)
    np.testing.assert_allclose(np.asarray(lib.functions["wbrel_tiny"]([0.5, 2.0])).ravel(),
                               [1.0, np.exp(0.5)])


@pytest.mark.parametrize("flag", ["-ffast-math", "-Ofast", "-funsafe-math-optimizations",
                                  "-ffinite-math-only", "-ffp-contract=fast", "-fno-honor-nans"])
def test_class6_flags_changing_floating_point_semantics_are_refused(monkeypatch, flag):
    from workbench.codegen import find_toolchain

    monkeypatch.setenv("WORKBENCH_CFLAGS", f"-O2 {flag}")
    with pytest.raises(ValueError, match=rf"^WORKBENCH_CFLAGS = .*{flag} changes floating-point"):
        find_toolchain()


def test_class6_missing_workbench_cc_is_named_with_the_compiler_used(monkeypatch):
    from workbench.codegen import find_toolchain

    monkeypatch.delenv("WORKBENCH_CFLAGS", raising=False)
    monkeypatch.setenv("WORKBENCH_CC", "/nonexistent/wbrel-cc")
    with pytest.warns(RuntimeWarning, match=r"WORKBENCH_CC = '/nonexistent/wbrel-cc'.*using /"):
        tc = find_toolchain()
    assert tc is not None and tc.cc != "/nonexistent/wbrel-cc"

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

"""The kernels' thread policy (workbench/sampling/kernels/threads.py): sleeping idle threads,
1 thread for small batches or busy cores, exactly n when asked, results independent of it."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import numpy as np
import pytest

from workbench.sampling.kernels import threads
from workbench.sampling.kernels.library import get_threads, set_threads

BIG = 10 * threads.SMALL_WORK


@pytest.fixture
def policy():
    """Restore the process's thread settings after a test."""
    saved = dict(threads._STATE)
    yield threads
    threads._STATE.clear()
    threads._STATE.update(saved)
    threads._APPLIED.clear()
    for s in threads._SETTERS:
        s(int(saved["max"] or 1))


def test_small_batches_and_busy_cores_run_on_one_thread(policy, monkeypatch):
    free = {"v": 2.0}
    monkeypatch.setattr(threads._LOAD, "free_cores", lambda: free["v"])
    set_threads(2)
    assert get_threads() == 2
    assert threads.threads_for(threads.SMALL_WORK - 1) == 1
    assert threads.threads_for(BIG) == 2
    for v, want in ((1.6, 2), (1.4, 1), (1.0, 1), (0.0, 1)):  # 2 threads: 1.5 cores free
        free["v"] = v
        assert threads.threads_for(BIG) == want, v
    set_threads(4)
    free["v"] = 2.6
    assert threads.threads_for(BIG) == 3
    set_threads(2, adaptive=False)  # exactly n, whatever the load and size
    free["v"] = 0.0
    assert threads.threads_for(1) == 2 and not threads.is_adaptive()
    monkeypatch.setattr(threads._LOAD, "free_cores", lambda: None)  # no /proc/stat
    set_threads(2)
    assert threads.threads_for(BIG) == 2 and threads.threads_for(1) == 1


def test_set_threads_is_validated(policy):
    with pytest.raises(ValueError, match="threads"):
        set_threads(0)
    with pytest.raises(ValueError, match="adaptive"):
        set_threads(2, adaptive="yes")
    set_threads("auto")
    assert get_threads() == len(os.sched_getaffinity(0))


def test_the_count_is_set_only_when_it_changes(policy, monkeypatch):
    monkeypatch.setattr(threads._LOAD, "free_cores", lambda: 8.0)
    set_threads(2)
    calls = []
    for work in (BIG, BIG, 1, 1, BIG):
        threads.apply(calls.append, work)
    assert calls == [2, 1, 2]


def test_the_load_probe_sees_busy_cores(policy, monkeypatch):
    """As many busy processes as cores: the probe finds (almost) no core free, so a large
    batch runs on 1 thread."""
    cores = len(os.sched_getaffinity(0))
    if cores > 8:
        pytest.skip("too many cores to load in a test")
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(cores)]
    try:
        time.sleep(0.3)
        probe = threads._LoadProbe()
        probe.free_cores()
        time.sleep(threads.WINDOW_S + 0.2)
        free = probe.free_cores()
    finally:
        for p in busy:
            p.kill()
            p.wait()
    assert free is not None and free < 0.75, free
    monkeypatch.setattr(threads._LOAD, "free_cores", lambda: free)
    set_threads(cores)
    assert threads.threads_for(BIG) == 1


def test_wait_policy_is_passive_unless_the_user_set_one(monkeypatch):
    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
    monkeypatch.delenv("GOMP_SPINCOUNT", raising=False)
    threads.prepare_runtime()
    assert os.environ["OMP_WAIT_POLICY"] == "passive"
    monkeypatch.delenv("OMP_WAIT_POLICY")
    monkeypatch.setenv("GOMP_SPINCOUNT", "1000")
    threads.prepare_runtime()
    assert "OMP_WAIT_POLICY" not in os.environ
    monkeypatch.setenv("OMP_WAIT_POLICY", "active")
    threads.prepare_runtime()
    assert os.environ["OMP_WAIT_POLICY"] == "active"


def test_a_fresh_process_loads_the_kernels_with_passive_threads():
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    code = ("import os\n"
            "from workbench.problem.models import double_integrator\n"
            "from workbench.problem.obstacles import Circle\n"
            "from workbench.problem.barrier import embed_barrier\n"
            "from workbench.sampling.problem import navigation_costs\n"
            "from workbench.sampling.kernels.library import sampler_library\n"
            "m = embed_barrier(double_integrator(obstacles=(Circle((2.0, 2.0), 0.8),)))\n"
            "lib = sampler_library(navigation_costs(m))\n"
            "print(lib is not None, os.environ.get('OMP_WAIT_POLICY'))\n")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=600, check=True).stdout.split()
    if out[0] != "True":
        pytest.skip("no C compiler")
    assert out[1] == "passive"


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_results_do_not_depend_on_the_thread_count(policy, precision):
    from workbench.problem.barrier import embed_barrier
    from workbench.problem.models import double_integrator
    from workbench.problem.obstacles import Circle
    from workbench.sampling.kernels.constants import SamplerConstants
    from workbench.sampling.problem import navigation_costs
    from workbench.sampling.sampler import Sampler

    model = embed_barrier(double_integrator(obstacles=(Circle((2.0, 2.0), 0.8),), u_limit=5.0))
    sp = navigation_costs(model)
    s = Sampler(sp, "compiled", precision)
    c = SamplerConstants(sigma=np.array([3.0, 3.0]), lam=1.0, nu_mix=0.0, u_min=model.u_min,
                         u_max=model.u_max, crash_cost=1e6, p=model.lift((4.0, 4.0, 0, 0)),
                         alpha=2e3)
    x0 = model.lift((1.0, 1.0, 1.0, 1.0))
    U, K = np.zeros((40, 2)), np.zeros((40, 2, 5))
    out = []
    for n in (1, 2):
        set_threads(n, adaptive=False)
        b = s.sais(x0, x0, U, K, 2000, c, 5)
        assert s.lib.cdll.wb_get_threads() == n  # the call ran on n threads
        out.append(b)
    for f in ("S_nom", "S_real", "crashed_real", "v_nom", "v_real"):
        assert np.array_equal(getattr(out[0], f), getattr(out[1], f)), f

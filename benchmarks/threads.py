"""Threads on a busy machine: 1-thread vs 2-thread sampler kernels, quiet and under a synthetic
load of two busy processes (``while True: pass``, as many as the cores of a 2-core machine).

``bench_threads(repeats)`` measures, for each OpenMP policy, in a fresh process (the wait
policy is read when the OpenMP runtime loads):

* ``spin_fixed`` — the previous behaviour: libgomp's default wait (idle threads spin, 300000
  iterations) and exactly the requested count;
* ``passive_fixed`` — idle threads sleep (``OMP_WAIT_POLICY=passive``), exactly the count;
* ``passive_adaptive`` — the library's default (:mod:`workbench.sampling.kernels.threads`):
  sleeping threads and the adaptive count (1 thread for small batches or when other processes
  keep the cores busy).

and, in each, the medians of a SAIS batch (N = 256, T = 40 and N = 1024, T = 100, the sampler
call) and of the SA-RMPPI control step (navigation map, N = 1024, T = 100, 9 x 64 candidates)
with ``set_threads(1)`` and ``set_threads(2)``, alternated call by call so load changes hit both.
Record value = the 2-thread median, baseline = the 1-thread median, ratio = baseline / value
(1 = no difference; below 1/1.3 = 0.77 the 2-thread setting is more than 1.3x slower).
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import time

POLICIES = {
    "spin_fixed": ({"GOMP_SPINCOUNT": "300000"}, False),
    "passive_fixed": ({"OMP_WAIT_POLICY": "passive"}, False),
    "passive_adaptive": ({}, True),
}
LOAD = 2  # busy processes (the cores of the 2-core machine this targets)
GOAL_RATIO = 1 / 1.3


def _busy(n: int) -> list[subprocess.Popen]:
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def _order(i: int) -> tuple[int, int]:
    """The thread counts of round i: 1 then 2, then 2 then 1, ... Under load, a call either
    runs through or loses the core for a whole scheduler time slice (two configurations that
    both ran on 1 thread, timed in blocks of 8 calls, differed 2.2x in one run); alternating
    call by call lets both counts meet the same phases of the other processes."""
    return (1, 2) if i % 2 == 0 else (2, 1)


def _measure(adaptive: bool, repeats: int) -> dict:
    """Runs in the child process: medians (ms) of 1- and 2-thread calls."""
    import casadi as ca
    import numpy as np

    from benchmarks.sampling import _setup
    from workbench.codegen.fastcall import FastFunction
    from workbench.sampling.kernels.library import set_threads
    from workbench.sampling.sampler import Sampler
    from workbench.sampling.threshold import ConstantThreshold

    nav, sp, U, K, c = _setup()
    sampler = Sampler(sp, "compiled")
    x0 = sp.model.lift(nav.x0)
    out: dict = {}
    blocks = max(3, repeats)
    get = sampler.lib.cdll.wb_get_threads
    used: dict[str, dict[int, list[int]]] = {}
    for N, T in ((256, 40), (1024, 100)):
        times: dict[int, list[float]] = {1: [], 2: []}
        ran = used.setdefault(f"sais_N{N}_T{T}", {1: [], 2: []})
        for i in range(8 * blocks):
            for n in _order(i):
                set_threads(n, adaptive=adaptive)
                t0 = time.perf_counter()
                sampler.sais(x0, x0, U[:T], K[:T], N, c, i)
                times[n].append(time.perf_counter() - t0)
                ran[n].append(get())
        out[f"sais_N{N}_T{T}"] = {n: 1e3 * statistics.median(v) for n, v in times.items()}
    ctrl = nav.controller("sa_rmppi", threshold=ConstantThreshold(2e4))
    f = FastFunction(ca.Function("plant", [nav.plant.x, nav.plant.u], [nav.plant.x_next]))
    rng = np.random.default_rng(0)
    state, x = ctrl.initial_state(nav.x0), np.asarray(nav.x0, float)
    steps: dict[int, list[float]] = {1: [], 2: []}
    ran = used.setdefault("sa_rmppi_step", {1: [], 2: []})
    for _ in range(5):  # warm-up: the feedback law's first solve
        state, u, _info = ctrl.step(state, x, rng)
    for i in range(6 * blocks):
        for n in _order(i):
            set_threads(n, adaptive=adaptive)
            t0 = time.perf_counter()
            state, u, _info = ctrl.step(state, x, rng)
            steps[n].append(time.perf_counter() - t0)
            ran[n].append(get())
            x = f(x, u)[0]
            if np.linalg.norm(x[:2] - nav.goal[:2]) < 1.0:  # start over near the goal
                state, x = ctrl.initial_state(nav.x0), np.asarray(nav.x0, float)
    out["sa_rmppi_step"] = {n: 1e3 * statistics.median(v) for n, v in steps.items()}
    # the share of calls (of the last kernel call of a step) that ran on 2 threads
    return {k: {**v, "two_thread_share": float(np.mean(np.array(used[k][2]) == 2))}
            for k, v in out.items()}


def _child(policy: str, load: int, repeats: int) -> dict:
    env_extra, adaptive = POLICIES[policy]
    env = {k: v for k, v in os.environ.items()
           if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "OMP_NUM_THREADS")}
    env.update(env_extra)
    code = ("import json, sys; from benchmarks.threads import _measure; "
            f"print(json.dumps(_measure({adaptive!r}, {repeats})))")
    procs = _busy(load)
    try:
        time.sleep(0.5 if load else 0.0)
        r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                           text=True, timeout=1800, check=True,
                           cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    finally:
        for p in procs:
            p.kill()
            p.wait()
    return {k: {(int(n) if n.isdigit() else n): v for n, v in d.items()} for k, d in
            json.loads(r.stdout.strip().splitlines()[-1]).items()}


def bench_threads(repeats: int) -> list[dict]:
    """One record per policy, load (0 or 2) and workload (see module docstring)."""
    from benchmarks.__main__ import record

    out = []
    for policy in POLICIES:
        for load in (0, LOAD):
            res = _child(policy, load, repeats)
            for work, t in res.items():
                out.append(record(
                    f"threads_{work}_{policy}_load{load}", t[2], "ms",
                    "same_call_1_thread_ms", t[1],
                    {"threads": 2, "load_processes": load, "policy": policy,
                     "two_thread_share": t["two_thread_share"],
                     "cores": os.cpu_count(), "goal_ratio": round(GOAL_RATIO, 3)
                     if work == "sa_rmppi_step" and load else None,
                     "includes": "the sampler call" if work.startswith("sais")
                     else "the SA-RMPPI control step (selection, K_safe, SAIS, update)"}))
    return out


if __name__ == "__main__":
    for r in bench_threads(int(sys.argv[1]) if len(sys.argv) > 1 else 3):
        print(f"{r['name']:52s} 2 threads {r['value']:8.3f} ms  1 thread "
              f"{r['baseline_value']:8.3f} ms  ratio {r['ratio']:.2f}  ran on 2: "
              f"{r['params']['two_thread_share']:.2f}")

"""Float32 against float64 sampler kernels on the same batches (1 thread): the SAIS and MPPI
batches of the navigation benchmark (N = 1024, T = 100, 30 circles) and the SA-RMPPI control
step, each timed in turn with its float64 twin in one process.

Record value = float32 median, baseline = float64 median, ratio = float64 / float32 (the
speed-up; goal 1.8 for the SAIS batch). A batch time is the sampler call: noise, rollout,
costs and, for float32, the guards (samples near the crash margin recomputed in float64; whole
batches recomputed when no sample is crash-free), whose activity is recorded. ``kernel_ratio``
is the same ratio for the bare kernel calls (no guards, no Python wrapping). No rollout-only
ratio is given: a kernel fed a noise array reads it with a stride of N samples from one
step to the next (a cache miss per step and sample block), which in one run made the float64
kernel fed the noise slower than the one drawing it, so seeded minus given noise is not the
generator's cost.

The calls are timed in blocks (:func:`benchmarks.timing.round_robin`: 4 timed calls of one
function after 1 untimed, the functions in turn), as the split and the robust step are: a
controller calls one precision's kernels over and over. Timed call by call in alternation,
each call first reloads what the other precision's call evicted from the caches, and that
fixed cost weighs more on the faster float32 call (the float32 SAIS kernel measured 1.85 ms
right after a float64 call, 1.37 ms in a block); those figures are kept as
``alternated_ratio`` and ``alternated_kernel_ratio``. ``cpu_ratio`` compares the calls' median
CPU (thread) times and ``*_ratio_q10`` their 10th percentiles (the calls least disturbed by
other work on a shared machine).
"""

from __future__ import annotations

import statistics

import numpy as np

from benchmarks.sampling import _setup
from benchmarks.timing import samples_in_turn
from workbench.sampling.kernels.threads import using
from workbench.sampling.sampler import Sampler, check_batch

GOAL = 1.8


def _record(name, value, unit, baseline, baseline_value, params) -> dict:
    from benchmarks.__main__ import record

    return record(name, value, unit, baseline, baseline_value, params)


def _alternate(calls: dict, n: int, block: int = 1, warm: int = 0) -> dict[str, dict[str, float]]:
    """Median wall and CPU (thread) time and the CPU time's 10th percentile of each call: the
    calls in turn n times, each turn ``warm`` untimed then ``block`` timed calls of one."""
    t = samples_in_turn(calls, n, block, warmup=0, warm=warm)
    return {k: {"wall": statistics.median(w), "cpu": statistics.median(c),
                "cpu_q10": float(np.quantile(c, 0.1))} for k, (w, c) in t.items()}


def _batch_records(repeats: int) -> list[dict]:
    nav, sp, U, K, c = _setup()
    s64, s32 = Sampler(sp, "compiled"), Sampler(sp, "compiled", "float32")
    x0 = sp.model.lift(nav.x0)
    N, T = 1024, U.shape[0]
    _, ck = check_batch(sp, N, U, c)
    consts = ck.kernel_consts()
    out = []
    for kind in ("sais", "mppi"):
        if kind == "sais":
            def call(s, i):
                return s.sais(x0, x0, U, K, N, c, i)

            def bare(lib, i):
                k = lib.sais
                return k(k.carry.pack(N, x=x0, x_nom=x0), consts=consts,
                         time_in={"u": U, "K": K.reshape(T, -1)}, seed=i)
        else:
            def call(s, i):
                return s.mppi(x0, U, N, c, i)

            def bare(lib, i):
                k = lib.mppi
                return k(k.carry.pack(N, x=x0), consts=consts, time_in={"u": U}, seed=i)
        g0 = (s32.guard.samples, s32.guard.rechecked, s32.guard.batches, s32.guard.reruns)
        rounds = max(repeats, 5) * 3
        calls = {"64": lambda i, f=call: f(s64, i), "32": lambda i, f=call: f(s32, i),
                 "k64": lambda i, f=bare: f(s64.lib, i),
                 "k32": lambda i, f=bare: f(s32.lib32, i)}
        t = _alternate(calls, rounds, block=4, warm=1)
        alt = _alternate(calls, rounds * 2)
        g = s32.guard
        samples, rechecked = g.samples - g0[0], g.rechecked - g0[1]
        a, b = call(s64, 1), call(s32, 1)
        flags = [f for f in vars(a) if f.startswith("crashed")]
        out.append(_record(
            f"{kind}_batch_N{N}_T{T}_1thread_float32", 1e3 * t["32"]["wall"], "ms",
            "same_batch_float64_ms", 1e3 * t["64"]["wall"],
            {"N": N, "T": T, "threads": 1, "goal_ratio": GOAL if kind == "sais" else None,
             "kernel_ratio": t["k64"]["wall"] / t["k32"]["wall"],
             "kernel64_ms": 1e3 * t["k64"]["wall"], "kernel32_ms": 1e3 * t["k32"]["wall"],
             "alternated_ratio": alt["64"]["wall"] / alt["32"]["wall"],
             "alternated_kernel_ratio": alt["k64"]["wall"] / alt["k32"]["wall"],
             "timing": "blocks of 4 timed calls after 1 untimed, the calls in turn",
             "cpu_ratio": t["64"]["cpu"] / t["32"]["cpu"],
             "kernel_cpu_ratio": t["k64"]["cpu"] / t["k32"]["cpu"],
             "cpu_ratio_q10": t["64"]["cpu_q10"] / t["32"]["cpu_q10"],
             "kernel_cpu_ratio_q10": t["k64"]["cpu_q10"] / t["k32"]["cpu_q10"],
             "guard_rechecked_fraction": rechecked / samples if samples else 0.0,
             "guard_rerun_batches": g.reruns - g0[3],
             "crash_flags_equal": all(np.array_equal(getattr(a, f), getattr(b, f))
                                      for f in flags),
             "lanes": {"float64": s64.lib.sais.spec.lanes,
                       "float32": s32.lib32.sais.spec.lanes},
             "includes": "the sampler call (noise, rollout, costs, float32 guards)"}))
    return out


def _step_record(steps: int) -> dict:
    from workbench.sampling.threshold import ConstantThreshold
    from workbench.sim import Disturbance, closed_loop

    nav = navigation_setup_cached()
    thr = ConstantThreshold(2e4)
    ctrls = {}
    for p in ("float64", "float32"):
        ctrl = nav.controller("sa_rmppi", threshold=thr)
        ctrl.sampler = Sampler(ctrl.sp, ctrl.cfg.backend, p)
        ctrl.mppi.sampler = ctrl.sampler
        ctrls[p] = ctrl
    times: dict[str, list[float]] = {p: [] for p in ctrls}
    for block in range(4):  # alternate episodes (the same streams for both precisions)
        for p, ctrl in ctrls.items():
            ep = closed_loop(ctrl, nav.plant, nav.x0, steps // 4, np.random.default_rng(block),
                             np.random.default_rng(100 + block), Disturbance(10.0),
                             keep_infos=False)
            times[p] += list(ep.step_time_s[5:])  # after the feedback law's first solves
    m = {p: 1e3 * statistics.median(v) for p, v in times.items()}
    g = ctrls["float32"].sampler.guard
    return _record("sa_rmppi_step_N1024_T100_1thread_float32", m["float32"], "ms",
                   "same_step_float64_ms", m["float64"],
                   {"steps": steps, "threads": 1, "disturbance_variance": 10.0,
                    "guard": {**g.fractions(), "batches": g.batches},
                    "includes": "the SA-RMPPI control step (selection, K_safe, SAIS, update)"})


_NAV: list = []


def navigation_setup_cached():
    from workbench.scenarios.navigation import navigation_setup

    if not _NAV:
        _NAV.append(navigation_setup())
    return _NAV[0]


def bench_precision(repeats: int) -> list[dict]:
    """float32 vs float64: SAIS batch, MPPI batch, SA-RMPPI step (1 thread, fixed)."""
    with using(1):
        return [*_batch_records(repeats), _step_record(max(200, 40 * repeats))]


if __name__ == "__main__":
    import sys

    for r in bench_precision(int(sys.argv[1]) if len(sys.argv) > 1 else 7):
        p = r["params"]
        extra = (f"  kernel {p['kernel_ratio']:.2f}x "
                 f"alternated {p['alternated_ratio']:.2f}x cpu {p['cpu_ratio']:.2f}x cpu q10 "
                 f"{p['cpu_ratio_q10']:.2f}x kernel cpu q10 {p['kernel_cpu_ratio_q10']:.2f}x "
                 f"rechecked {p['guard_rechecked_fraction']:.3f}" if "kernel_ratio" in p else "")
        print(f"{r['name']:44s} float32 {r['value']:8.3f} ms  float64 {r['baseline_value']:8.3f}"
              f" ms  ratio {r['ratio']:.2f}{extra}")

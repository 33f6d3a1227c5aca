"""Step-time tails and deadlines on the navigation map (``make bench`` records).

``method_latency``: every registered method, one disturbed episode alone on the machine: p50,
p95, p99 and maximum of the wall-clock step time, the mean CPU time, and where the tail comes
from, by tagging steps: the first step of the episode (first calls: page faults, lazy set-up),
steps where a fallback acted (an activity whose name holds "fallback", "backup" or "reset"),
steps right after 20 ms of idle Python (the OpenMP team wakes up), and the one-off costs
before the first step (building the controller, which compiles its kernels on a cold cache,
and calibrating the robust methods' threshold).

``deadline_records``: SA-RMPPI and BaS-MPPI with 8192 samples (a step takes longer than the
budget) at a 20 Hz and a 50 Hz budget (``MPPIConfig.deadline_s``), 1000 steps under a load of
2 (two busy processes beside the benchmark): the largest overshoot over the budget, the misses,
how often the deadline cut the samples, and the crash rate over a few disturbed episodes.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from dataclasses import replace

import numpy as np

from benchmarks.timing import record
from workbench.sampling.deadline import STATED_MARGIN
from workbench.sampling.threshold import AlphaRule
from workbench.scenarios.methods import build, method, names
from workbench.scenarios.navigation import NavigationSetup, navigation_setup
from workbench.sim import Disturbance, closed_loop
from workbench.study.latency import Latency

FALLBACK_WORDS = ("fallback", "backup", "reset")
VARIANCE = 100.0  # the velocity disturbance of the episodes
IDLE_S = 0.02


def _controller(nav: NavigationSetup, name: str) -> tuple[object, float, float]:
    """(controller, seconds to calibrate its threshold (0 if none), seconds to build it)."""
    t0 = time.perf_counter()
    thr = nav.threshold(AlphaRule(kappa=0.1), feedback=method(name).feedback or "bas_ilqg") \
        if method(name).robust else None
    t1 = time.perf_counter()
    ctrl = build(nav, name, threshold=thr)
    return ctrl, t1 - t0, time.perf_counter() - t1


def _fallback(info) -> bool:
    return any(v > 0 for k, v in info.stats.activity.items()
               if any(w in k for w in FALLBACK_WORDS))


def _after_idle(ctrl, nav: NavigationSetup, x, n: int, seed: int) -> list[float]:
    """Wall ms of ``n`` steps from ``x``, each after ``IDLE_S`` of sleep."""
    rng, state, out = np.random.default_rng(seed), ctrl.initial_state(x), []
    for _ in range(n):
        time.sleep(IDLE_S)
        t = time.perf_counter()
        state, _, _ = ctrl.step(state, x, rng)
        out.append(1e3 * (time.perf_counter() - t))
    return out


def method_latency(steps: int = 300, seed: int = 0) -> list[dict]:
    nav = navigation_setup()
    out = []
    for name in names():
        ctrl, calib_s, build_s = _controller(nav, name)
        ep = closed_loop(ctrl, nav.plant, nav.x0, steps, np.random.default_rng(seed),
                         np.random.default_rng(seed + 1), Disturbance(VARIANCE),
                         check_episode=False)
        wall, cpu = 1e3 * ep.step_time_s, 1e3 * ep.step_cpu_s
        w, rest = Latency.of(wall), Latency.of(wall[1:]) if wall.size > 1 else None
        fb = np.array([_fallback(i) for i in ep.infos])
        idle = Latency.of(_after_idle(ctrl, nav, ep.X[len(ep.U) // 2], 30, seed))
        tail = {"first_step_ms": float(wall[0]),
                "p99_without_first_ms": rest.p99_ms if rest else None,
                "fallback_steps": int(fb.sum()),
                "fallback_median_ms": float(np.median(wall[fb])) if fb.any() else None,
                "other_median_ms": float(np.median(wall[~fb])) if (~fb).any() else None,
                "after_idle_p50_ms": idle.p50_ms, "back_to_back_p50_ms": w.p50_ms,
                "calibration_s": calib_s, "build_s": build_s}
        out.append(record(f"step_latency_{name}", w.p99_ms, "ms (wall p99)", None, None,
                          {"steps": w.n, "crashed": bool(ep.crashed), "p50_ms": w.p50_ms,
                           "p95_ms": w.p95_ms, "p99_ms": w.p99_ms, "max_ms": w.max_ms,
                           "mean_ms": w.mean_ms, "cpu_mean_ms": float(cpu.mean()),
                           "variance": VARIANCE, "tail": tail}))
    return out


LOAD_UP_S = 1.0  # the load's processes start (the interpreter loads) before the first step


def _busy(n: int) -> list[subprocess.Popen]:
    """``n`` busy processes, running when this returns (a deadline's first steps seed its
    estimates: a warm-up step that ran before the load was up made them too optimistic)."""
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
    time.sleep(LOAD_UP_S)
    return procs


def _stop(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        p.kill()
        p.wait()


def deadline_records(steps: int = 1000, episodes: int = 4, episode_steps: int = 200,
                     n_samples: int = 8192, load: int = 2) -> list[dict]:
    """Per controller and rate: the loop run at the rate (a step every period, as on a
    robot; with the crash rate of disturbed episodes run so), and back to back (each step as
    soon as the last returns: the process as busy as the load, the harder case for the
    scheduler; no episodes)."""
    base = navigation_setup()
    out = []
    for name in ("bas_mppi", "sa_rmppi"):
        for hz in (20, 50):
            for paced in (True, False):
                out.append(_deadline_record(base, name, hz, paced, steps,
                                            episodes if paced else 0, episode_steps,
                                            n_samples, load))
    return out


def _deadline_record(base: NavigationSetup, name: str, hz: int, paced: bool, steps: int,
                     episodes: int, episode_steps: int, n_samples: int, load: int) -> dict:
    budget = 1.0 / hz
    period = budget if paced else None
    nav = navigation_setup(mppi=replace(base.mppi, n_samples=n_samples, deadline_s=budget))
    ctrl, _, _ = _controller(nav, name)
    procs = _busy(load)
    try:  # one warm-up step: first calls (page faults, lazy set-up) are not the loop's
        ctrl.step(ctrl.initial_state(nav.x0), nav.plant.lift(nav.x0), np.random.default_rng(99))
        ep = closed_loop(ctrl, nav.plant, nav.x0, steps, np.random.default_rng(0),
                         np.random.default_rng(1), check_episode=False, period_s=period)
        crashes = 0
        for j in range(episodes):
            e = closed_loop(ctrl, nav.plant, nav.x0, episode_steps,
                            np.random.default_rng(10 + j), np.random.default_rng(20 + j),
                            Disturbance(VARIANCE), keep_infos=False, check_episode=False,
                            period_s=period)
            crashes += int(e.crashed)
    finally:
        _stop(procs)
    wall, cpu = 1e3 * ep.step_time_s, 1e3 * ep.step_cpu_s
    rep = [i.deadline for i in ep.infos]
    over = float(np.max(wall) - 1e3 * budget)
    w = Latency.of(wall)
    margin = 1e3 * budget * STATED_MARGIN
    beyond = wall > 1e3 * budget + margin
    return record(f"deadline_{name}_{hz}hz" + ("" if paced else "_back_to_back"), over,
                  "ms (max over budget)", None, None,
                  {"budget_ms": 1e3 * budget, "steps": w.n, "load": load,
                   "loop": "at the rate" if paced else "back to back",
                   "n_samples": n_samples, "misses": int(np.sum(wall > 1e3 * budget)),
                   "p50_ms": w.p50_ms, "p95_ms": w.p95_ms, "p99_ms": w.p99_ms,
                   "max_ms": w.max_ms,
                   "truncated": float(np.mean([r.truncated for r in rep])),
                   "samples_mean": float(np.mean([r.samples for r in rep])),
                   "crash_rate": crashes / episodes if episodes else None,
                   "episodes": episodes, "episode_steps": episode_steps, "variance": VARIANCE,
                   "stated_margin_ms": margin, "holds": bool(not beyond.any()),
                   "beyond_margin_steps": int(beyond.sum()),
                   "beyond_margin_cpu_max_ms": float(cpu[beyond].max())
                   if beyond.any() else None,
                   "beyond_margin_phases_ms": _phases(ep, wall, beyond),
                   "cpu_p50_ms": float(np.median(cpu))})


def deadline_records_child() -> list[dict]:
    """:func:`deadline_records` in a fresh child process (no memory or threads left by the
    benchmarks before it)."""
    code = ("import json, sys; from benchmarks.latency import deadline_records; "
            "json.dump(deadline_records(), sys.stdout)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          check=False)
    if done.returncode:
        raise RuntimeError(f"deadline records failed in their process:\n{done.stderr[-2000:]}")
    return json.loads(done.stdout)


def records(repeats: int) -> list[dict]:
    """The latency and deadline records (``repeats`` is not used: the step counts are fixed)."""
    return method_latency() + deadline_records_child()


def _phases(ep, wall: np.ndarray, beyond: np.ndarray, most: int = 3) -> list[dict]:
    """Where the time of the (at most ``most``) longest steps beyond the margin went: the
    controller's own phase timings (ms; the robust controllers time selection, K_safe, SAIS
    and update), its samples, the step's wall and CPU ms, the tail after its last chunk and
    each chunk's samples, wall ms, process CPU ms and threads."""
    out = []
    for k in np.argsort(wall)[::-1][:most]:
        if not beyond[k]:
            break
        info = ep.infos[k]
        phases = getattr(info, "timing", None) or {}
        d = info.deadline
        out.append({"step": int(k), "wall_ms": float(wall[k]),
                    "cpu_ms": float(1e3 * ep.step_cpu_s[k]),
                    "samples": int(d.samples) if d else None,
                    **{f"{n}_ms": float(1e3 * v) for n, v in phases.items()},
                    "tail_ms": float(1e3 * d.tail_s) if d else None,
                    "chunks": [[n, 1e3 * w, 1e3 * c, t] for n, w, c, t in d.chunks] if d
                    else []})
    return out


def _chunks(q: dict) -> str:
    """A step's chunks as ``samples: wall / CPU ms`` (threads when more than one)."""
    return ", ".join(f"{n}: {w:.1f} / {c:.1f}" + (f" ({t} threads)" if t > 1 else "")
                     for n, w, c, t in q.get("chunks") or [])


def _beyond(p: dict) -> str:
    n = p.get("beyond_margin_steps")
    if not n:
        return "0"
    return f"{n} ({p['beyond_margin_cpu_max_ms']:.1f})"


def markdown(records_: list[dict]) -> list[str]:
    """The report's tail-latency and deadline tables."""
    lat = [r for r in records_ if r["name"].startswith("step_latency_") and r.get("params")]
    dl = [r for r in records_ if r["name"].startswith("deadline_") and r.get("params")]
    lines: list[str] = []
    if lat:
        lines += ["", "## Step time per method: p50 / p95 / p99 / max and where the tail "
                  "comes from", "",
                  "One disturbed episode per method on the navigation map, alone on the machine "
                  "(wall clock, ms). First step: the first call of the episode. Fallback: steps "
                  "where a fallback, backup or reset acted. After idle: median of steps after "
                  f"{1e3 * IDLE_S:.0f} ms of sleep (the OpenMP team wakes up). Calibration and "
                  "build happen once, before the first step.", "",
                  "| method | p50 | p95 | p99 | max | CPU mean | first step | p99 w/o first | "
                  "fallback steps (median) | after idle p50 | calibration s | build s |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|---:|"]
        for r in lat:
            p, t = r["params"], r["params"]["tail"]
            fb = (f"{t['fallback_steps']} ({t['fallback_median_ms']:.2f})"
                  if t["fallback_steps"] else "0")
            lines.append(
                f"| {r['name'].removeprefix('step_latency_')} | {p['p50_ms']:.2f} | "
                f"{p['p95_ms']:.2f} | {p['p99_ms']:.2f} | {p['max_ms']:.2f} | "
                f"{p['cpu_mean_ms']:.2f} | {t['first_step_ms']:.2f} | "
                f"{t['p99_without_first_ms']:.2f} | {fb} | {t['after_idle_p50_ms']:.2f} | "
                f"{t['calibration_s']:.2f} | {t['build_s']:.2f} |")
    if dl:
        lines += ["", "## Deadlines under a load of 2", "",
                  "`MPPIConfig.deadline_s` at a 20 Hz and a 50 Hz budget, 8192 samples per step "
                  "(more than fit), two busy processes beside the benchmark, 1000 steps after "
                  "one warm-up step, in a fresh process (a step with a deadline runs numpy's BLAS "
                  "on one thread: see the README). Each loop runs at its rate (a step every "
                  "period, as on a robot: the stated margin is checked on these) and back to "
                  "back (each step as soon as the last returns: the process as busy as the "
                  "load, a stress case). Overshoot: the largest step "
                  "time over the budget. Stated "
                  f"margin: {100 * STATED_MARGIN:.0f} % of the budget; CPU: the process's CPU "
                  "time of the steps beyond it (well below their wall time: the process "
                  "waited for a core). Crash rate: disturbed episodes with the same deadline "
                  "and load (run at the rate).", "",
                  "| controller | loop | budget ms | steps | misses | max over budget ms "
                  "| margin ms | holds | steps beyond (CPU max ms) | p50 | p99 | cut steps | "
                  "samples used (mean) | crash rate |",
                  "|---|---|---:|---:|---:|---:|---:|---|---|---:|---:|---:|---:|---|"]
        for r in dl:
            p = r["params"]
            crash = ("—" if p.get("crash_rate") is None else
                     f"{p['crash_rate']:.2f} ({p['episodes']} × {p['episode_steps']} steps)")
            lines.append(
                f"| {r['name'].removeprefix('deadline_').removesuffix('_back_to_back')} | "
                f"{p.get('loop', 'back to back')} | {p['budget_ms']:.0f} | "
                f"{p['steps']} | {p['misses']} | {r['value']:.2f} | "
                f"{p.get('stated_margin_ms', float('nan')):.1f} | "
                f"{'yes' if p.get('holds') else '**no**'} | {_beyond(p)} | {p['p50_ms']:.2f} | "
                f"{p['p99_ms']:.2f} | {100 * p['truncated']:.0f} % | {p['samples_mean']:.0f} | "
                f"{crash} |")
        worst = [(r["name"].removeprefix("deadline_"), q) for r in dl
                 for q in (r["params"].get("beyond_margin_phases_ms") or [])[:1]]
        if worst:
            lines += ["", "The longest step beyond the margin, per controller (ms):", ""]
            lines += [f"- {n}: " + ", ".join(f"{k.removesuffix('_ms')} {v:.1f}"
                                             for k, v in q.items()
                                             if k.endswith("_ms") and v is not None)
                      + (f"; chunks (samples: wall / CPU ms) {_chunks(q)}" if q.get("chunks")
                         else "")
                      for n, q in worst]
    return lines

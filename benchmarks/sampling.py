"""Sampler benchmarks: one SAIS iteration, compiled vs the NumPy twin, and the SA-RMPPI step."""

from __future__ import annotations

import statistics
import time

import numpy as np

from workbench.navigation import navigation_setup
from workbench.sampling.constants import SamplerConstants
from workbench.sampling.reference import sais_reference
from workbench.sampling.sampler import Sampler
from workbench.sampling.weights import importance_weights, weighted_controls
from workbench.sim import Disturbance, closed_loop


def _iteration_compiled(sampler, x0, U, K, N, c, seed):
    b = sampler.sais(x0, x0, U, K, N, c, seed)
    wn, wr = importance_weights(b.S_nom, c.lam), importance_weights(b.S_real, c.lam)
    return weighted_controls(b.v_nom, wn.w), weighted_controls(b.v_real, wr.w)


def _iteration_numpy(sp, x0, U, K, N, c, seed):
    T = U.shape[0]
    Z = np.random.default_rng(seed).standard_normal((N, T, sp.nu))
    r = sais_reference(sp, np.tile(x0, (N, 1)), np.tile(x0, (N, 1)), U, K, Z, c)
    wn, wr = importance_weights(r["S_nom"], c.lam), importance_weights(r["S_real"], c.lam)
    return (np.einsum("n,ntj->tj", wn.w, r["v_nom"]), np.einsum("n,ntj->tj", wr.w, r["v_real"]))


def sais_batch_records(repeats: int) -> list[dict]:
    nav = navigation_setup()
    sp = nav.problem
    sampler = Sampler(sp, "compiled")
    T = 100
    x0 = sp.model.lift(nav.x0)
    rng = np.random.default_rng(0)
    U = rng.normal(0, 1.0, (T, sp.nu))
    K = rng.normal(0, 1.0, (T, sp.nu, sp.nx))
    c = SamplerConstants(sigma=np.array(nav.mppi.sigma), lam=nav.mppi.lam, nu_mix=0.0,
                         u_min=sp.model.u_min, u_max=sp.model.u_max, crash_cost=1e6,
                         p=sp.model.lift(nav.goal), alpha=2e4)
    out = []
    for N in (256, 1024, 4096):
        _iteration_compiled(sampler, x0, U, K, N, c, 1)
        times = []
        for i in range(max(repeats, 5) * 4):
            t0 = time.perf_counter()
            _iteration_compiled(sampler, x0, U, K, N, c, i)
            times.append(time.perf_counter() - t0)
        t_fast = statistics.median(times)
        t0 = time.perf_counter()
        _iteration_numpy(sp, x0, U, K, N, c, 0)
        t_slow = time.perf_counter() - t0
        out.append({
            "name": f"sais_batch_N{N}_T100", "value": 1e3 * t_fast, "unit": "ms",
            "baseline": "numpy_twin_ms", "baseline_value": 1e3 * t_slow,
            "ratio": t_slow / t_fast,
            "params": {"N": N, "T": T, "obstacles": len(nav.scene.obstacles()),
                       "threads": sampler.lib.cdll.wb_get_threads(),
                       "includes": "noise draw + dual rollout + 3 costs + both weightings "
                       "and updates", "goal_ratio": 20, "goal_ms_N1024": 1.5}})
    return out


def sa_rmppi_step_record(steps: int = 80) -> dict:
    nav = navigation_setup()
    ctrl = nav.controller("sa_rmppi")  # default calibrated alpha rule
    closed_loop(ctrl, nav.plant, nav.x0, 5, np.random.default_rng(0), np.random.default_rng(1))
    ep = closed_loop(ctrl, nav.plant, nav.x0, steps, np.random.default_rng(2),
                     np.random.default_rng(3), Disturbance(10.0))
    split = {k: 1e3 * statistics.median(i.timing[k] for i in ep.infos)
             for k in ep.infos[0].timing}
    return {"name": "sa_rmppi_step_N1024_T100", "value": 1e3 * statistics.median(ep.step_time_s),
            "unit": "ms", "baseline": "goal_ms", "baseline_value": 5.0,
            "ratio": 5.0 / (1e3 * statistics.median(ep.step_time_s)),
            "params": {"split_median_ms": split, "steps": steps, "N": 1024, "T": 100,
                       "candidates": "9 x 64",
                       "K_safe": "one derivative evaluation + one backward pass",
                       "disturbance_variance": 10.0}}


def records(repeats: int) -> list[dict]:
    return [*sais_batch_records(repeats), sa_rmppi_step_record()]

"""The SA-RMPPI control step against its own SAIS batch, measured together.

On the navigation map (N = 1024, T = 100, 9 x 64 candidates, a disturbed episode of variance
10), at 1 and 2 pinned threads, every step of the episode times in turn (the two steps'
order alternating, the batch after them, so load changes hit all three alike):

* ``fast`` — ``RobustMPPI.step`` (the default: K_safe in one compiled call, the selection and
  the update vectorised);
* ``reference`` — the same step with ``fast=False`` and the step-by-step feedback law (the
  code before), from the same state with the same seed: its result is checked equal to the
  fast step's, bit for bit, before the episode goes on;
* ``batch`` — the step's own SAIS batch stand-alone: ``Sampler.sais`` on the step's inputs
  (measured state, chosen nominal state, plan, gains, threshold) + both importance weightings
  + both weighted control sums, as ``benchmarks.split`` times it.

Each step's split (selection, K_safe, SAIS call, update) comes from its info, and the
candidate batch's ``Sampler.candidates`` call is timed inside the selection (a wrapper on the
controller's sampler): ``outside_sampler_calls`` is the step minus both sampler calls, the
Python and compiled work of the step itself. Records: the fast and the reference step with
their splits, ``step_over_batch`` = median step / median batch (goal <= 1.25 on 2 threads) and
the part of the step outside the SAIS call (``outside_sais_ms``: selection with its candidate
batch + K_safe + update + glue). ``lower_bound_step_over_batch`` = (batch + the candidate
batch's call) / batch: the ratio if everything but the two sampler calls took no time.

Why step and batch are timed in one loop: pinned to 2 threads, a kernel call waits for a core
whenever another process holds one, so a step timed minutes apart from a batch (as the older
``sa_rmppi_step_vs_floor`` records are) can show a 2-thread SAIS part far above the batch's
(3.08 vs 1.88 ms in one ``make bench``) although the same call replayed at the same moment
takes the same time.
"""

from __future__ import annotations

import os
import statistics
import time
from dataclasses import replace

import casadi as ca
import numpy as np

from benchmarks.timing import pinned_threads, record, round_robin
from workbench.codegen.fastcall import FastFunction
from workbench.sampling.feedback import ILQGFeedback
from workbench.sampling.planning import shift_plan
from workbench.sampling.robust import RobustMPPI, strides
from workbench.sampling.robust_step import candidate_free_energies
from workbench.sampling.weights import free_energy, importance_weights, weighted_controls
from workbench.scenarios.navigation import navigation_setup
from workbench.sim import Disturbance

N, T = 1024, 100
GOAL_STEP_OVER_BATCH = 1.25  # 2 threads
VARIANCE = 10.0


def _controllers():
    nav = navigation_setup()
    thr = nav.threshold()  # the default calibrated progress rule
    fast = RobustMPPI(nav.problem, nav.goal, nav.mppi, feedback=nav.feedback("bas_ilqg"),
                      threshold=thr)
    sp = nav.problem
    fb = ILQGFeedback(sp.model, nav.mppi.horizon, sp.nx, nav.system.feedback_weights,
                      compiled=False)  # the step-by-step feedback law
    ref = RobustMPPI(nav.problem, nav.goal, nav.mppi, feedback=fb, threshold=thr, fast=False)
    return nav, fast, ref


def _same(a, b) -> bool:
    (sa, ua, ia), (sb, ub, ib) = a, b
    return (np.array_equal(ua, ub) and np.array_equal(sa.U, sb.U)
            and np.array_equal(sa.x_nom, sb.x_nom) and sa.index == sb.index
            and np.array_equal(sa.gains.K, sb.gains.K)
            and ia.free_energy_nom == ib.free_energy_nom and ia.ess_real == ib.ess_real)


def episode(nav, fast: RobustMPPI, ref: RobustMPPI, steps: int, seed: int = 2) -> dict:
    """Times (s) per step of the fast step, the reference step and the stand-alone batch, and
    the splits of both steps."""
    plant = nav.plant
    f = FastFunction(ca.Function("plant", [plant.x, plant.u], [plant.x_next]))
    rng_ctrl, rng_plant = np.random.default_rng(seed), np.random.default_rng(seed + 1)
    dist = Disturbance(VARIANCE)
    idx = dist.indices(plant)
    x = np.asarray(nav.x0, float)
    state = fast.initial_state(x)
    sp, lam = fast.sp, fast.cfg.lam
    st = strides(fast.rcfg.n_candidates)
    times = {"fast": [], "reference": [], "batch": []}
    splits = {"fast": [], "reference": []}
    cand = {"fast": [], "reference": []}
    for name, ctrl in (("fast", fast), ("reference", ref)):
        _time_candidates(ctrl, cand[name])
    for k in range(steps):
        s_seed = int(rng_ctrl.integers(0, 2**63))
        out = {}
        for name in (("fast", "reference") if k % 2 == 0 else ("reference", "fast")):
            ctrl = fast if name == "fast" else ref
            t0 = time.perf_counter()
            out[name] = ctrl.step(state, x, np.random.default_rng(s_seed))
            times[name].append(time.perf_counter() - t0)
            timing = dict(out[name][2].timing)
            if out[name][0].x_nom is not None and state.x_nom is not None:
                timing["candidates_call"] = cand[name][-1]
            else:  # the first step evaluates no candidate
                timing["candidates_call"] = 0.0
            timing["selection_outside_candidates"] = (timing["selection"]
                                                      - timing["candidates_call"])
            timing["outside_sampler_calls"] = (timing["total"] - timing["sais"]
                                               - timing["candidates_call"])
            splits[name].append(timing)
        if not _same(out["fast"], out["reference"]):
            raise AssertionError(f"step {k}: the fast step differs from the reference step")
        new, u, info = out["fast"]
        # the step's own SAIS batch: its inputs rebuilt from the step's outcome
        xb = sp.model.lift(x, fast.consts.scene)
        U_is = shift_plan(state.U, int(st[info.candidate]), fast.cfg.tail) if state.x_nom is not \
            None else state.U
        K, c = new.gains.K, replace(fast.consts, alpha=info.alpha)

        def batch(i, xb=xb, xn=info.x_nom, U_is=U_is, K=K, c=c):
            b = fast.sampler.sais(xb, xn, U_is, K, N, c, i)
            wn, wr = importance_weights(b.S_nom, lam), importance_weights(b.S_real, lam)
            return weighted_controls(b.v_nom, wn.w), weighted_controls(b.v_real, wr.w)

        t0 = time.perf_counter()
        batch(k + 1)
        times["batch"].append(time.perf_counter() - t0)
        state = new
        u = np.clip(u, plant.u_min, plant.u_max)
        x = f(x, u)[0] + dist.sample(plant.nx, plant.dt, rng_plant, idx, k)
        if np.min(plant.margins(x)) <= 0:  # a crash ends the episode
            break
    return {"times": times, "splits": splits}


def _time_candidates(ctrl: RobustMPPI, sink: list) -> None:
    """Record the wall time of every ``Sampler.candidates`` call of ``ctrl`` (kernel and its
    Python call) in ``sink``."""
    call = ctrl.sampler.candidates

    def timed(*a, **k):
        t0 = time.perf_counter()
        r = call(*a, **k)
        sink.append(time.perf_counter() - t0)
        return r

    ctrl.sampler.candidates = timed


def _med(v) -> float:
    return 1e3 * statistics.median(v)


def parts(nav, fast: RobustMPPI, ref: RobustMPPI, repeats: int, at: int = 20) -> dict:
    """Medians (ms) of the step's pieces, fast and reference, timed in turn on the state of
    step ``at`` of a disturbed episode: the candidate batch and the SAIS batch (sampler
    calls), K_safe, the selection's arithmetic, the update's weights and sums."""
    seen = []
    select = fast.select_nominal

    def spy(state, xb, rng):
        seen.append((state, xb))
        return select(state, xb, rng)

    fast.select_nominal = spy
    try:
        episode(nav, fast, ref, at + 1)
    finally:
        del fast.select_nominal
    state, xb = seen[at]
    c, lam, M = fast.consts, fast.cfg.lam, fast.rcfg.candidate_samples
    sel = fast.select_nominal(state, xb, np.random.default_rng(0))
    starts = fast._starts(state.x_nom, state.U[0], xb, c.scene)
    rep = np.repeat(starts, M, axis=0)
    S = fast.sampler.candidates(rep, state.U, fast._stride_rep, c, 1)
    K = fast.feedback.fast_gains(sel.x_nom, sel.U, state.gains, sel.stride).K
    ca_ = replace(c, alpha=sel.alpha_nominal)
    b = fast.sampler.sais(xb, sel.x_nom, sel.U, K, N, ca_, 1)
    wn = importance_weights(b.S_nom, lam)

    def ref_starts():
        a1 = ref._dyn(state.x_nom, state.U[0], c.scene)[0]
        mixed = ref._W @ np.stack([state.x_nom, a1, xb])
        return ref._lift_all(mixed[:, :4], c.scene)[0]

    fns = {
        "candidates_call": lambda i: fast.sampler.candidates(rep, state.U, fast._stride_rep, c,
                                                             i),
        "sais_call": lambda i: fast.sampler.sais(xb, sel.x_nom, sel.U, K, N, ca_, i),
        "k_safe_fast": lambda i: fast.feedback.fast_gains(sel.x_nom, sel.U, state.gains,
                                                          sel.stride),
        "k_safe_reference": lambda i: ref.feedback.gains(sel.x_nom, sel.U, state.gains,
                                                         sel.stride),
        "starts_fast": lambda i: fast._starts(state.x_nom, state.U[0], xb, c.scene),
        "starts_reference": lambda i: ref_starts(),
        "free_energies_fast": lambda i: candidate_free_energies(S, fast.rcfg.n_candidates,
                                                                lam),
        "free_energies_reference": lambda i: [free_energy(x, lam) for x in
                                              S.reshape(fast.rcfg.n_candidates, M)],
        "threshold": lambda i: fast.threshold(starts[:, :4]),
        "weights": lambda i: (importance_weights(b.S_nom, lam),
                              importance_weights(b.S_real, lam)),
        "nominal_sum": lambda i: weighted_controls(b.v_nom, wn.w),
    }
    return {k: 1e3 * v for k, v in round_robin(fns, max(repeats, 5) * 2, block=4, warm=1).items()}


def records(repeats: int = 7, steps: int = 80) -> list[dict]:
    """Fast and reference step, their splits and step / batch, at 1 and 2 pinned threads."""
    nav, fast, ref = _controllers()
    out = []
    threads = (1, 2) if (os.cpu_count() or 1) >= 2 else (1,)
    for th in threads:
        with pinned_threads(th):
            episode(nav, fast, ref, 5, seed=0)  # warm-up (first calls, page faults)
            r = episode(nav, fast, ref, steps)
            pieces = parts(nav, fast, ref, repeats)
        t, sp = r["times"], r["splits"]
        step, refstep, batch = _med(t["fast"]), _med(t["reference"]), _med(t["batch"])
        split = {name: {key: _med([s[key] for s in sp[name]]) for key in sp[name][0]}
                 for name in sp}
        outside = {name: split[name]["total"] - split[name]["sais"] for name in split}
        ratio = step / batch
        # the step can be no faster than its two sampler batches: the candidates' (9 x 64
        # rollouts of the whole horizon) and the SAIS batch, even with everything else free
        lower = (batch + split["fast"]["candidates_call"]) / batch
        goal = GOAL_STEP_OVER_BATCH if th == 2 else None
        common = {"N": N, "T": T, "threads": th, "steps": len(t["fast"]),
                  "candidates": "9 x 64", "disturbance_variance": VARIANCE,
                  "batch_ms": batch, "split_median_ms": split["fast"],
                  "reference_split_median_ms": split["reference"],
                  "outside_sais_ms": outside["fast"],
                  "reference_outside_sais_ms": outside["reference"],
                  "step_over_batch": ratio, "reference_step_over_batch": refstep / batch,
                  "lower_bound_step_over_batch": lower,
                  "per_step_ratio_median": statistics.median(
                      a / b for a, b in zip(t["fast"], t["batch"], strict=True)),
                  "parts_ms": pieces,
                  "goal_step_over_batch": goal,
                  "goal_met": None if goal is None else bool(ratio <= goal),
                  "includes": "batch = Sampler.sais + both weightings + both weighted "
                  "control sums on the step's own inputs, timed in the same loop"}
        suffix = f"N{N}_T{T}_{th}thread"
        out.append(record(f"sa_rmppi_step_over_sais_batch_{suffix}", step, "ms",
                          "sais_batch_same_run_ms", batch, common))
        out.append(record(f"sa_rmppi_step_fast_vs_reference_{suffix}", step, "ms",
                          "sa_rmppi_reference_step_ms", refstep,
                          {**common, "note": "reference = fast=False with the step-by-step "
                           "feedback law (the code before); same numbers, bit for bit"}))
    return out


if __name__ == "__main__":
    import json
    import sys

    for r in records(steps=int(sys.argv[1]) if len(sys.argv) > 1 else 80):
        if not r["name"].startswith("sa_rmppi_step_over_sais_batch"):
            continue
        p = r["params"]
        print(f"{p['threads']} thread(s): step {r['value']:.3f} ms, reference step "
              f"{p['reference_step_over_batch'] * p['batch_ms']:.3f} ms, SAIS batch "
              f"{p['batch_ms']:.3f} ms; step / batch {p['step_over_batch']:.3f} (reference "
              f"{p['reference_step_over_batch']:.3f}); lower bound (batch + candidate batch) "
              f"/ batch {p['lower_bound_step_over_batch']:.3f}")
        for key in ("split_median_ms", "reference_split_median_ms", "parts_ms"):
            print(f"   {key:26s}", json.dumps({k: round(v, 3) for k, v in p[key].items()}))

"""Where the time of a sampler batch goes, against the hand-written C floor
(``benchmarks/floor/sais_floor.c``) measured in the same run.

A SAIS (or BaS-MPPI) batch of N = 1024, T = 100 on the 30-circle map is split into

* noise generation — the kernel drawing its noise (seeded) minus the same kernel reading the
  same noise from a buffer (both called on prepared buffers, no Python); the library's
  stand-alone generator ``lib.normals`` is timed too;
* rollout — the kernel reading the noise from a buffer: dynamics, barrier state, crash test,
  the costs and the applied controls (what the floor computes);
* Python call — ``Sampler.sais`` (checks, packing, unpacking) minus the bare seeded kernel;
* weights — the two importance weightings (NumPy, ``importance_weights``);
* update — the two weighted control sums (``weighted_controls``);

and the whole batch (``Sampler`` call + weights + update) is timed as one piece. Every part is a
ratio to the floor at the same thread count: ratio = floor / part, ``x_floor`` = part / floor.
All parts and the floor are timed in turn in one loop (medians), after checking that the floor,
the kernel on given noise and the seeded kernel agree (1e-10 relative, crash flags equal).
"""

from __future__ import annotations

import os
import statistics

import numpy as np

from benchmarks.floor import FloorProblem, cpu_flags, cpu_model, load_floor
from benchmarks.sampling import _setup
from benchmarks.timing import pinned_threads, prepared_kernel, record, round_robin
from workbench.codegen.toolchain import find_toolchain
from workbench.sampling.kernels.flags import KERNEL_FLAGS, vector_bits
from workbench.sampling.sampler import Sampler, check_batch
from workbench.sampling.weights import importance_weights, weighted_controls
from workbench.sim import Disturbance, closed_loop

N, T = 1024, 100
RTOL, FLOOR = 1e-10, 1.0  # per element: |a - b| <= RTOL * max(|a|, |b|, FLOOR)
GOAL_X_FLOOR = 1.3  # SAIS batch, 1 thread: at most this many times the floor


def rel_err(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.max(np.abs(a - b) / np.maximum(np.maximum(np.abs(a), np.abs(b)), FLOOR)))


def machine() -> dict:
    """CPU model, vector extensions, core count, compiler and flags (the floor's and kernels')."""
    tc = find_toolchain()
    return {"cpu": cpu_model(), "cpu_flags": cpu_flags(), "cpus": os.cpu_count(),
            "compiler": None if tc is None else tc.describe(),
            "kernel_flags": list(KERNEL_FLAGS), "kernel_vector_bits": vector_bits()}


def _threads_list() -> tuple[int, ...]:
    return (1, 2) if (os.cpu_count() or 1) >= 2 else (1,)


def _parts_records(kind: str, threads: int, timed: tuple[dict, dict],
                   common: dict) -> list[dict]:
    """Records of one split: the floor, every part and the whole batch as ratios to the floor
    (medians; ``x_floor_min``: the same ratio of the least disturbed calls, for loaded
    machines)."""
    t, t_min = timed
    ms = {k: 1e3 * v for k, v in t.items()}
    ms_min = {k: 1e3 * v for k, v in t_min.items()}
    floor = ms["floor"]
    parts = {
        "noise_generation": ms["kernel_seeded"] - ms["kernel_given_noise"],
        "rollout_given_noise": ms["kernel_given_noise"],
        "python_call": ms["sampler_call"] - ms["kernel_seeded"],
        "weights": ms["weights"],
        "update": ms["update"],
    }
    suffix = f"N{N}_T{T}_{threads}thread"
    base = f"c_floor_{kind}_rollout_ms"
    p = {**common, "threads": threads, "medians_ms": ms, "minima_ms": ms_min,
         "sum_of_parts_ms": sum(parts.values()),
         "standalone_normals_ms": ms["normals"]}
    out = [record(f"floor_{kind}_rollout_{suffix}", floor, "ms", None, None,
                  {**p, "includes": "hand-written C: rollout, barrier, crash test, costs, "
                   "applied controls; noise given as an input array"})]
    for name, v in parts.items():
        out.append(record(f"{kind}_split_{name}_{suffix}", v, "ms", base, floor,
                          {**p, "part": name, "x_floor": v / floor,
                           "share_of_batch": v / ms["batch"]}))
    x = ms["batch"] / floor
    p["x_floor_min"] = ms_min["batch"] / ms_min["floor"]
    goal = GOAL_X_FLOOR if (kind == "sais" and threads == 1) else None
    out.append(record(f"{kind}_batch_vs_floor_{suffix}", ms["batch"], "ms", base, floor,
                      {**p, "x_floor": x, "goal_x_floor": goal,
                       "goal_met": None if goal is None else bool(x <= goal),
                       "includes": "Sampler call (noise + rollout + costs) + weights + update"}))
    return out


def sais_split_records(repeats: int) -> list[dict]:
    """The SAIS batch split, at 1 and 2 threads, against the SAIS floor."""
    nav, sp, U, K, c = _setup()
    _, c = check_batch(sp, N, U, c)  # the model's scene filled in
    sampler = Sampler(sp, "compiled")
    lib = sampler.lib
    floor = load_floor()
    floor4 = load_floor(group=4)
    floor_l4 = load_floor(lanes=4)
    prob = FloorProblem.of(sp, c)
    x0 = sp.model.lift(nav.x0)
    seed = 1
    Z = lib.normals(N, T, sp.nu, seed)
    k = lib.sais
    carry = k.carry.pack(N, x=x0, x_nom=x0)
    time_in = {"u": U, "K": K.reshape(T, -1)}
    given, outs_g, res_g = prepared_kernel(k, carry, c.kernel_consts(), time_in, noise=Z)
    seeded, outs_s, res_s = prepared_kernel(k, carry, c.kernel_consts(), time_in, seed=seed)
    fcall, fout = floor.prepare_sais(prob, x0, x0, U, K, Z)
    fcall4, fout4 = floor4.prepare_sais(prob, x0, x0, U, K, Z)
    fcall_l4, fout_l4 = floor_l4.prepare_sais(prob, x0, x0, U, K, Z)
    fseeded, fout_s = floor.prepare_sais(prob, x0, x0, U, K, N=N, seed=seed)
    # exactness first: seeded = given noise (bitwise), floor = kernel (1e-10 per element)
    given(), seeded(), fcall(), fcall4(), fseeded(), fcall_l4()
    if not (np.array_equal(floor.normals(N, T, sp.nu, seed), Z) and all(
            np.array_equal(v, fout_s()[n]) for n, v in fout().items())):
        raise AssertionError("the floor's generator does not draw the kernels' noise")
    if not (np.array_equal(res_g, res_s) and all(
            np.array_equal(a, b) for a, b in zip(outs_g, outs_s, strict=True))):
        raise AssertionError("SAIS kernel: seeded and given-noise results differ")
    r = k.result.unpack(res_g[:N])
    errs = {}
    for name, fo in (("floor", fout()), ("floor_group4", fout4()), ("floor_lanes4", fout_l4())):
        err = max([rel_err(fo[n], r[n]) for n in ("S_nom", "S_real", "S_state_nom", "S_hat",
                                                  "LR")]
                  + [rel_err(fo["v_nom"], outs_g[0][..., :N]),
                     rel_err(fo["v_real"], outs_g[1][..., :N])])
        same = all(np.array_equal(fo[n], r[n] > 0) for n in ("crashed_real", "crashed_nom"))
        if err > RTOL or not same:
            raise AssertionError(f"SAIS {name} differs from the kernel: {err:.2e}, crash flags "
                                 f"{'equal' if same else 'differ'}")
        errs[name] = err
    b = sampler.sais(x0, x0, U, K, N, c, seed)
    wn, wr = importance_weights(b.S_nom, c.lam), importance_weights(b.S_real, c.lam)

    def batch(i):
        bb = sampler.sais(x0, x0, U, K, N, c, i)
        w1, w2 = importance_weights(bb.S_nom, c.lam), importance_weights(bb.S_real, c.lam)
        return weighted_controls(bb.v_nom, w1.w), weighted_controls(bb.v_real, w2.w)

    fns = {
        "floor": lambda i: fcall(),
        "floor_group4": lambda i: fcall4(),
        "floor_seeded": lambda i: fseeded(),
        "floor_lanes4": lambda i: fcall_l4(),
        "floor_normals": lambda i: floor.normals(N, T, sp.nu, i),
        "kernel_given_noise": lambda i: given(),
        "kernel_seeded": lambda i: seeded(),
        "normals": lambda i: lib.normals(N, T, sp.nu, i),
        "sampler_call": lambda i: sampler.sais(x0, x0, U, K, N, c, i),
        "weights": lambda i: (importance_weights(b.S_nom, c.lam),
                              importance_weights(b.S_real, c.lam)),
        "update": lambda i: (weighted_controls(b.v_nom, wn.w), weighted_controls(b.v_real, wr.w)),
        "batch": batch,
    }
    common = {"N": N, "T": T, "obstacles": prob.n_circles, "float": "float64",
              "floor_lanes": floor.lanes, "kernel_lanes": k.spec.lanes,
              "max_rel_err_floor_vs_kernel": errs["floor"],
              "max_rel_err_floor_group4_vs_kernel": errs["floor_group4"],
              "floor_code": "benchmarks/floor/sais_floor.c:floor_sais", "machine": machine()}
    out = []
    for th in _threads_list():
        with pinned_threads(th, floor.set_threads):
            timed = round_robin(fns, max(repeats, 5) * 2, block=4, warm=2, with_min=True)
            t = timed[0]
            recs = _parts_records("sais", th, timed, common)
            f4 = 1e3 * t["floor_group4"]
            recs[0]["params"]["floor_group4_ms"] = f4
            out += recs
            fs = 1e3 * t["floor_seeded"]
            out.append(record(f"floor_sais_seeded_N{N}_T{T}_{th}thread", fs, "ms",
                              "c_floor_sais_rollout_ms", 1e3 * t["floor"],
                              {**common, "threads": th, "x_floor": fs / (1e3 * t["floor"]),
                               "noise_generation_in_floor_ms": fs - 1e3 * t["floor"],
                               "floor_normals_ms": 1e3 * t["floor_normals"],
                               "note": "the floor drawing the kernels' noise (the library's "
                               f"generator, {floor.lanes} samples per block) inside the "
                               "rollout; floor_normals_ms: that generator alone"}))
            fl4 = 1e3 * t["floor_lanes4"]
            out.append(record(f"floor_sais_4lanes_vs_8lanes_N{N}_T{T}_{th}thread", fl4, "ms",
                              "c_floor_sais_rollout_ms", 1e3 * t["floor"],
                              {**common, "threads": th, "x_floor": fl4 / (1e3 * t["floor"]),
                               "note": "the floor with 4 samples per block (one 256-bit "
                               "vector, the generated kernels' block without AVX-512) "
                               "instead of 8"}))
            out.append(record(f"floor_sais_group4_vs_pairwise_N{N}_T{T}_{th}thread", f4, "ms",
                              "c_floor_sais_rollout_ms", 1e3 * t["floor"],
                              {**common, "threads": th,
                               "note": "the floor with one division per four circles "
                               "((n1 d2 + n2 d1) / (d1 d2)) instead of per pair: tells whether "
                               "divisions bound the rollout"}))
    return out


def mppi_split_records(repeats: int) -> list[dict]:
    """The BaS-MPPI batch split, at 1 and 2 threads, against the MPPI floor."""
    nav, sp, U, _, c = _setup()
    _, c = check_batch(sp, N, U, c)
    sampler = Sampler(sp, "compiled")
    lib = sampler.lib
    floor = load_floor()
    prob = FloorProblem.of(sp, c)
    x0 = sp.model.lift(nav.x0)
    seed = 1
    Z = lib.normals(N, T, sp.nu, seed)
    k = lib.mppi
    carry = k.carry.pack(N, x=x0)
    given, outs_g, res_g = prepared_kernel(k, carry, c.kernel_consts(), {"u": U}, noise=Z)
    seeded, _, res_s = prepared_kernel(k, carry, c.kernel_consts(), {"u": U}, seed=seed)
    fcall, fout = floor.prepare_mppi(prob, x0, U, Z)
    given(), seeded(), fcall()
    if not np.array_equal(res_g, res_s):
        raise AssertionError("MPPI kernel: seeded and given-noise results differ")
    r = k.result.unpack(res_g[:N])
    fo = fout()
    err = max(rel_err(fo["S"], r["S"]), rel_err(fo["v"], outs_g[0][..., :N]))
    if err > RTOL or not np.array_equal(fo["crashed"], r["crashed"] > 0):
        raise AssertionError(f"MPPI floor differs from the kernel: {err:.2e}")
    b = sampler.mppi(x0, U, N, c, seed)
    w = importance_weights(b.S, c.lam)

    def batch(i):
        bb = sampler.mppi(x0, U, N, c, i)
        return weighted_controls(bb.v, importance_weights(bb.S, c.lam).w)

    fns = {
        "floor": lambda i: fcall(),
        "kernel_given_noise": lambda i: given(),
        "kernel_seeded": lambda i: seeded(),
        "normals": lambda i: lib.normals(N, T, sp.nu, i),
        "sampler_call": lambda i: sampler.mppi(x0, U, N, c, i),
        "weights": lambda i: importance_weights(b.S, c.lam),
        "update": lambda i: weighted_controls(b.v, w.w),
        "batch": batch,
    }
    common = {"N": N, "T": T, "obstacles": prob.n_circles, "float": "float64",
              "floor_lanes": floor.lanes, "kernel_lanes": k.spec.lanes,
              "max_rel_err_floor_vs_kernel": err,
              "floor_code": "benchmarks/floor/sais_floor.c:floor_mppi"}
    out = []
    for th in _threads_list():
        with pinned_threads(th, floor.set_threads):
            timed = round_robin(fns, max(repeats, 5) * 2, block=4, warm=2, with_min=True)
            out += _parts_records("bas_mppi", th, timed, common)
    return out


def sa_rmppi_step_records(steps: int = 80) -> list[dict]:
    """The SA-RMPPI control step (N = 1024, T = 100, disturbed episode) at each thread count,
    with its own split (selection, K_safe, SAIS batch, update), against the SAIS floor timed
    right after each episode at the same thread count."""
    nav, sp, U, K, c = _setup()
    _, c = check_batch(sp, N, U, c)
    ctrl = nav.controller("sa_rmppi")  # the default calibrated alpha rule
    lib = ctrl.sampler.lib
    floor = load_floor()
    prob = FloorProblem.of(sp, c)
    x0 = sp.model.lift(nav.x0)
    fcall, _ = floor.prepare_sais(prob, x0, x0, U, K, lib.normals(N, T, sp.nu, 1))
    out = []
    for th in _threads_list():
        with pinned_threads(th, floor.set_threads):
            closed_loop(ctrl, nav.plant, nav.x0, 5, np.random.default_rng(0),
                        np.random.default_rng(1))
            ep = closed_loop(ctrl, nav.plant, nav.x0, steps, np.random.default_rng(2),
                             np.random.default_rng(3), Disturbance(10.0))
            fl = 1e3 * round_robin({"floor": lambda i: fcall()}, max(10, steps // 4),
                                   block=1, warm=1)["floor"]
        step = 1e3 * statistics.median(ep.step_time_s)
        split = {k: 1e3 * statistics.median(i.timing[k] for i in ep.infos)
                 for k in ep.infos[0].timing}
        params = {"split_median_ms": split, "steps": steps, "N": N, "T": T,
                  "threads": th, "candidates": "9 x 64",
                  "K_safe": "one derivative evaluation + one backward pass",
                  "disturbance_variance": 10.0, "x_floor": step / fl,
                  "split_x_floor": {k: v / fl for k, v in split.items()}}
        out.append(record(f"sa_rmppi_step_vs_floor_N{N}_T{T}_{th}thread", step, "ms",
                          "c_floor_sais_rollout_ms", fl, params))
    # the record earlier reports carried, under the library's own thread setting
    closed_loop(ctrl, nav.plant, nav.x0, 5, np.random.default_rng(0), np.random.default_rng(1))
    ep = closed_loop(ctrl, nav.plant, nav.x0, steps, np.random.default_rng(2),
                     np.random.default_rng(3), Disturbance(10.0))
    split = {k: 1e3 * statistics.median(i.timing[k] for i in ep.infos)
             for k in ep.infos[0].timing}
    out.append(record(f"sa_rmppi_step_N{N}_T{T}", 1e3 * statistics.median(ep.step_time_s), "ms",
                      None, None, {"split_median_ms": split, "steps": steps, "N": N, "T": T,
                                   "threads": "library default (adaptive where available)",
                                   "candidates": "9 x 64", "goal_ms": 4.0,
                                   "disturbance_variance": 10.0}))
    return out


def records(repeats: int) -> list[dict]:
    return [*sais_split_records(repeats), *mppi_split_records(repeats), *sa_rmppi_step_records()]

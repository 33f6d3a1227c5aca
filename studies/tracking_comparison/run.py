"""Run the study: nominal solutions, (method, variant, seed) tasks, tidy data and summary.

Every task writes its per-rollout results atomically to ``<out>/.cache/tasks/`` under a content
hash of its inputs; a rerun (or an interrupted run) skips tasks whose file is present and whose
stored key matches. Tasks run in worker processes; each draws its noise from its own generator
(see :func:`~studies.tracking_comparison.rollouts.noise_generator`), so the results do not depend
on the worker count or the order in which tasks finish.
"""

from __future__ import annotations

import io
import json
import multiprocessing
import sys
import time
import zipfile
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from tqdm import tqdm

from studies.tracking_comparison.config import (
    METHODS,
    StudyConfig,
    Variant,
    nominal_key,
    task_key,
)
from studies.tracking_comparison.methods import Nominal, Setup, solve_nominal
from studies.tracking_comparison.rollouts import (
    LinearDynamics,
    control_noise,
    ecbf_rollouts,
    feedback_rollouts,
    lift_function,
    margins_function,
    noise_generator,
    rollout_metrics,
)
from workbench.barrier import embed_barrier
from workbench.ecbf import ECBFFilter
from workbench.io import atomic_write_bytes, atomic_write_json, atomic_write_text, manifest
from workbench.stats import wilson_interval

# [P] numbers of the paper (SPEC 14.1) and the SPEC 14.4 reproduction bands [A]
PAPER = {
    "ecbf": {"metric": "failure_rate", "value": 0.27, "band": (0.15, 0.40),
             "text": "≈27% of MC samples fail (unsafe or not at the target)"},
    "al": {"metric": "unsafe_rate", "value": 0.60, "band": (0.40, 0.80),
           "text": "≈60% of MC trajectories unsafe"},
    "bas": {"metric": "unsafe_rate", "value": 0.0, "band": (0.0, 0.01),
            "text": "0 violations in 500 MC samples"},
}
SWEEP_COLUMNS = ("n_rollouts", "unsafe_rate", "unsafe_ci_low", "unsafe_ci_high", "failure_rate",
                 "failure_ci_low", "failure_ci_high", "mean_final_distance",
                 "infeasible_qp_steps")
ROLLOUT_ARRAYS = ("min_h", "final_distance", "infeasible_steps", "fallback_steps", "qp_steps")


@dataclass(frozen=True)
class Task:
    """One (method, variant, seed) batch of Monte Carlo rollouts."""

    method: str
    variant: Variant
    seed_index: int
    n_rollouts: int
    key: str
    keep_paths: bool


def _npz_bytes(**arrays) -> bytes:
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def _load(path: Path, key: str) -> dict[str, np.ndarray] | None:
    """A stored result if it exists, is readable and carries the expected key."""
    try:
        with np.load(path, allow_pickle=False) as data:
            if str(data["key"]) != key:
                return None
            return {name: data[name] for name in data.files}
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile):
        return None


def _nominal_path(out: Path, method: str, key: str) -> Path:
    return out / ".cache" / "nominal" / f"{method}-{key}.npz"


def _task_path(out: Path, task: Task) -> Path:
    return out / ".cache" / "tasks" / f"{task.method}-s{task.seed_index}-{task.key}.npz"


def nominal_solution(method: str, variant: Variant, setup: Setup, out: Path) -> Nominal:
    """Solve (or load) a method's nominal solution for a variant."""
    key = nominal_key(method, variant, setup.fixed())
    path = _nominal_path(out, method, key)
    data = _load(path, key)
    if data is not None:
        return Nominal(method, data["X"], data["U"], data["K"], json.loads(str(data["info"])))
    nom = solve_nominal(method, variant, setup)
    atomic_write_bytes(path, _npz_bytes(key=key, X=nom.X, U=nom.U, K=nom.K,
                                        info=json.dumps(nom.info)))
    return nom


def closed_loop(method: str, variant: Variant, setup: Setup, nominal: Nominal,
                noise: np.ndarray) -> dict[str, np.ndarray]:
    """Run one batch of closed loops under ``noise`` (N, T, nu) and measure each rollout."""
    sc = setup.scene
    model = setup.model()
    dyn = LinearDynamics.from_model(model)
    x0 = np.array(sc.start)
    counts = {name: np.zeros(noise.shape[0], dtype=np.int64)
              for name in ("infeasible_steps", "fallback_steps", "qp_steps")}
    if method == "ecbf":
        r = ecbf_rollouts(dyn, x0, nominal.X, nominal.U, nominal.K, noise,
                          ECBFFilter(model, setup.ecbf_for(variant)),
                          noise_after=variant.ecbf_noise == "after")
        X = r.X
        counts = {"infeasible_steps": r.infeasible_steps, "fallback_steps": r.fallback_steps,
                  "qp_steps": r.qp_steps}
    else:
        lift = lift_function(embed_barrier(model, setup.barrier)) if method == "bas" else None
        X = feedback_rollouts(dyn, x0, nominal.X, nominal.U, nominal.K, noise, model.u_min,
                              model.u_max, lift)
    min_h, final = rollout_metrics(X, margins_function(model), np.array(sc.target[:2]))
    return {"X": X, "min_h": min_h, "final_distance": final, **counts}


def execute(task: Task, nominal: Nominal, setup: Setup, root_seed: int, noise_std: float,
            path: Path) -> dict[str, np.ndarray]:
    """Run a task and store its per-rollout results atomically (the worker entry point)."""
    rng = noise_generator(root_seed, task.method, task.seed_index)
    noise = control_noise(rng, task.n_rollouts, setup.scene.horizon, 2, noise_std)
    res = closed_loop(task.method, task.variant, setup, nominal, noise)
    arrays = {name: res[name] for name in ROLLOUT_ARRAYS}
    if task.keep_paths:
        arrays["positions"] = res["X"][:, :, :2].astype(np.float32)
    atomic_write_bytes(path, _npz_bytes(key=task.key, **arrays))
    return arrays


def plan(config: StudyConfig, setup: Setup) -> tuple[list[Task], list[tuple]]:
    """Main tasks (base variant) and, per sweep point, its tasks per method."""
    fixed = setup.fixed()

    def make(method, variant, s, n, keep):
        return Task(method, variant, s, n, task_key(config, method, variant, s, n, fixed), keep)

    main = [make(m, config.base, s, config.n_rollouts, s == 0)
            for m in config.methods for s in range(config.n_seeds)]
    points = [(name, value, {m: [make(m, variant, s, config.sweep_rollouts, False)
                                 for s in range(config.sweep_seeds)] for m in config.methods})
              for name, value, variant in config.sweep_points()]
    return main, points


def _nominal_id(method: str, variant: Variant) -> tuple:
    """Nominal solutions are shared by the variants that agree on the method's values."""
    return method, tuple(variant.relevant(method).items())


def _run_tasks(pending: list[tuple[Task, Path]], nominals: dict, setup: Setup,
               config: StudyConfig, progress: bool) -> dict[str, dict[str, np.ndarray]]:
    results: dict[str, dict[str, np.ndarray]] = {}
    bar = tqdm(total=len(pending), desc="tracking comparison", unit="task", file=sys.stderr,
               disable=not progress)
    # slow ECBF tasks first, so the workers finish together
    pending = sorted(pending, key=lambda tp: (tp[0].method != "ecbf", -tp[0].n_rollouts))

    def args(task, path):
        nom = nominals[_nominal_id(task.method, task.variant)]
        return task, nom, setup, config.seed, config.noise_std, path

    workers = min(config.workers, len(pending))
    if workers <= 1:
        for task, path in pending:
            results[task.key] = execute(*args(task, path))
            bar.update()
    else:
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
            futures = {pool.submit(execute, *args(t, p)): t for t, p in pending}
            for fut in as_completed(futures):
                results[futures[fut].key] = fut.result()
                bar.update()
    bar.close()
    return results


def summarise(rows: pd.DataFrame, target_radius: float) -> dict:
    """Pooled rates with Wilson intervals and per-seed spread for one method's rollouts."""
    n = len(rows)
    unsafe = rows["min_h"].to_numpy() < 0
    reached = rows["final_distance"].to_numpy() <= target_radius
    failure = unsafe | ~reached
    out: dict = {"n_rollouts": n}
    for name, flags in (("unsafe", unsafe), ("failure", failure)):
        k = int(flags.sum())
        lo, hi = wilson_interval(k, n)
        out.update({f"n_{name}": k, f"{name}_rate": k / n, f"{name}_ci_low": lo,
                    f"{name}_ci_high": hi})
    min_h = rows["min_h"].to_numpy()
    fd = rows["final_distance"].to_numpy()
    infeasible = rows["infeasible_qp_steps"].to_numpy()
    out.update({
        "n_not_reached": int((~reached).sum()),
        "n_unsafe_and_not_reached": int((unsafe & ~reached).sum()),
        "n_grazing": int(((min_h >= 0) & (min_h < 1e-6)).sum()),
        "mean_final_distance": float(fd.mean()),
        "median_final_distance": float(np.median(fd)),
        "min_h": {"min": float(min_h.min()), "p05": float(np.quantile(min_h, 0.05)),
                  "median": float(np.median(min_h)), "mean": float(min_h.mean())},
        "infeasible_qp_steps": int(infeasible.sum()),
        "rollouts_with_infeasible_qp": int((infeasible > 0).sum()),
        "unsafe_with_infeasible_qp": int((unsafe & (infeasible > 0)).sum()),
        "fallback_steps": int(rows["fallback_steps"].sum()),
        "qp_steps": int(rows["qp_steps"].sum()),
    })
    if "seed_index" in rows:
        per_seed = []
        for s, grp in rows.groupby("seed_index"):
            u = grp["min_h"].to_numpy() < 0
            f = u | (grp["final_distance"].to_numpy() > target_radius)
            per_seed.append({"seed_index": int(s), "n": len(grp), "unsafe_rate": float(u.mean()),
                             "failure_rate": float(f.mean())})
        out["per_seed"] = per_seed
        for name in ("unsafe_rate", "failure_rate"):
            v = np.array([p[name] for p in per_seed])
            out[f"per_seed_{name}"] = {"mean": float(v.mean()), "std": float(v.std(ddof=0)),
                                       "min": float(v.min()), "max": float(v.max())}
    return out


def _rows(task: Task, arrays: dict[str, np.ndarray], study: str,
          target_radius: float) -> pd.DataFrame:
    n = task.n_rollouts
    unsafe = arrays["min_h"] < 0
    return pd.DataFrame({
        "study": study, "method": task.method, "q_beta": task.variant.q_beta,
        "pole": task.variant.pole, "q_scale": task.variant.q_scale,
        "ecbf_noise": task.variant.ecbf_noise,
        "seed_index": task.seed_index, "rollout": np.arange(n), "min_h": arrays["min_h"],
        "final_distance": arrays["final_distance"], "unsafe": unsafe,
        "failure": unsafe | (arrays["final_distance"] > target_radius),
        "infeasible_qp_steps": arrays["infeasible_steps"],
        "fallback_steps": arrays["fallback_steps"], "qp_steps": arrays["qp_steps"]})


def _ranking(rates: dict[str, dict]) -> dict:
    """Does the paper's ordering BaS < ECBF < AL hold (strictly, by point estimate)?"""
    out = {}
    for metric in ("unsafe_rate", "failure_rate"):
        if all(m in rates for m in METHODS):
            r = {m: rates[m][metric] for m in METHODS}
            out[metric] = bool(r["bas"] < r["ecbf"] < r["al"])
            out[f"{metric}_order"] = " < ".join(sorted(METHODS, key=lambda m: (r[m], m)))
    return out


def assumed_values(config: StudyConfig, setup: Setup) -> list[dict[str, str]]:
    """Every value the run used that the paper does not give ([A]) or takes from elsewhere."""
    sc, w, b, e, a, i = setup.scene, setup.weights, setup.barrier, setup.ecbf, setup.al, \
        setup.ilqg
    rows = [
        ("start, target", f"{sc.start}, {sc.target}", "A (SPEC 3.3)"),
        ("obstacle", f"centre {sc.obstacle.center}, radius {sc.obstacle.radius} m",
         "A (SPEC 3.3)"),
        ("reference", "straight line start -> target at constant speed over N dt "
         "(10/3 m/s), through the obstacle", "A (SPEC 3.3)"),
        ("horizon N, dt", f"{sc.horizon}, {sc.dt} s", "A (SPEC 2.5)"),
        ("model", "planar double integrator, explicit Euler; h = ‖p − c‖² − r²",
         "A / X (SPEC 2, 3.1)"),
        ("control box", f"+-{sc.u_limit} per axis", "P"),
        ("control noise", f"N(0, {config.noise_std:g}^2 I) i.i.d. per step; "
         f"{config.base.ecbf_noise} the ECBF filter; inside the clip for AL and BaS",
         "P (std) / A (where, SPEC E7)"),
        ("Monte Carlo size", f"{config.n_seeds} seeds x {config.n_rollouts} rollouts per method",
         "P (500, BaS) / A (others, seeds)"),
        ("tracking weights", f"Q = {config.base.q_scale:g} x diag{w.Q}, R = diag{w.R}, "
         f"S = diag{w.S}", "A (SPEC 6)"),
        ("BaS barrier", f"{b.kind} 1/h, one summed state, gamma = {b.gamma}, crash at "
         f"h <= {b.eps_h:g} -> beta = {b.beta_max:g}", "X (DBaS-code) / A"),
        ("BaS weights", f"q_beta = {config.base.q_beta:g} (swept), s_beta = {w.s_beta}, "
         f"cost on (beta - beta_target)^2", "A / X (SPEC 4.5, 6.1)"),
        ("iLQG", f"mu0 = {i.mu_init}, factor {i.mu_factor}, tol_rel = {i.tol_rel:g}, "
         f"max_iter = {i.max_iter}, box QP, U0 = 0", "X / A (SPEC 5)"),
        ("AL-iLQG", f"lambda0 = {a.lambda_init:g}, mu0 = {a.mu_init:g}, phi = {a.phi:g}, "
         f"tau = {a.tau:g}, mu_max = {a.mu_max:g}, eps_c = {a.constraint_tol:g} m^2, "
         f"<= {a.max_outer} outer, {a.mu_update} mu update, Gauss-Newton, inner tol_rel = "
         f"{a.inner.tol_rel:g}", "A / X (SPEC 6.2, ALTRO)"),
        ("ECBF poles", f"p1 = p2 = {config.base.pole:g} (k1 = p1 + p2, k0 = p1 p2), swept",
         "A (SPEC 7.1)"),
        ("ECBF QP", f"{e.mode} rows normalised to ‖a_i‖ = 1, slack cost {e.slack_linear:g} "
         f"delta + {e.slack_quadratic:g} delta^2 (SPEC: 1e6 delta^2), infeasible if delta > "
         f"{e.slack_tol:g}; OSQP eps {e.eps_abs:g}, polish {e.polish}, warm start",
         "A (deviation, see workbench/ecbf.py) / SPEC 7.2"),
        ("ECBF nominal", "plain iLQG on the tracking problem without the obstacle",
         "P / SPEC 6.3"),
        ("unsafe", "min over k = 0..N and obstacles of h(x_k) < 0", "SPEC 6.4"),
        ("failure", f"unsafe or ‖p_N − p_target‖ > {config.target_radius:g} m", "A (SPEC 6.4)"),
        ("randomness", f"root seed {config.seed}; SeedSequence spawned per (method, seed)",
         "A"),
        ("sweep", f"q_beta in {config.sweep_q_beta}, poles in {config.sweep_pole}, Q scale in "
         f"{config.sweep_q_scale}, ECBF noise {config.sweep_ecbf_noise} the filter; "
         f"{config.sweep_seeds} seeds x {config.sweep_rollouts} "
         "rollouts (same noise prefix as the main seeds)", "A"),
    ]
    return [{"name": n, "value": v, "source": src} for n, v, src in rows]


def _csv(df: pd.DataFrame, fmt: str) -> str:
    buf = io.StringIO()
    df.to_csv(buf, index=False, float_format=fmt)
    return buf.getvalue()


def run(config: StudyConfig, out: Path, setup: Setup | None = None,
        progress: bool = True) -> dict:
    """Run (or resume) the study and write rollouts.csv, sweep.csv and summary.json to ``out``."""
    t_start = time.perf_counter()
    setup = setup or Setup()
    out = Path(out)
    main, points = plan(config, setup)
    tasks = {t.key: t for t in main}
    for _, _, per_method in points:
        tasks.update({t.key: t for ts in per_method.values() for t in ts if t.key not in tasks})
    results, pending = {}, []
    for task in tasks.values():
        path = _task_path(out, task)
        data = _load(path, task.key)
        if data is None:
            pending.append((task, path))
        else:
            results[task.key] = data
    needed = [(t.method, t.variant) for t, _ in pending] + [(m, config.base)
                                                             for m in config.methods]
    nominals: dict = {}
    for method, variant in needed:
        if _nominal_id(method, variant) not in nominals:
            nominals[_nominal_id(method, variant)] = nominal_solution(method, variant, setup, out)
    results.update(_run_tasks(pending, nominals, setup, config, progress))

    main_keys = {t.key for t in main}
    frames = {k: _rows(t, results[k], "main" if k in main_keys else "sweep",
                       config.target_radius) for k, t in tasks.items()}
    methods = {m: summarise(pd.concat([frames[t.key] for t in main if t.method == m]),
                            config.target_radius) for m in config.methods}

    sweep_table, sweep_ranking = [], []
    for name, value, per_method in points:
        rates = {}
        for m, ts in per_method.items():
            rates[m] = summarise(pd.concat([frames[t.key] for t in ts]), config.target_radius)
            sweep_table.append({"parameter": name, "value": value, "method": m,
                                **{k: rates[m][k] for k in SWEEP_COLUMNS}})
        sweep_ranking.append({"parameter": name, "value": value, **_ranking(rates)})

    # nominal (noise-free) closed loops and the Monte Carlo paths of seed 0, for the figures
    traj, nominal_info = {"reference": setup.scene.reference()[:, :2]}, {}
    T = setup.scene.horizon
    for m in config.methods:
        nom = nominals[_nominal_id(m, config.base)]
        cl = closed_loop(m, config.base, setup, nom, np.zeros((1, T, 2)))
        traj[f"{m}_nominal"] = cl["X"][0, :, :2]
        traj[f"{m}_mc"] = results[next(t.key for t in main if t.method == m)]["positions"]
        nominal_info[m] = {**nom.info, "closed_loop_min_h": float(cl["min_h"][0]),
                           "closed_loop_final_distance": float(cl["final_distance"][0]),
                           "closed_loop_infeasible_qp_steps": int(cl["infeasible_steps"][0])}
    atomic_write_bytes(out / ".cache" / "trajectories.npz", _npz_bytes(**traj))

    summary = {
        "study": "tracking_comparison", "config": config.as_dict(), "setup": setup.fixed(),
        "scene": setup.scene.assumed_values(),
        "methods": methods, "paper": PAPER, "nominal": nominal_info,
        "assumed": assumed_values(config, setup),
        "ranking_main": _ranking(methods), "sweep": sweep_table, "sweep_ranking": sweep_ranking,
        "tasks": {"total": len(tasks), "computed": len(pending),
                  "loaded": len(tasks) - len(pending)},
        "wall_time_s": time.perf_counter() - t_start, "manifest": manifest(),
    }
    atomic_write_text(out / "rollouts.csv",
                      _csv(pd.concat(frames.values(), ignore_index=True), "%.10g"))
    atomic_write_text(out / "sweep.csv", _csv(pd.DataFrame(sweep_table), "%.6g"))
    atomic_write_json(out / "summary.json", summary)
    return summary

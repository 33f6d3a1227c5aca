"""The study's task: one SA-RMPPI episode on the navigation map at one velocity variance, with
the Lemma-1 estimators and checks (workbench.bound) at every step, stored as a per-step tidy
table ``steps`` (no per-sample arrays)."""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from studies.free_energy_bound.config import CONSTANTS, RESULT_VERSION, TESTS, StudyConfig
from studies.free_energy_bound.shared import Shared, bound_config, controller, grid, navigation
from workbench.bound import BoundEstimator, BoundStep, episode_checks, independent_batch
from workbench.sim import Disturbance, closed_loop
from workbench.study import TaskContext, TaskOutput
from workbench.study.latency import step_table
from workbench.study.spec import Declaration
from workbench.validation import as_array


@dataclass(frozen=True)
class Episode:
    """Episode ``episode`` at velocity variance ``variance``, at most ``steps`` plant steps."""

    variance: float
    episode: int
    steps: int

    def stream_key(self) -> tuple[int, int]:
        return round(self.variance * 1000), self.episode


class Recorder:
    """Controller wrapper for ``sim.closed_loop``: each step's first SAIS batch goes to the
    estimators (with an independent batch of the same step for T2E) and is then dropped."""

    def __init__(self, est: BoundEstimator, rng: np.random.Generator, independent: bool):
        self.est, self.ctrl, self.rng, self.independent = est, est.ctrl, rng, independent
        self.records: list[BoundStep] = []
        self.step_s: list[float] = []  # the controller's step alone: wall and process CPU
        self.cpu_s: list[float] = []
        self.bound_s: list[float] = []

    def initial_state(self, x0):
        return self.ctrl.initial_state(x0)

    def step(self, state, x, rng):
        t0, c0 = time.perf_counter(), time.process_time()
        state, u, info = self.ctrl.step(state, x, rng)
        t1, c1 = time.perf_counter(), time.process_time()
        ind = None
        if self.independent:
            seed = int(self.rng.integers(2**31))
            ind = independent_batch(self.ctrl, info.batch, seed if seed != info.batch.seed
                                    else seed + 1)
        self.records.append(self.est.step(info.batch, info, x, u, independent=ind))
        self.step_s.append(t1 - t0)
        self.cpu_s.append(c1 - c0)
        self.bound_s.append(time.perf_counter() - t1)
        return state, u, replace(info, batch=None)


def step_rows(records: list[BoundStep], clearance=None) -> dict[str, np.ndarray]:
    """One row per step: estimator values, strata flags and every check's holds (1/0, nan where
    not evaluated: T3* at an episode's last step, T2E without an independent batch, T1s when no
    sample pair stayed safe), slack, lhs, rhs and Lipschitz term, per set of constants (local,
    global, sampled tube); ``clearance`` (one per step: the measured position's distance to the
    nearest obstacle's edge) or nan."""
    n = len(records)
    checks = episode_checks(records)
    col = {"step": np.arange(n)}
    col["clearance"] = (np.full(n, np.nan) if clearance is None
                        else as_array("clearance", clearance, (n,)))

    def put(name, f, dtype=float):
        col[name] = np.array([f(s) for s in records], dtype=dtype)

    for name, f in {
        "F_real": lambda s: s.F_real.value, "F_nom": lambda s: s.F_nom.value,
        "F_real_code": lambda s: s.F_real_code, "F_nom_code": lambda s: s.F_nom_code,
        "E": lambda s: s.E, "ess_real": lambda s: s.F_real.ess, "alpha": lambda s: s.alpha,
        "R": lambda s: s.tube.R, "R99": lambda s: s.tube.R99,
        "R_position": lambda s: s.tube.R_position, "L_q": lambda s: s.local.L_q,
        "L_phi": lambda s: s.local.L_phi, "secant_q": lambda s: s.local.secant_q,
        "secant_phi": lambda s: s.local.secant_phi, "L_q_global": lambda s: s.global_.L_q,
        "L_phi_global": lambda s: s.global_.L_phi, "D": lambda s: s.D, "D_F": lambda s: s.D_F,
        "delta_local": lambda s: s.delta("local"), "delta_global": lambda s: s.delta("global"),
        "F_nom_ind": lambda s: s.F_nom_ind, "delta_sampled": lambda s: s.delta_sampled,
        "delta_sampled_max": lambda s: s.delta_sampled_max,
    }.items():
        put(name, f)
    for name, f in {"n_q": lambda s: s.n_q, "n_samples": lambda s: s.n_samples,
                    "n_crashed_real": lambda s: s.n_crashed_real,
                    "n_crashed_nom": lambda s: s.n_crashed_nom,
                    "excluded_q": lambda s: s.local.excluded_q}.items():
        put(name, f, np.int64)
    for name, f in {"all_real_safe": lambda s: s.all_real_safe,
                    "fallback_used": lambda s: s.fallback_used,
                    "nominal_differs": lambda s: s.nominal_differs,
                    "nominal_admissible": lambda s: s.nominal_admissible,
                    "secant_ok": lambda s: s.local.secant_ok}.items():
        put(name, f, bool)
    # step t+1's flags on row t (False at the last step): the T3d premise and selection
    col["fallback_next"] = np.array([records[i + 1].fallback_used if i + 1 < n else False
                                     for i in range(n)], dtype=bool)
    col["nominal_admissible_next"] = np.array([records[i + 1].nominal_admissible if i + 1 < n
                                               else False for i in range(n)], dtype=bool)
    for t in TESTS:
        for c in CONSTANTS:
            for part in ("holds", "slack", "lhs", "rhs", "term"):
                col[f"{t}_{c}_{part}"] = np.full(n, np.nan)
    for i, cs in enumerate(checks):
        for ch in cs:
            if ch.test == "T1s" and not np.isfinite(records[i].t1_gap_safe):
                continue  # no sample pair stayed safe: nothing to test
            p = f"{ch.test}_{ch.constants}_"
            col[p + "holds"][i] = float(ch.holds)
            col[p + "slack"][i], col[p + "lhs"][i] = ch.slack, ch.lhs
            col[p + "rhs"][i], col[p + "term"][i] = ch.rhs, ch.lipschitz_term
    return col


def run_task(task: Episode, ctx: TaskContext, config: StudyConfig, shared: Shared) -> TaskOutput:
    """One episode: the tidy per-step table, the path, and episode facts in meta."""
    nav = navigation(config.n_samples, config.horizon)
    ctrl = controller(config, shared)
    if ctrl.sampler.lib is not None:
        ctrl.sampler.lib.set_threads(ctx.threads)
    dist = Disturbance(task.variance)
    est = BoundEstimator(ctrl, dist, bound_config(config), grid(config),
                         global_constant=shared.global_)
    rec = Recorder(est, ctx.rng(2), config.independent)
    ep = closed_loop(rec, nav.plant, nav.x0, task.steps, ctx.rng(0), ctx.rng(1), dist,
                     keep_infos=False)
    P = ep.X[: len(rec.records), :2]
    clear = np.min([np.linalg.norm(P - np.asarray(o.center), axis=1) - o.radius
                    for o in nav.plant.obstacles], axis=0) if nav.plant.obstacles else None
    row = {"crashed": bool(ep.crashed), "n_steps": len(rec.records),
           "final_distance": float(np.linalg.norm(ep.X[-1, :2] - nav.goal[:2]))}
    meta = {"step_ms_median": float(1e3 * np.median(rec.step_s)),  # timing: not a result
            "bound_ms_median": float(1e3 * np.median(rec.bound_s))}
    return TaskOutput(tables={"steps": step_rows(rec.records, clear),
                              "episodes": {k: np.array([v]) for k, v in row.items()},
                              "step_times": step_table(rec.step_s, rec.cpu_s)},
                      arrays={"path": ep.X[:, :2]}, meta=meta)


def tasks(config: StudyConfig) -> tuple[Episode, ...]:
    """Every (variance, episode), variance-major."""
    return tuple(Episode(v, j, config.steps) for v in config.variances
                 for j in range(config.episodes))


def run(task: Episode, ctx: TaskContext, config: StudyConfig, prepared: Shared) -> TaskOutput:
    """The framework's task function: the shared set-up comes prepared."""
    return run_task(task, ctx, config, prepared)


def declare(config: StudyConfig) -> Declaration:
    """The episodes of a run; results depend on the config's result values."""
    return Declaration(tasks(config), run, fingerprint={"config": config.results_dict()},
                       version=RESULT_VERSION)

"""Set-up computed once per study in the coordinating process and handed to every task: the
calibrated alpha threshold (an undisturbed run) and the global Lipschitz constants (a grid over
the whole map, seconds). Cached in the run directory as ``shared.json``, keyed by the config
values they depend on, so a resumed run does not recompute them."""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import asdict, dataclass
from functools import cache
from pathlib import Path

import numpy as np

from studies.free_energy_bound.config import StudyConfig
from workbench.bound import BoundConfig, CostGradients, Lipschitz, LipschitzGrid
from workbench.sampling.mppi import MPPIConfig
from workbench.sampling.robust import RMPPIConfig, RobustMPPI
from workbench.sampling.threshold import AlphaRule, ProgressThreshold
from workbench.scenarios.navigation import (
    TUNED_LAMBDA,
    TUNED_SIGMA,
    NavigationSetup,
    navigation_setup,
)
from workbench.study.io import atomic_write_json


@dataclass(frozen=True)
class Shared:
    """What every task gets: the threshold's knots (ProgressThreshold fields), the global
    constants and the description of the grid they were taken over."""

    log_d: tuple[float, ...]
    F: tuple[float, ...]
    kappa: float
    global_: Lipschitz
    no_barrier: Lipschitz  # global constants of q, φ in x̄ = [x; β], β a coordinate: no h chain
    grid: str
    setup_s: dict  # seconds spent: {"alpha": ..., "global": ...} (not a result)

    def threshold(self, nav: NavigationSetup) -> ProgressThreshold:
        return ProgressThreshold(np.array(self.log_d), np.array(self.F), self.kappa,
                                 nav.goal[:2].copy(), tuple(nav.plant.position))


def rule(config: StudyConfig) -> AlphaRule:
    return AlphaRule(kind="progress", kappa=config.kappa,
                     calibration_steps=config.calibration_steps)


def grid(config: StudyConfig) -> LipschitzGrid:
    return LipschitzGrid(spacing=config.grid_spacing, n_rings=config.grid_rings,
                         ring_angles=config.grid_angles)


def bound_config(config: StudyConfig) -> BoundConfig:
    return BoundConfig(z=config.z, n_q=config.n_q, space=config.space)


@cache
def navigation(n_samples: int, horizon: int) -> NavigationSetup:
    """The map, plant and barrier-embedded problem (once per process)."""
    return navigation_setup(mppi=MPPIConfig(n_samples=n_samples, horizon=horizon,
                                            sigma=TUNED_SIGMA, lam=TUNED_LAMBDA))


def controller(config: StudyConfig, shared: Shared) -> RobustMPPI:
    """SA-RMPPI (K_safe from BaS-iLQG) with the shared threshold, handing out its SAIS batch."""
    nav = navigation(config.n_samples, config.horizon)
    return RobustMPPI(nav.problem, nav.goal, nav.mppi, RMPPIConfig(diagnostics=True),
                      nav.feedback("bas_ilqg"), shared.threshold(nav))


def _key(config: StudyConfig) -> str:
    d = {k: v for k, v in config.results_dict().items() if k not in ("z", "n_q", "independent")}
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]


def compute(config: StudyConfig) -> Shared:
    nav = navigation(config.n_samples, config.horizon)
    t0 = time.perf_counter()
    th = nav.threshold(rule(config), "bas_ilqg", RMPPIConfig())
    t1 = time.perf_counter()
    g = grid(config)
    ctrl = RobustMPPI(nav.problem, nav.goal, nav.mppi, RMPPIConfig(), nav.feedback("bas_ilqg"),
                      th)
    p = np.asarray(ctrl.consts.p, float)
    glob = CostGradients(nav.problem, "auto", config.space).global_constant(g, p)
    t2 = time.perf_counter()
    plain = CostGradients(nav.problem, "auto", "augmented").global_constant(g, p)
    return Shared(tuple(map(float, th.log_d)), tuple(map(float, th.F)), float(th.kappa), glob,
                  plain, g.describe(nav.problem.eps_h),
                  {"alpha": t1 - t0, "global": t2 - t1, "no_barrier": time.perf_counter() - t2})


def load_or_compute(config: StudyConfig, out: Path) -> Shared:
    """The shared set-up from ``out/shared.json`` when it was computed for these values."""
    path, key = Path(out) / "shared.json", _key(config)
    if path.exists():
        try:
            d = json.loads(path.read_text())
            if d.get("key") == key:
                return Shared(tuple(d["log_d"]), tuple(d["F"]), d["kappa"],
                              Lipschitz(**d["global_"]), Lipschitz(**d["no_barrier"]),
                              d["grid"], d["setup_s"])
        except (ValueError, KeyError, TypeError):
            pass  # unreadable or old: recompute
    s = compute(config)
    atomic_write_json(path, {"key": key, **asdict(s)})
    return s

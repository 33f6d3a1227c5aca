"""SAIS Workbench: safety in sampling-based model predictive control, on CasADi.

Everything a user needs is importable from here (``import workbench as wb``)::

    model = wb.double_integrator(obstacles=(wb.Circle((2.0, 0.0), 0.5),))
    result, problem = wb.bas_ilqg(model, x0, x_ref, target)

Names load on first use, so ``import workbench`` stays fast. The layers, lowest first:
:mod:`workbench.problem` (models, obstacles, costs, barrier states, ``Problem``),
:mod:`workbench.ilqg` (iLQG, BaS-iLQG, AL-iLQG, the IPOPT oracle), :mod:`workbench.filters`
(the ECBF-QP), :mod:`workbench.sampling` (MPPI, RMPPI, SA-RMPPI on generated C),
:mod:`workbench.sim` (closed loop, disturbances), :mod:`workbench.scenarios` (scenes and their
set-ups), :mod:`workbench.bound` (Lemma-1 checks) and :mod:`workbench.study` (the study runner).
"""

from __future__ import annotations

import importlib
import sys
import types
from importlib import metadata
from typing import TYPE_CHECKING

try:
    __version__ = metadata.version("sais-workbench")
except metadata.PackageNotFoundError:  # run from a source tree that was never installed
    __version__ = "0+unknown"

_EXPORTS = {
    "workbench.problem.models": ("Model", "circle_scene", "double_integrator",
                                 "single_integrator"),
    "workbench.problem.obstacles": ("Circle", "circle_margins", "circles_from_arrays",
                                    "scene_symbol", "scene_vector", "slot_margins"),
    "workbench.problem.scene_kinds": ("Capsule", "HalfSpace", "MovingCircle", "SCENE_KINDS",
                                      "SceneKind", "Sphere", "register_scene_kind"),
    "workbench.problem.scene_layout": ("SceneLayout",),
    "workbench.problem.sdf_grid": ("SignedDistanceGrid",),
    "workbench.codegen.cache": ("build_counts",),
    "workbench.problem.costs": ("Cost", "quadratic_tracking"),
    "workbench.problem.problem": ("Problem",),
    "workbench.problem.barrier": ("BarrierOptions", "embed_barrier"),
    "workbench.ilqg.solver": ("ILQGOptions", "ILQGResult", "ilqg"),
    "workbench.ilqg.bas": ("TrackingWeights", "bas_ilqg", "tracking_params", "tracking_problem"),
    "workbench.ilqg.al": ("ALOptions", "ALResult", "al_ilqg", "al_problem"),
    "workbench.ilqg.oracle": ("solve_ipopt",),
    "workbench.filters.ecbf": ("ECBFFilter", "ECBFOptions"),
    "workbench.sampling.problem": ("SamplingProblem", "goal_costs", "navigation_costs"),
    "workbench.sampling.mppi": ("MPPI", "MPPIConfig"),
    "workbench.sampling.robust": ("RMPPIConfig", "RobustMPPI"),
    "workbench.sampling.feedback.base": ("FeedbackWeights",),
    "workbench.sampling.feedback.ilqg": ("ILQGFeedback",),
    "workbench.sampling.feedback.al": ("ALFeedback", "ALFeedbackOptions"),
    "workbench.sampling.feedback.ecbf": ("ECBFFeedback",),
    "workbench.sampling.step_stats": ("StepStats",),
    "workbench.sampling.samples": ("SampleTrajectories",),
    "workbench.sampling.methods.tube": ("TubeConfig", "TubeMPPI"),
    "workbench.sampling.methods.cbf_projection": ("CBFProjectionConfig", "CBFProjectionMPPI"),
    "workbench.sampling.methods.shield": ("ShieldConfig", "ShieldMPPI"),
    "workbench.sampling.methods.gatekeeper": ("Gatekeeper", "GatekeeperConfig",
                                              "backup_from_expression", "braking_backup",
                                              "model_braking_backup"),
    "workbench.problem.dcbf": ("DiscreteCBF", "discrete_cbf"),
    "workbench.sampling.threshold": ("AlphaRule", "ConstantThreshold", "ProgressThreshold",
                                     "make_threshold"),
    "workbench.sampling.calibration": ("calibrate", "calibration_trace"),
    "workbench.sampling.kernels.library": ("get_threads", "set_threads"),
    "workbench.sim": ("Disturbance", "Episode", "closed_loop", "scene_sequence"),
    "workbench.scenarios.scenes": ("CircleScene", "NavigationScene", "ObstacleScene",
                                   "TrackingScene"),
    "workbench.scenarios.occupancy": ("OccupancyMap", "load_map"),
    "workbench.scenarios.navigation": ("NavigationSetup", "navigation_setup"),
    "workbench.scenarios.methods": ("MethodSettings", "MethodSpec", "register_method",
                                    "method_names"),
    "workbench.scenarios.mechanism_health": ("MechanismWarning", "episode_health",
                                             "study_health"),
    "workbench.problem.vehicles": ("kinematic_bicycle", "planar_quadrotor", "unicycle"),
    "workbench.scenarios.systems": ("SYSTEMS", "System", "register_system", "system"),
    "workbench.scenarios.model_system": ("ModelScene", "system_from_model"),
    "workbench.scenarios.maps": ("LAYOUT_FAMILIES", "MAP_FAMILIES", "GeneratedMap",
                                 "MapDifficulty", "MapFamily", "difficulty", "generate"),
    "workbench.scenarios.tuned": ("ControllerSettings", "Tuned", "tuned"),
    "workbench.study.tuning": ("Param", "TuningBudget", "tune"),
    "workbench.study.stats": ("pooled_paired",),
    "workbench.scenarios.compare": ("compare_methods",),
}
_WHERE = {name: module for module, names in _EXPORTS.items() for name in names}
__all__ = [*sorted(_WHERE), "__version__"]


def __getattr__(name: str):
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module 'workbench' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


class _Workbench(types.ModuleType):
    """``wb.ilqg`` is the solver function although ``workbench.ilqg`` is also a subpackage:
    importing the subpackage makes the import system set it as this module's attribute, which
    would hide the function. The subpackage stays reachable through ``import workbench.ilqg``."""

    @property
    def ilqg(self):
        from workbench.ilqg.solver import ilqg

        return ilqg

    @ilqg.setter
    def ilqg(self, value) -> None:  # the import system's record of the subpackage: ignored
        pass


sys.modules[__name__].__class__ = _Workbench


if TYPE_CHECKING:  # for type checkers and IDEs: the same names, imported eagerly
    from workbench.codegen.cache import build_counts
    from workbench.filters.ecbf import ECBFFilter, ECBFOptions
    from workbench.ilqg.al import ALOptions, ALResult, al_ilqg, al_problem
    from workbench.ilqg.bas import TrackingWeights, bas_ilqg, tracking_params, tracking_problem
    from workbench.ilqg.oracle import solve_ipopt
    from workbench.ilqg.solver import ILQGOptions, ILQGResult, ilqg
    from workbench.problem.barrier import BarrierOptions, embed_barrier
    from workbench.problem.costs import Cost, quadratic_tracking
    from workbench.problem.models import (
        Model,
        circle_scene,
        double_integrator,
        single_integrator,
    )
    from workbench.problem.obstacles import (
        Circle,
        circle_margins,
        circles_from_arrays,
        scene_symbol,
        scene_vector,
        slot_margins,
    )
    from workbench.problem.problem import Problem
    from workbench.problem.scene_kinds import (
        SCENE_KINDS,
        Capsule,
        HalfSpace,
        MovingCircle,
        SceneKind,
        Sphere,
        register_scene_kind,
    )
    from workbench.problem.scene_layout import SceneLayout
    from workbench.problem.sdf_grid import SignedDistanceGrid
    from workbench.problem.vehicles import kinematic_bicycle, planar_quadrotor, unicycle
    from workbench.sampling.calibration import calibrate, calibration_trace
    from workbench.sampling.feedback import FeedbackWeights, ILQGFeedback
    from workbench.sampling.kernels.library import get_threads, set_threads
    from workbench.sampling.mppi import MPPI, MPPIConfig
    from workbench.sampling.problem import SamplingProblem, goal_costs, navigation_costs
    from workbench.sampling.robust import RMPPIConfig, RobustMPPI
    from workbench.sampling.samples import SampleTrajectories
    from workbench.sampling.threshold import AlphaRule, make_threshold
    from workbench.scenarios.compare import compare_methods
    from workbench.scenarios.maps import (
        LAYOUT_FAMILIES,
        MAP_FAMILIES,
        GeneratedMap,
        MapDifficulty,
        MapFamily,
        difficulty,
        generate,
    )
    from workbench.scenarios.mechanism_health import (
        MechanismWarning,
        episode_health,
        study_health,
    )
    from workbench.scenarios.methods import (
        MethodSettings,
        MethodSpec,
        method_names,
        register_method,
    )
    from workbench.scenarios.model_system import ModelScene, system_from_model
    from workbench.scenarios.navigation import NavigationSetup, navigation_setup
    from workbench.scenarios.occupancy import OccupancyMap, load_map
    from workbench.scenarios.scenes import (
        CircleScene,
        NavigationScene,
        ObstacleScene,
        TrackingScene,
    )
    from workbench.scenarios.systems import SYSTEMS, System, register_system, system
    from workbench.scenarios.tuned import ControllerSettings, Tuned, tuned
    from workbench.sim import Disturbance, Episode, closed_loop, scene_sequence
    from workbench.study.stats import pooled_paired
    from workbench.study.tuning import Param, TuningBudget, tune

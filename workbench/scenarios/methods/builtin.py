"""The ten built-in safe-sampling methods, one :class:`MethodSpec` each, registered in the
order of every table and figure.

Every method shares the set-up's sampler settings (N, T, sigma, lambda) and its map; each adds
its own safety mechanism (see each spec's ``mechanism``). Cost ranks: measured per step on the
navigation map (N = 1024, T = 100, one thread), slowest first.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from workbench.filters.ecbf import ECBFOptions
from workbench.sampling.feedback.al import ALFeedbackOptions
from workbench.sampling.methods.cbf_projection import CBFProjectionConfig, CBFProjectionMPPI
from workbench.sampling.methods.gatekeeper import Gatekeeper, GatekeeperConfig
from workbench.sampling.methods.shield import ShieldConfig, ShieldMPPI
from workbench.sampling.methods.tube import TubeConfig, TubeMPPI
from workbench.sampling.mppi import MPPI
from workbench.sampling.robust import RMPPIConfig, RobustMPPI
from workbench.scenarios.methods.feedback_laws import feedback_law
from workbench.scenarios.methods.settings import MethodSettings
from workbench.scenarios.methods.spec import MethodSpec, register
from workbench.study.tuning import Param

if TYPE_CHECKING:
    from workbench.sampling.feedback import FeedbackWeights
    from workbench.sampling.threshold import Threshold
    from workbench.scenarios.navigation import NavigationSetup


def _bas_mppi(nav: NavigationSetup, settings: MethodSettings) -> MPPI:
    return MPPI(nav.problem, nav.goal, nav.mppi)


def _mppi_crash(nav: NavigationSetup, settings: MethodSettings) -> MPPI:
    return MPPI(nav.physical_problem(), nav.goal, nav.mppi)


def _tube(nav: NavigationSetup, settings: MethodSettings) -> TubeMPPI:
    return TubeMPPI(nav.physical_problem(), nav.goal, nav.mppi, settings.tube)


def _cbf_projection(nav: NavigationSetup, settings: MethodSettings) -> CBFProjectionMPPI:
    return CBFProjectionMPPI(nav.physical_problem(), nav.goal, nav.mppi, settings.cbf_projection)


def _shield(nav: NavigationSetup, settings: MethodSettings) -> ShieldMPPI:
    return ShieldMPPI(nav.physical_problem(), nav.goal, nav.mppi, settings.shield)


def _gatekeeper(nav: NavigationSetup, settings: MethodSettings) -> Gatekeeper:
    return Gatekeeper(MPPI(nav.physical_problem(), nav.goal, nav.mppi), nav.plant,
                      nav.system.backup(nav.plant, settings.braking_gain), settings.gatekeeper)


def robust_builder(kind: str):
    """The build function of a robust method with feedback law ``kind``: Robust MPPI on the
    barrier-embedded problem with that law and the given selection threshold."""

    def build(nav: NavigationSetup, settings: MethodSettings, *, threshold: Threshold,
              robust: RMPPIConfig, weights: FeedbackWeights | None) -> RobustMPPI:
        law = feedback_law(nav, kind, settings, weights)
        return RobustMPPI(nav.problem, nav.goal, nav.mppi, robust, law, threshold)

    return build


BUILTIN = (
    MethodSpec("bas_mppi", "BaS-MPPI", "barrier state", _bas_mppi, marker="o", cost_rank=8),
    MethodSpec("sa_rmppi", "SA-RMPPI (K_safe)", "barrier state + BaS-iLQG feedback",
               robust_builder("bas_ilqg"), marker="s", feedback="bas_ilqg",
               activity="nominal_differs", requires=("margins", "tracking"), cost_rank=3,
               wraps="bas_mppi"),
    MethodSpec("rmppi", "RMPPI (iLQG)", "barrier state + tracking feedback",
               robust_builder("ilqg"), marker="^", feedback="ilqg",
               requires=("margins", "tracking"), cost_rank=4, wraps="bas_mppi"),
    MethodSpec("mppi_crash", "MPPI (crash cost)", "crash cost", _mppi_crash, marker="v",
               cost_rank=9),
    MethodSpec("tube_mppi", "Tube-MPPI", "crash cost + ancillary tracker", _tube, marker="D",
               options=TubeConfig, options_key="tube",
               tunable=(Param("tube.threshold", -100.0, 20.0, log=False),),
               activity="nominal_tracked", cost_rank=5, wraps="mppi_crash"),
    MethodSpec("cbf_projection", "CBF projection per sample", "per-sample CBF projection",
               _cbf_projection, marker="P", options=CBFProjectionConfig,
               options_key="cbf_projection",
               tunable=(Param("cbf_projection.gamma", 0.02, 1.0),), activity="projected",
               cost_rank=0, wraps="mppi_crash"),
    MethodSpec("shield_mppi", "Shield-MPPI", "DCBF cost + shield", _shield, marker="*",
               options=ShieldConfig, options_key="shield",
               tunable=(Param("shield.w_dcbf", 10.0, 1e5),), activity="shield_acted",
               cost_rank=6, wraps="mppi_crash"),
    MethodSpec("gatekeeper", "Gatekeeper (braking backup)", "crash cost + backup shield",
               _gatekeeper, marker="X", options=GatekeeperConfig, options_key="gatekeeper",
               tunable=(Param("gatekeeper.horizon", 20, 120, log=False, integer=True),),
               activity="backup_used", cost_rank=7, wraps="mppi_crash"),
    MethodSpec("sais_al", "SAIS + AL-iLQG gains", "barrier state + AL feedback",
               robust_builder("al_ilqg"), marker="h", feedback="al_ilqg",
               options=ALFeedbackOptions, options_key="al", activity="al_active",
               requires=("margins", "tracking"), cost_rank=2, wraps="bas_mppi"),
    MethodSpec("sais_ecbf", "SAIS + ECBF-filtered gains", "barrier state + ECBF feedback",
               robust_builder("ecbf"), marker="p", feedback="ecbf", options=ECBFOptions,
               options_key="ecbf", activity="ecbf_active",
               requires=("margins", "tracking", "relative_degree"),
               cost_rank=1, wraps="bas_mppi"),
)

for _spec in BUILTIN:  # once per process: this module is imported once
    register(_spec)

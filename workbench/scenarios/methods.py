"""The safe-sampling methods on a navigation set-up, by name, with their options as one
frozen config: what the sampling-safety study compares.

Every method shares the set-up's sampler settings (N, T, sigma, lambda) and its map; each adds
its own safety mechanism:

========================  ==================================================================
``bas_mppi``              MPPI on the barrier-embedded model (barrier state in the cost)
``sa_rmppi``              Robust MPPI, SAIS sampler, K_safe = BaS-iLQG gains
``rmppi``                 Robust MPPI, SAIS sampler, plain iLQG tracking gains
``mppi_crash``            MPPI on the plain model with a crash cost only
``tube_mppi``             Tube-MPPI: MPPI on a nominal state + an iLQG ancillary tracker
``cbf_projection``        MPPI whose every sample is projected onto the discrete CBF constraint
``shield_mppi``           discrete-CBF violation cost + a shield repairing the applied control
``gatekeeper``            crash-cost MPPI behind a backup shield (braking)
``sais_al``               Robust MPPI, SAIS sampler, gains of an augmented-Lagrangian iLQG
``sais_ecbf``             Robust MPPI, SAIS sampler, gains of an ECBF-filtered tracking law
========================  ==================================================================
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import casadi as ca
import numpy as np

from workbench.filters.ecbf import ECBFOptions
from workbench.problem.models import Model
from workbench.sampling.feedback import FeedbackWeights
from workbench.sampling.feedback.al import ALFeedback, ALFeedbackOptions
from workbench.sampling.feedback.ecbf import ECBFFeedback
from workbench.sampling.methods.cbf_projection import CBFProjectionConfig, CBFProjectionMPPI
from workbench.sampling.methods.gatekeeper import Gatekeeper, GatekeeperConfig
from workbench.sampling.methods.shield import ShieldConfig, ShieldMPPI
from workbench.sampling.methods.tube import TubeConfig, TubeMPPI
from workbench.sampling.mppi import MPPI
from workbench.sampling.planning import physical_model
from workbench.sampling.robust import RMPPIConfig, RobustMPPI
from workbench.validation import fail, one_of

if TYPE_CHECKING:
    from workbench.sampling.threshold import Threshold
    from workbench.scenarios.navigation import NavigationSetup

METHODS = ("bas_mppi", "sa_rmppi", "rmppi", "mppi_crash", "tube_mppi", "cbf_projection",
           "shield_mppi", "gatekeeper", "sais_al", "sais_ecbf")
ROBUST_METHODS = ("sa_rmppi", "rmppi", "sais_al", "sais_ecbf")  # calibrate a threshold
NAMES = {"bas_mppi": "BaS-MPPI", "sa_rmppi": "SA-RMPPI (K_safe)", "rmppi": "RMPPI (iLQG)",
         "mppi_crash": "MPPI (crash cost)", "tube_mppi": "Tube-MPPI",
         "cbf_projection": "CBF projection per sample", "shield_mppi": "Shield-MPPI",
         "gatekeeper": "Gatekeeper (braking backup)", "sais_al": "SAIS + AL-iLQG gains",
         "sais_ecbf": "SAIS + ECBF-filtered gains"}
MECHANISM = {"bas_mppi": "barrier state", "sa_rmppi": "barrier state + BaS-iLQG feedback",
             "rmppi": "barrier state + tracking feedback", "mppi_crash": "crash cost",
             "tube_mppi": "crash cost + ancillary tracker",
             "cbf_projection": "per-sample CBF projection", "shield_mppi": "DCBF cost + shield",
             "gatekeeper": "crash cost + backup shield",
             "sais_al": "barrier state + AL feedback", "sais_ecbf": "barrier state + ECBF feedback"}
# slowest first (measured on the navigation map, N = 1024, T = 100, one thread): the order in
# which studies dispatch their tasks
SLOWEST_FIRST = ("cbf_projection", "sais_ecbf", "sais_al", "sa_rmppi", "rmppi", "tube_mppi",
                 "shield_mppi", "gatekeeper", "bas_mppi", "mppi_crash")
FEEDBACK = {"sa_rmppi": "bas_ilqg", "rmppi": "ilqg", "sais_al": "al_ilqg", "sais_ecbf": "ecbf"}


@dataclass(frozen=True)
class MethodSettings:
    """Each method's own options (the sampler settings are the set-up's)."""

    tube: TubeConfig = field(default_factory=TubeConfig)
    cbf_projection: CBFProjectionConfig = field(default_factory=CBFProjectionConfig)
    shield: ShieldConfig = field(default_factory=ShieldConfig)
    gatekeeper: GatekeeperConfig = field(default_factory=GatekeeperConfig)
    # [A] the backup's u = -gain v (clipped); None: 1/dt, which stops each axis within 50
    # steps from 5 m/s, inside the gatekeeper's 60-step horizon. Other systems: the gain of
    # their own backup law (System.backup; the bicycle brakes a = -gain v, the quadrotor's
    # hover law uses it as its velocity gain, the unicycle's stop ignores it)
    braking_gain: float | None = None
    al: ALFeedbackOptions = field(default_factory=ALFeedbackOptions)
    ecbf: ECBFOptions = field(default_factory=ECBFOptions)

    def __post_init__(self) -> None:
        for name, kind in (("tube", TubeConfig), ("cbf_projection", CBFProjectionConfig),
                           ("shield", ShieldConfig), ("gatekeeper", GatekeeperConfig),
                           ("al", ALFeedbackOptions), ("ecbf", ECBFOptions)):
            if not isinstance(getattr(self, name), kind):
                raise fail(f"methods.{name}", getattr(self, name), f"must be a {kind.__name__}")
        g = self.braking_gain
        if g is not None and not (isinstance(g, int | float) and not isinstance(g, bool)
                                  and np.isfinite(g) and g > 0):
            raise fail("methods.braking_gain", g, "must be a finite number > 0 (or left out: "
                       "1/dt)")


def affine_in_controls(model: Model) -> Model:
    """``model`` itself when its step is affine in u, else its first-order expansion in u
    about u = 0, F(x, 0) + dF/du(x, 0) u (same margins, box and names; for the kinematic
    bicycle tan(delta) becomes delta, 8.5 % less turn rate at the 0.5 rad steering limit)."""
    if not ca.depends_on(ca.jacobian(model.x_next, model.u), model.u):
        return model
    u0 = ca.DM.zeros(model.nu)
    f0 = ca.substitute(model.x_next, model.u, u0)
    g0 = ca.substitute(ca.jacobian(model.x_next, model.u), model.u, u0)
    return replace(model, name=f"{model.name}~affine", x_next=f0 + ca.mtimes(g0, model.u))


def feedback_law(nav: NavigationSetup, kind: str, settings: MethodSettings = MethodSettings(),
                 weights: FeedbackWeights | None = None):
    """The feedback law of a robust method: "bas_ilqg" (K_safe), "ilqg", "al_ilqg", "ecbf"
    (the last two act on the plain model; gains on the barrier state are zero). ``weights``:
    tracking weights (default: the system's). The ECBF filter needs dynamics affine in u: for
    a system without them (the kinematic bicycle) its gains come from
    :func:`affine_in_controls` of the plant (the sampler keeps the true model)."""
    one_of("feedback", kind, ("bas_ilqg", "ilqg", "al_ilqg", "ecbf"))
    weights = nav.system.feedback_weights if weights is None else weights
    if kind in ("bas_ilqg", "ilqg"):
        return nav.feedback(kind, weights)
    plain = physical_model(nav.problem.model)
    if kind == "al_ilqg":
        return ALFeedback(plain, nav.mppi.horizon, nav.problem.nx, weights, settings.al)
    return ECBFFeedback(affine_in_controls(plain), nav.mppi.horizon, nav.problem.nx, weights,
                        settings.ecbf)


def build(nav: NavigationSetup, name: str, settings: MethodSettings = MethodSettings(), *,
          threshold: Threshold | None = None, robust: RMPPIConfig = RMPPIConfig(),
          weights: FeedbackWeights | None = None):
    """The controller ``name`` (one of :data:`METHODS`) on ``nav``. Robust methods need a
    ``threshold`` calibrated with their own feedback law (``nav.threshold(rule, feedback=
    FEEDBACK[name])``); ``robust`` and ``weights`` are their selection and tracking settings
    (weights default to the system's). The gatekeeper's backup is the system's
    (:attr:`~workbench.scenarios.systems.System.backup`: braking for the double integrator)."""
    one_of("controller", name, METHODS)
    phys = nav.physical_problem()
    if name == "bas_mppi":
        return MPPI(nav.problem, nav.goal, nav.mppi)
    if name == "mppi_crash":
        return MPPI(phys, nav.goal, nav.mppi)
    if name == "tube_mppi":
        return TubeMPPI(phys, nav.goal, nav.mppi, settings.tube)
    if name == "cbf_projection":
        return CBFProjectionMPPI(phys, nav.goal, nav.mppi, settings.cbf_projection)
    if name == "shield_mppi":
        return ShieldMPPI(phys, nav.goal, nav.mppi, settings.shield)
    if name == "gatekeeper":
        return Gatekeeper(MPPI(phys, nav.goal, nav.mppi), nav.plant,
                          nav.system.backup(nav.plant, settings.braking_gain),
                          settings.gatekeeper)
    if threshold is None:
        raise fail("threshold", None, f"{name} is a robust controller: give its selection "
                   f"threshold, calibrated with its own feedback law (nav.threshold(rule, "
                   f"feedback={FEEDBACK[name]!r})), or use nav.controller({name!r}), which "
                   "calibrates one")
    law = feedback_law(nav, FEEDBACK[name], settings, weights)
    return RobustMPPI(nav.problem, nav.goal, nav.mppi, robust, law, threshold)

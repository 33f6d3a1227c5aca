"""The feedback laws of the robust methods on a navigation set-up, by kind."""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import casadi as ca

from workbench.problem.models import Model
from workbench.sampling.feedback import FeedbackWeights
from workbench.sampling.feedback.al import ALFeedback
from workbench.sampling.feedback.ecbf import ECBFFeedback
from workbench.sampling.planning import physical_model
from workbench.scenarios.methods.settings import MethodSettings
from workbench.scenarios.methods.spec import FEEDBACK_LAWS
from workbench.validation import one_of

if TYPE_CHECKING:
    from workbench.scenarios.navigation import NavigationSetup


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


def feedback_law(nav: NavigationSetup, kind: str, settings: MethodSettings | None = None,
                 weights: FeedbackWeights | None = None):
    """The feedback law of a robust method: "bas_ilqg" (K_safe), "ilqg", "al_ilqg", "ecbf"
    (the last two act on the plain model; gains on the barrier state are zero), with the AL
    and ECBF options of ``settings`` (default options when None). ``weights``: tracking
    weights (default: the system's). The ECBF filter needs dynamics affine in u: for a system
    without them (the kinematic bicycle) its gains come from :func:`affine_in_controls` of the
    plant (the sampler keeps the true model)."""
    one_of("feedback", kind, FEEDBACK_LAWS)
    weights = nav.system.feedback_weights if weights is None else weights
    settings = MethodSettings() if settings is None else settings
    if kind in ("bas_ilqg", "ilqg"):
        return nav.feedback(kind, weights)
    plain = physical_model(nav.problem.model)
    if kind == "al_ilqg":
        return ALFeedback(plain, nav.mppi.horizon, nav.problem.nx, weights, settings.al)
    return ECBFFeedback(affine_in_controls(plain), nav.mppi.horizon, nav.problem.nx, weights,
                        settings.ecbf)

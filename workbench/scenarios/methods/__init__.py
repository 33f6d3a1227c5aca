"""The safe-sampling methods by name: one registry (:mod:`.spec`), the built-in catalogue
(:mod:`.builtin`), each method's options (:class:`MethodSettings`) and :func:`build`.

``names()`` lists every registered method in table order; ``method(name)`` is its
:class:`MethodSpec` (label, mechanism, marker, feedback law, options, tunable parameters,
requirements). Add a method with :func:`register` (see :class:`MethodSpec`).
"""

from __future__ import annotations

import contextlib
from typing import TYPE_CHECKING

from workbench.sampling.robust import RMPPIConfig
from workbench.scenarios.methods.builtin import BUILTIN as BUILTIN
from workbench.scenarios.methods.feedback_laws import affine_in_controls, feedback_law
from workbench.scenarios.methods.settings import MethodSettings, check_fields
from workbench.scenarios.methods.spec import (
    FEEDBACK_LAWS,
    REQUIREMENTS,
    MethodSpec,
    labels,
    markers,
    method,
    methods,
    names,
    register,
    robust_names,
    slowest_first,
    unregister,
)
from workbench.scenarios.plugins import load_plugins
from workbench.validation import fail

if TYPE_CHECKING:
    from workbench.sampling.feedback import FeedbackWeights
    from workbench.sampling.threshold import Threshold
    from workbench.scenarios.navigation import NavigationSetup

register_method = register  # the names of the top-level API (``wb.register_method``)
method_names = names

check_fields()
load_plugins()  # $WORKBENCH_PLUGINS: your own methods and systems


def build(nav: NavigationSetup, name: str, settings: MethodSettings | None = None, *,
          threshold: Threshold | None = None, robust: RMPPIConfig | None = None,
          weights: FeedbackWeights | None = None):
    """The controller ``name`` (a registered method) on ``nav``. Robust methods need a
    ``threshold`` calibrated with their own feedback law (``nav.threshold(rule, feedback=
    method(name).feedback)``); ``robust`` and ``weights`` are their selection and tracking
    settings (weights default to the system's). A method that needs what the set-up's system
    lacks (:attr:`MethodSpec.requires`) is refused with the reason.

    A controller of a method with a mechanism (:attr:`MethodSpec.activity`) and without a
    ``check_episode`` of its own gets one: :func:`workbench.sim.closed_loop` then warns when
    the mechanism never acted or acted on every step
    (:mod:`workbench.scenarios.mechanism_health`)."""
    ctrl = _build(nav, name, settings, threshold, robust, weights)
    if method(name).activity is not None and getattr(ctrl, "check_episode", None) is None:
        from workbench.scenarios.mechanism_health import EpisodeCheck

        with contextlib.suppress(AttributeError, TypeError):  # a controller without __dict__
            ctrl.check_episode = EpisodeCheck(name)
    return ctrl


def _build(nav: NavigationSetup, name: str, settings: MethodSettings | None,
           threshold: Threshold | None, robust: RMPPIConfig | None,
           weights: FeedbackWeights | None):
    spec = method(name)
    settings = MethodSettings() if settings is None else settings
    why = spec.missing(nav, weights)
    if why is not None:
        raise fail("controller", name, why)
    if not spec.robust:
        return spec.build(nav, settings)
    if threshold is None:
        raise fail("threshold", None, f"{name} is a robust controller: give its selection "
                   f"threshold, calibrated with its own feedback law (nav.threshold(rule, "
                   f"feedback={spec.feedback!r})), or use nav.controller({name!r}), which "
                   "calibrates one")
    return spec.build(nav, settings, threshold=threshold,
                      robust=RMPPIConfig() if robust is None else robust, weights=weights)


__all__ = ["FEEDBACK_LAWS", "REQUIREMENTS", "MethodSettings", "MethodSpec", "affine_in_controls",
           "build", "feedback_law", "labels", "markers", "method", "method_names", "methods",
           "names", "register", "register_method", "robust_names", "slowest_first",
           "unregister"]

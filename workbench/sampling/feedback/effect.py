"""What counts as a safety mechanism acting: an effect on what reaches the plant, never a call.

Every method's activity (:attr:`~workbench.sampling.step_stats.StepStats.activity`, the key a
method declares in :attr:`~workbench.scenarios.methods.MethodSpec.activity`) counts a step, a
sample-step or a horizon step only when the mechanism changed the applied control, or the
samples' controls, costs or the gains that determine it, by more than :data:`EFFECT_RTOL`
(:func:`differs`; assumptions §12.3). A mechanism that runs but leaves those numbers as they
were reports 0 there. Per mechanism:

- ``nominal_differs`` (SA-RMPPI, and every Robust MPPI): the selected nominal state differs
  from the measured one, so the batch starts there and the feedback enters the samples and the
  applied control.
- ``al_active`` / ``ecbf_active`` (the AL and ECBF feedback laws): the share of horizon steps
  where the law's gains differ from the plain tracking gains (an active penalty term; a
  filter row that replaced the tracking gain), and only on steps where the nominal state
  differs from the measured one: otherwise x - x* is 0 in every sample and in the applied
  control, and no gain reaches the plant (:class:`~workbench.sampling.robust.RMPPIInfo`).
- ``nominal_tracked`` (Tube-MPPI): the applied control (nominal plan plus tracking feedback)
  differs from the first control of the plan from the measured state, the one MPPI applies.
- ``projected`` (CBF projection): the share of sample-steps whose control the projection
  moved; ``applied_projected``: the applied control was moved.
- ``shield_acted`` (Shield-MPPI): the repaired control differs from the proposal;
  ``dcbf_active``: the share of samples whose cost the DCBF term raised.
- ``backup_used`` (Gatekeeper): the backup's control was applied and differs from the
  proposal.

Fallbacks (``feedback_fallback``, ``selection_fallback``, ``shield_failed``, ``infeasible``,
``ecbf_infeasible``, ``backup_not_at_rest``) and ``nominal_reset`` are events: how often the
method took that path, whatever its effect.
"""

from __future__ import annotations

import numpy as np

# A number changed when it moved by more than this, relative to max(1, |before|, |after|) per
# element: far above the rounding of one operation (2.2e-16) or of a closed loop's last bits
# (~1e-11 relative, see workbench.sampling.robust_step), far below any change that moves a
# plant (a control of 1e-9 m/s^2 moves the double integrator 2e-13 m in a step).
EFFECT_RTOL = 1e-9


def differs(a, b, axis=None) -> np.ndarray:
    """Whether ``a`` and ``b`` differ by more than :data:`EFFECT_RTOL` in some element:
    |a - b| > EFFECT_RTOL max(1, |a|, |b|). ``axis``: the axes to reduce over (None: all,
    giving one bool); non-finite entries differ unless equal."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    with np.errstate(invalid="ignore"):
        scale = np.maximum(1.0, np.maximum(np.abs(a), np.abs(b)))
        moved = ~(np.abs(a - b) <= EFFECT_RTOL * scale) & ~(a == b)
    return moved.any(axis=axis)

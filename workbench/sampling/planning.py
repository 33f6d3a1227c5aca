"""Planning helpers shared by every sampling controller: the measured state as a full
(lifted) state, the plan's validity check and its receding-horizon shift, the batch constants
of a goal in a scene, and the physical part of a barrier-embedded model."""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from workbench.problem.models import Model
from workbench.sampling.kernels.constants import SamplerConstants
from workbench.sampling.problem import SamplingProblem
from workbench.validation import as_array, fail

if TYPE_CHECKING:
    from workbench.sampling.mppi import MPPIConfig


def shift_plan(U: np.ndarray, s: int, tail: str) -> np.ndarray:
    """The plan ``U`` (T, nu) slid ``s`` steps forward; the last ``s`` rows repeat the last
    control (``tail="hold"``) or are zero."""
    if s == 0:
        return U
    out = np.empty_like(U)
    out[:-s] = U[s:]
    out[-s:] = U[-1] if tail == "hold" else 0.0
    return out


def full_state(sp: SamplingProblem, x, scene=None) -> np.ndarray:
    """The measured state ``x`` as the problem's full state: a physical state is lifted in
    ``scene`` (barrier-embedded models), a full one is checked and returned."""
    x = np.asarray(x, dtype=float).ravel()
    if not np.all(np.isfinite(x)):
        raise fail("x", x, "the measured state must be finite")
    if x.size == sp.model.n_physical and sp.nx != x.size:
        return sp.model.lift(x, scene)
    return as_array("x", x, (sp.nx,))


def frozen_goal(goal) -> np.ndarray:
    """``goal`` as a read-only float vector (a controller's public ``goal``)."""
    g = np.array(goal, dtype=float).ravel()
    g.flags.writeable = False
    return g


def plan_constants(sp: SamplingProblem, goal,
                   config: MPPIConfig) -> tuple[SamplerConstants, np.ndarray | None]:
    """The batch constants of a controller planning to ``goal`` with ``config`` in the model's
    own scene, and the physical goal to lift again in every new scene (None when the goal is
    not lifted: a full state, or cost parameters that are not a state)."""
    g = np.asarray(goal, dtype=float).ravel()
    # a physical goal is lifted in the current scene (beta_g = B(h(p_g))), again per scene
    lift = g if sp.n_p == sp.nx and g.size == sp.model.n_physical != sp.nx else None
    p = full_state(sp, goal) if sp.n_p == sp.nx else as_array("goal", goal, (sp.n_p,))
    consts = SamplerConstants(
        sigma=np.array(config.sigma), lam=config.lam, nu_mix=config.nu_mix,
        u_min=sp.model.u_min, u_max=sp.model.u_max, crash_cost=config.crash_cost, p=p,
        scene=sp.model.scene_value.copy())
    return consts, lift


def constants_in_scene(sp: SamplingProblem, consts: SamplerConstants, goal: np.ndarray | None,
                       scene) -> SamplerConstants:
    """``consts`` in ``scene`` (circles or a flat vector), the goal ``goal`` (from
    :func:`plan_constants`) lifted there when it is one to lift."""
    s = sp.model.scene_vector(scene)
    p = consts.p if goal is None else sp.model.lift(goal, s)
    return replace(consts, scene=s, p=p)


def check_plan(U: np.ndarray, T: int, nu: int) -> None:
    """Refuse a plan (``state.U``) that is not a finite (T, nu) array."""
    if not isinstance(U, np.ndarray) or U.shape != (T, nu) or not np.all(np.isfinite(U)):
        raise fail("state.U", getattr(U, "shape", U),
                   f"the plan must be a finite ({T}, {nu}) array")


def physical_model(m: Model) -> Model:
    """The physical part of a barrier-embedded model, as a plain Model."""
    n = m.n_physical
    return Model.from_expressions(
        m.name.replace("+bas", ""), m.x[:n], m.u, m.x_next[:n], dt=m.dt, u_min=m.u_min,
        u_max=m.u_max, h=m.h if m.nh else None, state_names=m.state_names[:n],
        control_names=m.control_names, position=m.position, obstacles=m.obstacles,
        scene=m.scene, scene_value=m.scene_value, scene_capacity=m.scene_capacity,
        scene_layout=m.scene_layout,
        state_units=None if m.state_units is None else m.state_units[:n])


class PlansToGoal:
    """What MPPI and the safe-MPPI planner share: the goal they plan to (``goal``, read-only,
    as given), the scene they plan in (``scene``) and :meth:`set_scene`. Set up with
    :meth:`_plan_to` after ``self.sp``."""

    sp: SamplingProblem
    consts: SamplerConstants

    def _plan_to(self, goal, config) -> None:
        self.consts, self._lift = plan_constants(self.sp, goal, config)
        self._target = frozen_goal(goal)

    @property
    def goal(self) -> np.ndarray:
        """The goal this controller was built with (read-only; a physical state, or the cost
        parameters of a problem whose goal is not a state)."""
        return self._target

    @property
    def scene(self) -> np.ndarray:
        """The current scene vector."""
        return self.consts.scene

    def set_scene(self, scene) -> None:
        """Plan in ``scene`` from the next step on: circles (a sequence of
        :class:`~workbench.problem.Circle` or (x, y, radius) triples, at most the model's
        ``scene_capacity``) or a flat scene vector (see
        :meth:`~workbench.problem.Model.scene_vector`). Costs microseconds."""
        self.consts = constants_in_scene(self.sp, self.consts, self._lift, scene)

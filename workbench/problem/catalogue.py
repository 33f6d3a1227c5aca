"""The model factories the workbench ships, by name: what ``workbench list`` prints under
"models". Each builds a :class:`~workbench.problem.models.Model` with obstacles given as
circles (or a general margin through ``Model.from_expressions``)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from workbench.problem.models import Model, double_integrator, single_integrator
from workbench.problem.vehicles import kinematic_bicycle, planar_quadrotor, unicycle


@dataclass(frozen=True)
class ModelEntry:
    """A shipped model factory and one line on what it models."""

    factory: Callable[..., Model]
    text: str

    @property
    def call(self) -> str:
        return f"workbench.{self.factory.__name__}(...)"


MODELS: dict[str, ModelEntry] = {
    "double_integrator": ModelEntry(
        double_integrator, "planar double integrator, state (px, py, vx, vy), control (ax, ay)"),
    "single_integrator": ModelEntry(
        single_integrator, "planar single integrator, state (px, py), control (vx, vy)"),
    "unicycle": ModelEntry(
        unicycle, "kinematic unicycle, state (px, py, theta), control (v, omega)"),
    "kinematic_bicycle": ModelEntry(
        kinematic_bicycle, "kinematic bicycle, state (px, py, theta, v), control (a, delta)"),
    "planar_quadrotor": ModelEntry(
        planar_quadrotor, "planar quadrotor in the x-z plane, state (x, x_dot, z, z_dot, "
        "theta, theta_dot), control (T1, T2) or hover offsets (dT1, dT2)"),
}

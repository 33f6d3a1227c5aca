"""Discrete barrier states (DBaS, assumptions §4): embed safety margins into the dynamics.

beta_{k+1} = sum_{i in g} B(h_i(F(x_k,u_k))) - gamma (beta_k - sum_{i in g} B(h_i(x_k)))

Crash handling (assumptions §4.6): when any margin of a group is <= eps_h the state is set to
beta_max,
and beta is capped at beta_max everywhere, so penetration is never rewarded by the negative
values the inverse barrier takes inside an obstacle.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import casadi as ca
import numpy as np

from workbench.problem.models import Model
from workbench.problem.prediction import predicts, scene_sx_at
from workbench.validation import fail, one_of, real

BarrierKind = Literal["inverse", "log", "exp"]
BARRIER_KINDS: tuple[str, ...] = ("inverse", "log", "exp")


@dataclass(frozen=True)
class BarrierOptions:
    """How margins become barrier states.

    kind: inverse 1/h (default, [DBaS-code]); log -log(h/(1+h)); exp exp(-kappa h) (assumptions
    §13 B1: the
    paper's "exponential" barrier, which does not blow up at h=0 — flagged, not the default).
    grouping: "sum" (one summed state, default), "per_obstacle", or a tuple of index groups.
    """

    kind: BarrierKind = "inverse"
    grouping: Literal["sum", "per_obstacle"] | tuple[tuple[int, ...], ...] = "sum"
    gamma: float = 0.0
    kappa: float = 1.0
    beta_max: float = 1e6
    eps_h: float = 1e-6

    def __post_init__(self) -> None:
        one_of("BarrierOptions.kind", self.kind, BARRIER_KINDS)
        if isinstance(self.grouping, str):
            one_of("BarrierOptions.grouping", self.grouping, ("sum", "per_obstacle"))
        real("BarrierOptions.gamma", self.gamma, -1.0, maximum=1.0)
        real("BarrierOptions.kappa", self.kappa, 0.0, strict=True)
        real("BarrierOptions.beta_max", self.beta_max, 0.0, strict=True)
        real("BarrierOptions.eps_h", self.eps_h, 0.0)

    def groups(self, nh: int) -> tuple[tuple[int, ...], ...]:
        """Index groups of margins, one per barrier state."""
        if nh == 0:
            raise fail("model.h", nh, "a barrier state needs at least one safety margin")
        if self.grouping == "sum":
            return (tuple(range(nh)),)
        if self.grouping == "per_obstacle":
            return tuple((i,) for i in range(nh))
        flat = sorted(i for g in self.grouping for i in g)
        if flat != list(range(nh)) or any(len(g) == 0 for g in self.grouping):
            raise fail("BarrierOptions.grouping", self.grouping,
                       f"groups must partition the margin indices 0..{nh - 1}")
        return tuple(tuple(g) for g in self.grouping)

    def barrier(self, eta):
        """B(eta) on CasADi or NumPy values."""
        if self.kind == "inverse":
            return 1.0 / eta
        lib = ca if isinstance(eta, ca.SX) else np
        if self.kind == "log":
            return -lib.log(eta / (1.0 + eta))
        return lib.exp(-self.kappa * eta)


@dataclass(frozen=True)
class BarrierSpec:
    """What an embedded model carries about its barrier states."""

    options: BarrierOptions
    groups: tuple[tuple[int, ...], ...]

    @property
    def n_beta(self) -> int:
        return len(self.groups)


def min_margin(h: ca.SX, indices) -> ca.SX:
    """min_i h_i as a chain of fmin (one vector min per margin in generated kernels)."""
    out: ca.SX | None = None
    for i in indices:
        out = h[i] if out is None else ca.fmin(out, h[i])
    if out is None:
        raise fail("indices", indices, "must name at least one margin")
    return out


def _barrier_sum(h: ca.SX, g, opts: BarrierOptions) -> ca.SX:
    """sum_i B(h_i). For the inverse barrier, pairs are summed as (h_a + h_b) / (h_a h_b): one
    division per pair instead of two (divisions bound the sampler kernels)."""
    if opts.kind != "inverse":
        return sum((opts.barrier(h[i]) for i in g), ca.SX(0))
    terms = [(h[a] + h[b]) / (h[a] * h[b]) for a, b in zip(g[0::2], g[1::2], strict=False)]
    if len(g) % 2:
        terms.append(1.0 / h[g[-1]])
    return sum(terms, ca.SX(0))


def _barrier_values(h: ca.SX, opts: BarrierOptions, groups) -> ca.SX:
    """Barrier-state values of margins h, with the crash rule and the cap."""
    out = []
    for g in groups:
        raw = _barrier_sum(h, g, opts)
        crashed = min_margin(h, g) <= opts.eps_h
        out.append(ca.if_else(crashed, opts.beta_max, ca.fmin(raw, opts.beta_max)))
    return ca.vertcat(*out)


def embed_barrier(model: Model, options: BarrierOptions | None = None) -> Model:
    """The safety-embedded model x_bar = [x; beta] (assumptions §4.4), exact CasADi expressions.

    beta is recomputed from the margins in the model's scene symbol, so the embedded dynamics
    take the current scene as an input like the margins do. With moving circles in the scene
    (a layout with moving slots) that scene is the one of the next state's time (the samplers
    predict it per step); with gamma != 0 the present state's term then sees the moving
    circles one step earlier (c - v dt), i.e. where they are at the present state's time."""
    opts = options or BarrierOptions()
    if model.n_physical != model.nx:
        raise fail("model", model.name, "is already barrier-embedded")
    groups = opts.groups(model.nh)
    beta = ca.SX.sym("beta", len(groups))
    h_fn = ca.Function("h", [model.x, model.scene], [model.h])
    now = _barrier_values(model.h, opts, groups)
    nxt = _barrier_values(h_fn(model.x_next, model.scene), opts, groups)
    # the dynamics' scene is that of x_{k+1}'s time: with moving circles x_k's margins see
    # them one step earlier, at c - v dt (the lift keeps the present scene)
    before = now
    if opts.gamma != 0.0 and predicts(model):
        before = _barrier_values(h_fn(model.x, scene_sx_at(model, model.scene, -model.dt)),
                                 opts, groups)
    beta_next = nxt - opts.gamma * (beta - before) if opts.gamma != 0.0 else nxt
    x_bar = ca.vertcat(model.x, beta)
    names = tuple(f"beta{j}" for j in range(len(groups))) if len(groups) > 1 else ("beta",)
    return Model(
        name=f"{model.name}+bas",
        x=x_bar,
        u=model.u,
        x_next=ca.vertcat(model.x_next, beta_next),
        h=model.h,
        dt=model.dt,
        u_min=model.u_min,
        u_max=model.u_max,
        state_names=model.state_names + names,
        control_names=model.control_names,
        position=model.position,
        obstacles=model.obstacles,
        n_physical=model.nx,
        barrier=BarrierSpec(options=opts, groups=groups),
        lift_expr=ca.vertcat(model.x, now),
        scene=model.scene,
        scene_value=model.scene_value,
        scene_capacity=model.scene_capacity,
        scene_layout=model.scene_layout,
        state_units=None if model.state_units is None else model.state_units + ("",) * len(names),
    )

"""Costs as CasADi expressions with per-step parameters (assumptions §4.5, 6, 10.2).

A :class:`Cost` holds the stage cost l(x, u, p_k) for k < T and the terminal cost l_T(x, p_T).
Values that change between solves (references, targets, AL multipliers) live in the parameter
vector p, so a new reference is a new array, never a rebuild. Parameter arrays have shape
(T+1, n_p): row k feeds stage k, row T feeds the terminal cost.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import casadi as ca
import numpy as np

from workbench.problem.models import Model
from workbench.validation import MAX_STEPS, as_array, fail, integer, one_of, real

BetaCost = Literal["relative", "absolute"]


@dataclass(frozen=True, eq=False)
class Cost:
    """Stage and terminal cost expressions over (x, u, p) of a given model."""

    stage: ca.SX
    terminal: ca.SX
    p: ca.SX
    param_layout: tuple[tuple[str, int], ...] = field(default=())
    description: str = ""
    # Optional replacements of the exact state Hessians (e.g. Gauss-Newton for AL penalties,
    # assumptions §6.2); expressions in (x, u, p) and (x, p), shape (nx, nx). None = exact Hessian.
    stage_hessian_x: ca.SX | None = None
    terminal_hessian_x: ca.SX | None = None

    @property
    def n_p(self) -> int:
        return int(self.p.numel())

    def params(self, T: int, **values) -> np.ndarray:
        """Stack named parameter blocks into a (T+1, n_p) array.

        Each value is either one row (broadcast over time) or an array with T+1 rows;
        T is an integer in [0, :data:`~workbench.validation.MAX_STEPS`].
        """
        T = integer("T", T, 0, MAX_STEPS)
        P = np.zeros((T + 1, self.n_p))
        col = 0
        names = {n for n, _ in self.param_layout}
        unknown = set(values) - names
        if unknown:
            raise fail("params", sorted(unknown), f"known parameter blocks are {sorted(names)}")
        for name, size in self.param_layout:
            if name in values:
                v = np.asarray(values[name], dtype=float)
                v = np.broadcast_to(v, (T + 1, size)) if v.ndim <= 1 else v
                P[:, col : col + size] = as_array(name, v, (T + 1, size))
            col += size
        return P


def _weight(name: str, W, n: int) -> np.ndarray:
    W = np.asarray(W, dtype=float)
    if W.ndim == 1:
        W = np.diag(W)
    W = as_array(name, W, (n, n))
    if not np.allclose(W, W.T) or np.min(np.linalg.eigvalsh(W)) < -1e-12:
        raise fail(name, W, "must be symmetric positive semidefinite")
    return W


def quadratic_tracking(
    model: Model,
    *,
    Q,
    R,
    S,
    q_beta: float = 0.0,
    s_beta: float = 0.0,
    beta_cost: BetaCost = "relative",
) -> Cost:
    """½|x-x_ref|²_Q + ½|u-u_ref|²_R [+ ½ q_beta |beta-beta_ref|²]; terminal ½|x-x_ref|²_S.

    Q, S act on the physical state; on an embedded model q_beta and s_beta weigh the barrier
    states about beta_ref (assumptions §13 B3: relative by default, "absolute" fixes beta_ref = 0).
    Parameter blocks: x_ref (n_physical), u_ref (nu) and, for embedded models, beta_ref (n_beta).
    """
    one_of("beta_cost", beta_cost, ("relative", "absolute"))
    n, nu = model.n_physical, model.nu
    Qm, Rm, Sm = _weight("Q", Q, n), _weight("R", R, nu), _weight("S", S, n)
    for nm, val in (("q_beta", q_beta), ("s_beta", s_beta)):
        real(nm, val, 0.0)
    n_beta = model.nx - n
    layout = [("x_ref", n), ("u_ref", nu)] + ([("beta_ref", n_beta)] if n_beta else [])
    p = ca.SX.sym("p", sum(s for _, s in layout))
    xr, ur = p[:n], p[n : n + nu]
    ex, eu = model.x[:n] - xr, model.u - ur
    stage = 0.5 * ca.mtimes([ex.T, Qm, ex]) + 0.5 * ca.mtimes([eu.T, Rm, eu])
    terminal = 0.5 * ca.mtimes([ex.T, Sm, ex])
    if n_beta:
        br = p[n + nu :] if beta_cost == "relative" else ca.SX.zeros(n_beta)
        eb = model.x[n:] - br
        stage += 0.5 * q_beta * ca.sumsqr(eb)
        terminal += 0.5 * s_beta * ca.sumsqr(eb)
    return Cost(stage=stage, terminal=terminal, p=p, param_layout=tuple(layout),
                description="quadratic tracking")

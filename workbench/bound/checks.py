"""The inequalities of assumptions §11.3 for one step (T1, T2) and consecutive steps t, t+1
(T3-T3d).

Each check reports ``holds`` (LHS <= RHS), ``slack`` = RHS − LHS, both sides, and the
Lipschitz-dependent term of the RHS (δ or δ D_F), for local or global constants, or for the
sampled-tube bound of assumptions §11.4 (``"sampled"``: δ_λ in place of δ; in T1 and T1s the
bound max_n δ_n on the largest per-sample gap). Free energies
are the pure-state-cost estimates of assumptions §11.2 item 3 (``estimate="code"``: from S_real and
S_nom as Algorithm 1 computes them). Readings (assumptions §13, L2-L3):

* T1  max_n (Sx_n − Sx*_n) <= δ_t                       (per sample, all n)
* T1s T1 over the samples whose real and nominal rollouts both stayed safe (a diagnostic, not
      in assumptions §11.3: a crashed real sample carries β_max, so T1 can only fail through it)
* T2  F̂_real(t) <= F̂_nom(t) + δ_t
* T2E F̂_real(t) <= F̂'_nom(t) + δ_t + 2 max(Ê, Ê') with F̂' from an independent batch of the
      same step (the "true-F version" of assumptions §11.3; only when the step has one)
* T3  F̂_real(t+1) − F̂_real(t) <= α_t − F̂_nom(t) + 2Ê + R_t (L_φ + n_q L_q) D̂_F(t)   (as printed)
* T3b as T3 with δ_t in place of δ_t D̂_F(t) (the proof's δ)
* T3c as T3 with F̂_nom(t+1) in place of F̂_nom(t)
* T3d F̂_real(t+1) <= α_{t+1} + δ_{t+1} + 2Ê
      (the absolute form; its premise is F̂_nom(t+1) <= α_{t+1})

α_t is the threshold at step t's chosen nominal state (the SAIS clamp's α); Ê = max(Ê_t, Ê_{t+1})
in the transition checks (the lemma's single uncertainty bound covers both estimates).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from workbench.bound.step import CONSTANTS, BoundStep, Constants
from workbench.validation import fail, one_of

STEP_TESTS = ("T1", "T1s", "T2", "T2E")
TRANSITION_TESTS = ("T3", "T3b", "T3c", "T3d")
Estimate = Literal["pure", "code"]


@dataclass(frozen=True)
class Check:
    test: str
    constants: str  # "local" or "global"
    holds: bool
    slack: float  # RHS − LHS
    lhs: float
    rhs: float
    lipschitz_term: float  # the part of the RHS that depends on the Lipschitz constants


def _check(test, constants, lhs, rhs, term) -> Check:
    return Check(test=test, constants=constants, holds=bool(lhs <= rhs), slack=float(rhs - lhs),
                 lhs=float(lhs), rhs=float(rhs), lipschitz_term=float(term))


def _F(s: BoundStep, estimate: Estimate) -> tuple[float, float]:
    one_of("estimate", estimate, ("pure", "code"))
    if estimate == "pure":
        return s.F_real.value, s.F_nom.value
    return s.F_real_code, s.F_nom_code


def step_checks(s: BoundStep, constants: tuple[Constants, ...] = CONSTANTS,
                estimate: Estimate = "pure") -> list[Check]:
    """T1, T1s, T2 (and T2E with an independent batch) at one step, per set of constants."""
    if not isinstance(s, BoundStep):
        raise fail("step", type(s).__name__, "need a BoundStep")
    Fr, Fn = _F(s, estimate)
    out = []
    for c in constants:
        d = s.delta(c)
        d1, d1s = s.delta_per_sample(c), s.delta_per_sample(c, safe=True)
        out.append(_check("T1", c, -s.t1_gap, d1, d1))
        out.append(_check("T1s", c, -s.t1_gap_safe, d1s, d1s))
        out.append(_check("T2", c, Fr, Fn + d, d))
        if np.isfinite(s.F_nom_ind) and estimate == "pure":
            out.append(_check("T2E", c, Fr, s.F_nom_ind + d + 2 * max(s.E, s.E_ind), d))
    return out


def transition_checks(s0: BoundStep, s1: BoundStep,
                      constants: tuple[Constants, ...] = CONSTANTS,
                      estimate: Estimate = "pure") -> list[Check]:
    """T3, T3b, T3c, T3d for consecutive steps t (``s0``) and t+1 (``s1``)."""
    for name, s in (("s0", s0), ("s1", s1)):
        if not isinstance(s, BoundStep):
            raise fail(name, type(s).__name__, "need a BoundStep")
    Fr0, Fn0 = _F(s0, estimate)
    Fr1, Fn1 = _F(s1, estimate)
    E2 = 2.0 * max(s0.E, s1.E)
    dF = Fr1 - Fr0
    out = []
    for c in constants:
        d0, d1 = s0.delta(c), s1.delta(c)
        t3 = d0 * s0.D_F
        out.append(_check("T3", c, dF, s0.alpha - Fn0 + E2 + t3, t3))
        out.append(_check("T3b", c, dF, s0.alpha - Fn0 + E2 + d0, d0))
        out.append(_check("T3c", c, dF, s0.alpha - Fn1 + E2 + t3, t3))
        out.append(_check("T3d", c, Fr1, s1.alpha + d1 + E2, d1))
    return out


def episode_checks(steps: list[BoundStep], constants: tuple[Constants, ...] = CONSTANTS,
                   estimate: Estimate = "pure") -> list[list[Check]]:
    """Per step t: T1, T1s, T2 at t and, when t+1 exists, T3-T3d for (t, t+1)."""
    out = []
    for t, s in enumerate(steps):
        c = step_checks(s, constants, estimate)
        if t + 1 < len(steps):
            c += transition_checks(s, steps[t + 1], constants, estimate)
        out.append(c)
    return out

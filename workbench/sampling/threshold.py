"""The free-energy threshold alpha of RMPPI's nominal-state selection (assumptions §9.3, §10.3).

A candidate nominal state c is admissible when its free energy F(c) is below alpha(c). The rule
must bind: the free energy falls by three orders of magnitude from the start to the goal on the
paper's map (≈ 15000 → ≈ 21 for undisturbed BaS-MPPI), so any constant calibrated at the start
(assumptions §10.3's first rule, ``kind="start"``) is never reached later and SA-RMPPI degenerates
to
BaS-MPPI. Rules (:class:`AlphaRule`):

* ``"progress"`` (default) — alpha(x) = (1 + kappa) F_und(d(x)): F_und(d) is the free energy an
  undisturbed run has at the same distance d to the goal, measured with the selection's own
  estimator (M_c samples, real-state candidate), smoothed and made non-decreasing in d;
* ``"quantile"`` — a constant: the q-quantile of F_und over the undisturbed run;
* ``"fixed"`` — a constant given by the user (MPPI-G style);
* ``"start"`` — factor x F_und at the start (kept to show why it fails).

The calibration run is SA-RMPPI itself with alpha = inf (always the real state), undisturbed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Protocol

import casadi as ca
import numpy as np

from workbench.validation import MAX_STEPS, fail, integer, one_of, real, real_or_inf

AlphaKind = Literal["progress", "quantile", "fixed", "start"]


@dataclass(frozen=True)
class AlphaRule:
    """How alpha is chosen (defaults [A]: kappa = 0.1 chosen from an activation sweep on the
    navigation map; the navigation study's alpha sweep repeats it). ``calibration_steps`` in
    [10, :data:`~workbench.validation.MAX_STEPS`]."""

    kind: AlphaKind = "progress"
    kappa: float = 0.1  # progress: alpha = (1 + kappa) F_und(d); 0.1 from the activation study
    quantile: float = 0.5  # quantile: alpha = quantile of F_und
    value: float = np.inf  # fixed
    factor: float = 1.5  # start: alpha = factor x F_und(start)
    calibration_steps: int = 600  # undisturbed steps (the paper map's run reaches the goal ~300)

    def __post_init__(self) -> None:
        one_of("AlphaRule.kind", self.kind, ("progress", "quantile", "fixed", "start"))
        for name in ("kappa", "factor"):
            real(f"AlphaRule.{name}", getattr(self, name), 0.0)
        real("AlphaRule.quantile", self.quantile, 0.0, maximum=1.0)
        real_or_inf("AlphaRule.value", self.value)
        integer("AlphaRule.calibration_steps", self.calibration_steps, 10, MAX_STEPS)

    @property
    def needs_calibration(self) -> bool:
        return self.kind != "fixed"

    def label(self) -> str:
        return {"progress": f"progress(kappa={self.kappa:g})",
                "quantile": f"quantile(q={self.quantile:g})",
                "fixed": f"fixed({self.value:g})",
                "start": f"start(x{self.factor:g})"}[self.kind]


class Threshold(Protocol):
    """alpha at each of n physical states (n, n_physical) -> (n,)."""

    def __call__(self, X: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class ConstantThreshold:
    """alpha(x) = value everywhere. ``ConstantThreshold(np.inf)`` (or :meth:`selection_off`)
    switches the nominal-state selection off: the real-state candidate is always taken and the
    robust part of RMPPI never acts. :class:`~workbench.sampling.robust.RobustMPPI` uses
    that only when it is handed over explicitly (calibration runs do so on purpose)."""

    value: float

    @classmethod
    def selection_off(cls) -> ConstantThreshold:
        """alpha = +inf: the explicit opt-out of RMPPI's selection (never binds)."""
        return cls(value=np.inf)

    def __call__(self, X: np.ndarray) -> np.ndarray:
        return np.full(np.atleast_2d(X).shape[0], float(self.value))


@dataclass(frozen=True, eq=False)
class ProgressThreshold:
    """alpha(x) = (1 + kappa) F(d(x)), F interpolated in log distance, clamped at the ends.

    d(x) is the distance from the goal in the ``position`` coordinates, or ``measure(x)`` when
    a progress measure (a CasADi Function of the physical state, >= 0, 0 at the goal) is
    given."""

    log_d: np.ndarray  # increasing knots
    F: np.ndarray  # non-decreasing values
    kappa: float
    goal: np.ndarray  # goal position
    position: tuple[int, ...]
    measure: ca.Function | None = None

    def __call__(self, X: np.ndarray) -> np.ndarray:
        d = progress_distance(X, self.goal, self.position, self.measure)
        ld = np.log(np.maximum(d, 1e-12))
        return (1.0 + self.kappa) * np.interp(ld, self.log_d, self.F)


def progress_distance(X: np.ndarray, goal: np.ndarray, position: tuple[int, ...],
                      measure: ca.Function | None = None) -> np.ndarray:
    """The progress measure d at states X (n, >= n_physical): ``measure(x)`` when given, else
    the distance from ``goal`` in the ``position`` coordinates."""
    X = np.atleast_2d(np.asarray(X, float))
    if measure is not None:
        n = measure.size1_in(0)
        return np.asarray(measure.map(X.shape[0])(X[:, :n].T)).ravel()
    D = X[:, list(position)] - goal
    return np.sqrt(np.add.reduce(D * D, axis=1))  # np.linalg.norm(D, axis=1), same sums


def progress_curve(d: np.ndarray, F: np.ndarray, bins: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """Median free energy per log-distance bin (``bins`` in [1, 10^4]), made non-decreasing
    in distance."""
    bins = integer("bins", bins, 1, 10**4)
    d, F = np.asarray(d, float), np.asarray(F, float)
    ok = np.isfinite(F) & np.isfinite(d) & (d > 0)
    if ok.sum() < 2:
        raise fail("F", F, "need at least two finite calibration points")
    ld, F = np.log(d[ok]), F[ok]
    edges = np.linspace(ld.min(), ld.max() + 1e-12, bins + 1)
    idx = np.clip(np.digitize(ld, edges) - 1, 0, bins - 1)
    knots, vals = [], []
    for b in range(bins):
        m = idx == b
        if m.any():
            knots.append(float(np.median(ld[m])))
            vals.append(float(np.median(F[m])))
    return np.array(knots), np.maximum.accumulate(np.array(vals))


def make_threshold(rule: AlphaRule, X: np.ndarray | None = None, F: np.ndarray | None = None,
                   goal=None, position: tuple[int, ...] | None = (0, 1),
                   progress: ca.Function | None = None) -> Threshold:
    """The threshold of a rule from an undisturbed trace: states X (n, n_physical) and the
    real-state candidate free energies F (n,) (None for ``kind="fixed"``). The progress rule
    measures distance from the goal in the ``position`` coordinates, or by ``progress`` (a
    Function of the physical state) when given."""
    if rule.kind == "fixed":
        return ConstantThreshold(value=rule.value)
    if X is None or F is None or goal is None:
        raise fail("calibration", None, f"alpha rule {rule.kind!r} needs an undisturbed trace "
                   "(states, free energies) and the goal")
    F = np.asarray(F, float)
    finite = F[np.isfinite(F)]
    if finite.size < 2:
        raise fail("F", F, "need at least two finite calibration free energies")
    if rule.kind == "start":
        return ConstantThreshold(value=rule.factor * float(finite[0]))
    if rule.kind == "quantile":
        return ConstantThreshold(value=float(np.quantile(finite, rule.quantile)))
    if progress is None and position is None:
        raise fail("progress", None, "the progress rule needs the plant's position coordinates "
                   "(Model.position) or a progress measure: give progress= a CasADi expression "
                   "in the plant's state (>= 0, 0 at the goal)")
    position = tuple(position or ())
    goal = np.asarray(goal, float).ravel()
    if goal.size != len(position):  # a full state: its position coordinates
        goal = goal[list(position)]
    log_d, vals = progress_curve(progress_distance(X, goal, position, progress), F)
    return ProgressThreshold(log_d=log_d, F=vals, kappa=rule.kappa, goal=goal,
                             position=position, measure=progress)

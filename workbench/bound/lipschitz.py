"""Lipschitz constants of the state costs q and φ (assumptions §11.2 item 6, 11.3 baseline).

Space. The costs are functions of the barrier-embedded state x̄ = [x; β], but on every sample
β_k = B(h(p_k)) exactly (γ = 0; the real start is lifted, the nominal start is a candidate whose
β is recomputed from its position). So along trajectories q(x̄_k) = q̃(x_k) := q(lift(x_k)), a
function of the physical state x = (p, v), and Lemma 1's step |q(x̄) − q(x̄*)| ≤ L_q ‖x − x*‖
holds with L_q = sup ‖∇q̃‖ in the physical norm — the norm of the tube radius R
(:mod:`workbench.bound.tube`). ∇q̃ carries the β-cost term 2 q_β (β − β_g) Σ B'(h_i) ∇h_i of
assumptions §11.2, which is what makes L_q large near obstacles and small away from them.

* Local (per step): max ‖∇q̃‖ at x*ⁿ_k + s (xⁿ_k − x*ⁿ_k), s ∈ {0, ¼, ½, ¾, 1}, over all n and
  k = 1..T (the steps whose q is summed), and ‖∇φ̃‖ likewise at k = T; points with min h ≤ 0
  are excluded and counted. Secant check: max |q̃(x) − q̃(x*)| / ‖x − x*‖ over segments whose five
  points are all safe; it can exceed the 5-point gradient estimate only where ‖∇q̃‖ peaks
  between the points (never for a quadratic cost: ‖∇q̃‖ is then convex along the segment).
* Global: the same maxima over a dense, documented grid (:class:`LipschitzGrid`).

``space="augmented"`` is assumptions §11.2 item 5's other reading: β is a coordinate, points are
x̄* + s (x̄ − x̄*) in the full state, norms (and so the tube radius) include β; ∇q has no barrier
term, but R then carries the β differences, which are large near obstacles.

Gradients are CasADi's exact derivatives of the sampling problem's q and φ composed with the
model's lift, evaluated by the generated kernel ``wb_cost_gradients``
(:mod:`workbench.sampling.kernels.diagnostics`), or by the CasADi virtual machine without a
compiler.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from workbench.bound.tube import check_trajectories
from workbench.sampling.kernels.diagnostics import (
    GRADIENT_RESULTS,
    SEGMENT_POINTS,
    SPACES,
    composed_costs,
    diagnostics_library,
)
from workbench.sampling.problem import SamplingProblem
from workbench.validation import as_array, fail, integer, one_of, real


@dataclass(frozen=True)
class Lipschitz:
    """Lipschitz estimates of q̃ and φ̃ and how they were obtained."""

    L_q: float
    L_phi: float
    secant_q: float  # max |q̃(x) − q̃(x*)| / ‖x − x*‖ (0 when no segment qualifies)
    secant_phi: float
    points_q: int  # points evaluated for L_q (including excluded ones)
    points_phi: int
    excluded_q: int  # points with min h <= 0 (not used)
    excluded_phi: int

    @property
    def secant_ok(self) -> bool:
        """The secant check of assumptions §11.2: secants never exceed the gradient estimates."""
        return self.secant_q <= self.L_q and self.secant_phi <= self.L_phi


@dataclass(frozen=True)
class LipschitzGrid:
    """Points for the global constant (defaults [A], the assumptions §3.2 map in [0, 10]²).

    Positions: a regular grid over ``x_range`` × ``y_range`` with ``spacing``, plus, for every
    obstacle, ``n_rings`` rings of ``ring_angles`` points at margins h (the model's
    h = ‖p − c‖² − r²) spaced geometrically from ``min_margin`` to ``max_margin`` — the
    near-obstacle points where the barrier term peaks. ``min_margin = None`` uses twice the
    barrier's crash margin eps_h: states with h <= eps_h are crashed (β = β_max), so the rings
    reach as close to the obstacles as a non-crashed state can be, up to a factor 2 in h. Points
    inside any obstacle (min h <= 0) are excluded by the evaluation, as in the local estimate.
    Velocities: an ``n_v`` × ``n_v`` grid over [−v_max, v_max]² (corners included, where the
    quadratic velocity cost peaks). Every position is combined with every velocity.

    With the inverse barrier, ‖∇q̃‖ grows like h⁻³ (β ∇β) near an obstacle, so the global
    constant is set by the innermost ring: it is a property of the barrier's cap, not of the map.
    """

    x_range: tuple[float, float] = (0.0, 10.0)
    y_range: tuple[float, float] = (0.0, 10.0)
    spacing: float = 0.1
    min_margin: float | None = None
    max_margin: float = 1.0
    n_rings: int = 25
    ring_angles: int = 360
    v_max: float = 5.0
    n_v: int = 3

    def __post_init__(self) -> None:
        for name in ("spacing", "v_max", "max_margin"):
            real(f"LipschitzGrid.{name}", getattr(self, name), 0.0, strict=True)
        if self.min_margin is not None and not (
                0 < real("LipschitzGrid.min_margin", self.min_margin) < self.max_margin):
            raise fail("LipschitzGrid.min_margin", self.min_margin,
                       f"must be None or a number in (0, max_margin = {self.max_margin:g})")
        for name in ("x_range", "y_range"):
            lo, hi = (real(f"LipschitzGrid.{name}", v) for v in getattr(self, name))
            if not lo < hi:
                raise fail(f"LipschitzGrid.{name}", (lo, hi), "need finite lo < hi")
        for name in ("ring_angles", "n_v", "n_rings"):
            integer(f"LipschitzGrid.{name}", getattr(self, name), 1)

    def margins(self, eps_h: float) -> np.ndarray:
        lo = self.min_margin if self.min_margin is not None else 2.0 * max(eps_h, 1e-12)
        return np.geomspace(lo, self.max_margin, self.n_rings)

    def positions(self, obstacles, eps_h: float = 1e-6) -> np.ndarray:
        xs = np.arange(self.x_range[0], self.x_range[1] + 0.5 * self.spacing, self.spacing)
        ys = np.arange(self.y_range[0], self.y_range[1] + 0.5 * self.spacing, self.spacing)
        P = [np.stack(np.meshgrid(xs, ys, indexing="ij"), -1).reshape(-1, 2)]
        th = np.linspace(0.0, 2 * np.pi, self.ring_angles, endpoint=False)
        ring = np.stack([np.cos(th), np.sin(th)], -1)
        for o in obstacles:
            for h in self.margins(eps_h):
                P.append(np.asarray(o.center) + np.sqrt(o.radius**2 + h) * ring)
        return np.vstack(P)

    def velocities(self) -> np.ndarray:
        v = np.linspace(-self.v_max, self.v_max, self.n_v) if self.n_v > 1 else np.zeros(1)
        return np.stack(np.meshgrid(v, v, indexing="ij"), -1).reshape(-1, 2)

    def points(self, obstacles, n_physical: int = 4, eps_h: float = 1e-6) -> np.ndarray:
        """(M, n_physical) grid states (p, v) of a planar double integrator."""
        if n_physical != 4:
            raise fail("n_physical", n_physical, "the grid is for planar double integrators "
                       "(p, v); evaluate your own points with CostGradients.at_points")
        P, V = self.positions(obstacles, eps_h), self.velocities()
        return np.hstack([np.repeat(P, len(V), axis=0), np.tile(V, (len(P), 1))])

    def describe(self, eps_h: float = 1e-6) -> str:
        m = self.margins(eps_h)
        return (f"positions: {self.spacing:g} m grid over {self.x_range} x {self.y_range} + "
                f"{self.n_rings} rings x {self.ring_angles} angles per obstacle at margins h = "
                f"{m[0]:.3g}..{m[-1]:.3g} (geometric); velocities: {self.n_v}x{self.n_v} grid "
                f"over [-{self.v_max:g}, {self.v_max:g}]^2; points with min h <= 0 excluded")


@dataclass(frozen=True)
class Segments:
    """Per point (k, n) of one batch, arrays (T+1, N): the maxima of ‖∇q̃‖ and ‖∇φ̃‖ at the
    five points of the segment from x*ⁿ_k to xⁿ_k (excluded points not counted), the secant
    slopes |q̃(x) − q̃(x*)| / ‖x − x*‖ (0 where a point is excluded or x = x*), the number of
    excluded points, and the segment's length ‖xⁿ_k − x*ⁿ_k‖."""

    grad_q: np.ndarray
    grad_phi: np.ndarray
    secant_q: np.ndarray
    secant_phi: np.ndarray
    excluded: np.ndarray
    distance: np.ndarray

    def lipschitz(self) -> Lipschitz:
        """The local constants: maxima over k = 1..T (q) and k = T (φ), as
        :meth:`CostGradients.local`."""
        T1, N = self.grad_q.shape
        ns = len(SEGMENT_POINTS)
        return Lipschitz(L_q=float(self.grad_q[1:].max()), L_phi=float(self.grad_phi[-1].max()),
                         secant_q=float(self.secant_q[1:].max()),
                         secant_phi=float(self.secant_phi[-1].max()),
                         points_q=ns * (T1 - 1) * N, points_phi=ns * N,
                         excluded_q=int(self.excluded[1:].sum()),
                         excluded_phi=int(self.excluded[-1].sum()))

    def products(self) -> np.ndarray:
        """Per sample n: δₙ = Σ_{k=1..T} G^q_{nk} ‖e_{nk}‖ + G^φ_{nT} ‖e_{nT}‖, the segment
        gradient maxima times the segment lengths (the sampled-tube bound, assumptions
        §11.4)."""
        return (np.sum(self.grad_q[1:] * self.distance[1:], axis=0)
                + self.grad_phi[-1] * self.distance[-1])


class CostGradients:
    """Gradient norms of q̃, φ̃ of one sampling problem (module docstring); build once."""

    def __init__(self, sp: SamplingProblem, backend: str = "auto", space: str = "physical"):
        one_of("backend", backend, ("auto", "compiled", "numpy"))
        one_of("space", space, SPACES)
        self.sp, self.space = sp, space
        self.n = sp.model.n_physical if space == "physical" else sp.nx  # point dimension
        self.lib = None if backend == "numpy" else diagnostics_library(sp)
        if backend == "compiled" and self.lib is None:
            raise fail("backend", backend, "no C compiler is available; use 'numpy' or 'auto'")
        y, p, qt, pt, mh = composed_costs(sp, space)
        gq, gp = ca.gradient(qt, y), ca.gradient(pt, y)
        self._point = ca.Function("cost_point", [y, p],
                                  [qt, pt, ca.dot(gq, gq), ca.dot(gp, gp), mh])

    def _p(self, p) -> np.ndarray:
        return as_array("p", p, (self.sp.n_p,))

    def at_points(self, Y, p) -> dict[str, np.ndarray]:
        """q, φ, ‖∇q‖, ‖∇φ‖ and min h at points Y (M, n) of the space (physical: n_physical,
        augmented: nx), CasADi VM."""
        r = self._at_points(Y, p)
        r["grad_q"], r["grad_phi"] = np.sqrt(r.pop("g2_q")), np.sqrt(r.pop("g2_phi"))
        return r

    def _at_points(self, Y, p) -> dict[str, np.ndarray]:
        Y = as_array("Y", Y, (None, self.n))
        out = self._point.map(Y.shape[0])(Y.T, self._p(p))
        return {k: np.asarray(v).ravel()
                for k, v in zip(("q", "phi", "g2_q", "g2_phi", "min_h"), out, strict=True)}

    def local(self, X, X_nom, p) -> Lipschitz:
        """Local constants on the tube of one batch: trajectories (T+1, nx, N), k = 0..T."""
        X, X_nom = check_trajectories(X, X_nom)
        if X.shape[1] != self.sp.nx:
            raise fail("X", X.shape, f"expected (T+1, {self.sp.nx}, N)")
        T1 = X.shape[0]
        wq = np.ones((T1, 1))
        wq[0] = 0.0  # q is summed over k = 1..T
        wphi = np.zeros((T1, 1))
        wphi[-1] = 1.0
        return self._run(X, X_nom, wq, wphi, self._p(p))

    def segments(self, X, X_nom, p) -> Segments:
        """Per-point results on the tube of one batch (k = 0..T, every sample): the maxima of
        ‖∇q̃‖, ‖∇φ̃‖ over each real–nominal segment, its secants and exclusions. One
        evaluation gives both the local constants (:meth:`Segments.lipschitz`, equal to
        :meth:`local`) and the per-sample Lipschitz products of the sampled-tube bound."""
        X, X_nom = check_trajectories(X, X_nom)
        if X.shape[1] != self.sp.nx:
            raise fail("X", X.shape, f"expected (T+1, {self.sp.nx}, N)")
        T1, nx, N = X.shape
        flat = [np.ascontiguousarray(np.transpose(a, (1, 0, 2)).reshape(1, nx, T1 * N))
                for a in (X, X_nom)]  # one lane per (k, n), lane index k N + n
        r = self._raw(flat[0], flat[1], np.ones((1, 1)), np.ones((1, 1)), self._p(p))
        d = np.sqrt(np.sum((X[:, : self.n] - X_nom[:, : self.n]) ** 2, axis=1))
        return Segments(grad_q=np.sqrt(r["L2_q"]).reshape(T1, N),
                        grad_phi=np.sqrt(r["L2_phi"]).reshape(T1, N),
                        secant_q=np.sqrt(r["sec2_q"]).reshape(T1, N),
                        secant_phi=np.sqrt(r["sec2_phi"]).reshape(T1, N),
                        excluded=np.asarray(r["excluded_q"]).reshape(T1, N), distance=d)

    def global_constant(self, grid: LipschitzGrid, p, chunk: int = 1 << 20) -> Lipschitz:
        """Global constants: the maxima over the grid's points (no secants), in chunks of
        ``chunk`` points to bound memory."""
        Y = grid.points(self.sp.model.obstacles, self.sp.model.n_physical, self.sp.eps_h)
        p = self._p(p)
        parts = []
        lift = self.sp.model.lift_function
        for i in range(0, Y.shape[0], chunk):
            Yc = Y[i : i + chunk]
            X = np.zeros((1, self.sp.nx, Yc.shape[0]))
            if self.space == "physical":
                X[0, : Yc.shape[1]] = Yc.T
            else:  # the grid's states on the model's manifold: beta = B(h(p))
                lift_n = lift.map("lift", "serial", Yc.shape[0], [1], [])
                X[0] = np.asarray(lift_n(Yc.T, self.sp.model.scene_value))
            parts.append(self._run(X, X, np.ones((1, 1)), np.ones((1, 1)), p))
        return Lipschitz(L_q=max(q.L_q for q in parts), L_phi=max(q.L_phi for q in parts),
                         secant_q=0.0, secant_phi=0.0,
                         points_q=sum(q.points_q for q in parts),
                         points_phi=sum(q.points_phi for q in parts),
                         excluded_q=sum(q.excluded_q for q in parts),
                         excluded_phi=sum(q.excluded_phi for q in parts))

    def _raw(self, X, X_nom, wq, wphi, p) -> dict[str, np.ndarray]:
        if self.lib is not None:
            k = self.lib.gradients if self.space == "physical" else self.lib.gradients_augmented
            N = X.shape[2]
            out = k(np.zeros((N, len(GRADIENT_RESULTS))), consts={"p": p},
                    time_in={"wq": wq, "wphi": wphi}, lane_in={"x": X, "x_nom": X_nom})
            return k.result.unpack(out.result)
        return self._reference(X, X_nom, wq, wphi, p)

    def _run(self, X, X_nom, wq, wphi, p) -> Lipschitz:
        if self.lib is not None:
            k = self.lib.gradients if self.space == "physical" else self.lib.gradients_augmented
            N = X.shape[2]
            out = k(np.zeros((N, len(GRADIENT_RESULTS))), consts={"p": p},
                    time_in={"wq": wq, "wphi": wphi}, lane_in={"x": X, "x_nom": X_nom})
            r = k.result.unpack(out.result)
        else:
            r = self._reference(X, X_nom, wq, wphi, p)
        return Lipschitz(L_q=float(np.sqrt(r["L2_q"].max())),
                         L_phi=float(np.sqrt(r["L2_phi"].max())),
                         secant_q=float(np.sqrt(r["sec2_q"].max())),
                         secant_phi=float(np.sqrt(r["sec2_phi"].max())),
                         points_q=int(r["points_q"].sum()), points_phi=int(r["points_phi"].sum()),
                         excluded_q=int(r["excluded_q"].sum()),
                         excluded_phi=int(r["excluded_phi"].sum()))

    def _reference(self, X, X_nom, wq, wphi, p) -> dict[str, np.ndarray]:
        """The kernel's computation with the CasADi VM, per sample (the kernel's twin)."""
        n = self.n
        T1, _, N = X.shape
        A, B = X_nom[:, :n], X[:, :n]  # (T1, n, N)
        ev = []
        for s in SEGMENT_POINTS:
            Y = np.transpose(A + s * (B - A), (0, 2, 1)).reshape(-1, n)
            ev.append({k: v.reshape(T1, N) for k, v in self._at_points(Y, p).items()})
        wq, wphi = wq[:, :1], wphi[:, :1]
        ok = np.stack([e["min_h"] > 0 for e in ev])  # (5, T1, N)
        gq = np.stack([e["g2_q"] for e in ev])
        gp = np.stack([e["g2_phi"] for e in ev])
        d2 = np.sum((B - A) ** 2, axis=1)  # (T1, N)
        use = ok.all(axis=0) & (d2 > 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            sq = np.where(use, (ev[-1]["q"] - ev[0]["q"]) ** 2 / d2, 0.0)
            sp_ = np.where(use, (ev[-1]["phi"] - ev[0]["phi"]) ** 2 / d2, 0.0)
        nsp = len(SEGMENT_POINTS)
        return {
            "L2_q": np.where(ok & (wq > 0), gq, 0.0).max(axis=(0, 1)),
            "L2_phi": np.where(ok & (wphi > 0), gp, 0.0).max(axis=(0, 1)),
            "sec2_q": np.where(wq > 0, sq, 0.0).max(axis=0),
            "sec2_phi": np.where(wphi > 0, sp_, 0.0).max(axis=0),
            "excluded_q": (wq * (~ok)).sum(axis=(0, 1)),
            "excluded_phi": (wphi * (~ok)).sum(axis=(0, 1)),
            "points_q": np.full(N, nsp * wq.sum()), "points_phi": np.full(N, nsp * wphi.sum()),
        }

"""The model evaluation of the sampler twins (:mod:`workbench.sampling.twin`,
:mod:`workbench.sampling.methods.twin`): :func:`model_twin` picks a plain-NumPy twin of the
built-in navigation problem (a double integrator in the plane or in space, run-time obstacles
of any scene kind or baked circles, discrete barrier states, assumptions §8.2 costs) or, for
any other model, the CasADi virtual machine mapped over samples. Sample-major like every twin:
states X (N, nx), controls V (N, nu).

The navigation twin shares no code with the CasADi expressions: :func:`numpy_navigation_twin`
builds it from the model's obstacles (circles, or the NumPy margins of its
:class:`~workbench.problem.scene_layout.SceneLayout`, assumptions §3.4) and barrier options and
checks it against the CasADi model at random points; it returns None when the model is not one
it can reproduce.
"""

from __future__ import annotations

import numpy as np

from workbench.problem.models import Model
from workbench.problem.obstacles import scene_vector
from workbench.problem.prediction import scene_at
from workbench.sampling.problem import SamplingProblem


class NumpyNavigation:
    """Vectorised over samples: X (N, nx), V (N, nu). Position x[:d], velocity x[d:2d]
    (d = 2 or 3), barrier states after them; margins of squared circles, or those of the
    model's scene layout in form ``h_form``."""

    def __init__(self, model: Model, zoh: bool, weights: dict[str, np.ndarray],
                 h_form: str = "squared"):
        self.dt = model.dt
        self.zoh = zoh
        self.spec = model.barrier
        self.w = weights
        self.layout = model.scene_layout
        self.h_form = h_form
        self.d = 2 if self.layout is None else self.layout.dim
        if self.layout is not None or model.scene_capacity:
            self.set_scene(model.scene_value)
        else:
            self.set_scene(scene_vector(model.obstacles, len(model.obstacles)))

    def set_scene(self, scene: np.ndarray) -> None:
        """The obstacles: a flat scene vector (inert slots included, as in the kernels): of
        (x, y, r) circle slots, or of the model's scene layout."""
        v = np.array(scene, dtype=float)
        if self.layout is not None:
            if v.shape != (self.layout.size,):
                raise ValueError(f"scene: {v.shape} entries; this layout's scene vector has "
                                 f"({self.layout.size},)")
            self.scene = v
            return
        c = v.reshape(-1, 3)
        self.centers, self.radii2 = c[:, :2], c[:, 2] ** 2

    def margins(self, X) -> np.ndarray:
        if self.layout is not None:
            return self.layout.numpy_margins(X[:, :self.d], self.scene, self.h_form)
        d = X[:, None, :2] - self.centers[None]
        return d[..., 0] ** 2 + d[..., 1] ** 2 - self.radii2[None]

    def _beta(self, h) -> np.ndarray:
        spec = self.spec
        if spec is None:
            raise ValueError("barrier-state values of a model without a barrier spec")
        o = spec.options
        if o.kind == "inverse":
            B = 1.0 / h
        elif o.kind == "log":
            B = -np.log(h / (1.0 + h))
        else:
            B = np.exp(-o.kappa * h)
        out = []
        for g in spec.groups:
            raw = B[:, list(g)].sum(axis=1)
            crashed = np.any(h[:, list(g)] <= o.eps_h, axis=1)
            out.append(np.where(crashed, o.beta_max, np.minimum(raw, o.beta_max)))
        return np.stack(out, axis=1)

    def step(self, X, V):
        dt, d = self.dt, self.d
        p, v = X[:, :d], X[:, d:2 * d]
        p_next = p + dt * v + (0.5 * dt * dt * V if self.zoh else 0.0)
        x_next = np.hstack([p_next, v + dt * V])
        if self.spec is None:
            return x_next
        o = self.spec.options
        with np.errstate(divide="ignore", invalid="ignore"):
            beta = self._beta(self.margins(x_next))
            if o.gamma != 0.0:
                h_now = self.margins(X)
                if self.layout is not None and self.layout.moves:  # x_k's time: c - v dt
                    h_now = self.layout.numpy_margins(
                        X[:, :d], self.layout.predicted(self.scene, -dt), self.h_form)
                beta = beta - o.gamma * (X[:, 2 * d:] - self._beta(h_now))
        return np.hstack([x_next, beta])

    def crashed(self, X, eps_h) -> np.ndarray:
        return np.any(self.margins(X) <= eps_h, axis=1)

    def q(self, X, g) -> np.ndarray:
        d = self.d
        ep, v = X[:, :d] - g[:d], X[:, d:2 * d]
        out = ep**2 @ self.w["Qp"] + v**2 @ self.w["Qv"]
        if X.shape[1] > 2 * d:
            out = out + self.w["q_beta"] * np.sum((X[:, 2 * d:] - g[2 * d:]) ** 2, axis=1)
        return out

    def phi(self, X, g) -> np.ndarray:
        return (X - g) ** 2 @ self.w["S"]


def numpy_navigation_twin(model: Model, weights: dict[str, np.ndarray], functions
                          ) -> NumpyNavigation | None:
    """The NumPy twin if it reproduces the CasADi model at random points, else None."""
    layout = model.scene_layout
    d = 2 if layout is None else layout.dim
    if (model.n_physical != 2 * d or model.position != tuple(range(d))
            or np.shape(weights.get("Qp", ())) != (d,)):
        return None
    if layout is None and (not model.obstacles
                           or model.nh != (model.scene_capacity or len(model.obstacles))):
        return None
    if layout is not None and model.nh != layout.n_margins:
        return None
    rng = np.random.default_rng(0)
    n = 16
    lo, hi = _box(model, d)
    P = rng.uniform(lo, hi, (n, d))
    X = np.hstack([P, rng.normal(0, 2, (n, d))])
    V = rng.normal(0, 3, (n, model.nu))
    dyn = functions["dyn"].map("dyn", "serial", n, [2], [])
    h_ref = np.asarray(functions["margins"].map("margins", "serial", n, [1], [])(
        X.T if model.nx == 2 * d else np.hstack([X, np.zeros((n, model.nx - 2 * d))]).T,
        model.scene_value)).T
    forms = ("squared",) if layout is None else ("squared", "signed_distance")
    for h_form, zoh in ((f, z) for f in forms for z in (False, True)):
        twin = NumpyNavigation(model, zoh, weights, h_form)
        Xb = X if model.nx == 2 * d else np.hstack([X, twin._beta(twin.margins(X))])
        ref = np.asarray(dyn(Xb.T, V.T, model.scene_value)).T
        with np.errstate(all="ignore"):
            same = (np.allclose(twin.step(Xb, V), ref, rtol=1e-12, atol=1e-12, equal_nan=True)
                    and (layout is None or np.allclose(twin.margins(X), h_ref, rtol=1e-12,
                                                       atol=1e-12))
                    and np.allclose(twin.q(Xb, Xb[0]),
                                    np.asarray(functions["q"].map(n)(Xb.T, Xb[0])).ravel(),
                                    rtol=1e-12)
                    and np.allclose(twin.phi(Xb, Xb[0]),
                                    np.asarray(functions["phi"].map(n)(Xb.T, Xb[0])).ravel(),
                                    rtol=1e-12))
        if same:
            return twin
    return None


def _box(model: Model, d: int) -> tuple[np.ndarray, np.ndarray]:
    """A box of positions around the model's obstacles (2 m beyond them; +-5 m without any
    that have a place) for the twin's check."""
    if model.scene_layout is None:
        pts = np.array([c.center for c in model.obstacles])
    else:
        from workbench.problem.scene_layout import anchor_points

        pts = anchor_points(model.scene_layout, model.scene_value)
    if not len(pts):
        return -5.0 * np.ones(d), 5.0 * np.ones(d)
    return pts.min(axis=0) - 2, pts.max(axis=0) + 2


def model_twin(sp: SamplingProblem, N: int, scene, model_backend: str = "auto"):
    """Model evaluation for the twin in ``scene`` (empty: the model's own): plain NumPy for
    the built-in navigation problem (unless ``model_backend == "casadi"``), otherwise the CasADi
    virtual machine mapped over samples. With moving circles in the scene, rollout step k is
    evaluated in the scene predicted to (k + 1) dt: call ``at((k + 1) dt)`` before each step."""
    scene = sp.model.scene_vector(scene if np.size(scene) else None)
    if model_backend != "casadi" and sp.weights is not None:
        twin = numpy_navigation_twin(sp.model, sp.weights, sp.functions())
        if twin is not None:
            if sp.model.scene_capacity or sp.model.scene_layout is not None:
                # (else the twin holds the baked circles)
                twin.set_scene(scene)
            return NumpyModelTwin(twin, scene)
    return CasadiModelTwin(sp, N, scene)


class CasadiModelTwin:
    def __init__(self, sp: SamplingProblem, N: int, scene: np.ndarray):
        f = sp.functions()
        self.dyn = f["dyn"].map("dyn", "serial", N, [2], [])  # the scene is shared
        self.margins = (f["margins"].map("margins", "serial", N, [1], []) if sp.model.nh
                        else None)
        self.q, self.phi = f["q"].map(N), f["phi"].map(N)
        self.scene = self.present = scene
        self.model = sp.model

    def at(self, t: float) -> None:
        """Evaluate the next steps in the scene predicted to time ``t`` from now (moving circles
        at c + v t, :func:`~workbench.problem.prediction.scene_at`); nothing changes for a
        scene without moving circles."""
        self.scene = scene_at(self.model, self.present, t)

    def step(self, X, V):
        return np.asarray(self.dyn(X.T, V.T, self.scene)).T

    def crashed(self, X, eps_h):
        if self.margins is None:
            return np.zeros(X.shape[0], bool)
        return np.any(np.asarray(self.margins(X.T, self.scene)).T <= eps_h, axis=1)

    def cost(self, fn, X, p):
        return np.asarray(fn(X.T, p)).ravel()


class NumpyModelTwin:
    def __init__(self, twin, scene: np.ndarray | None = None):
        self.twin = twin
        self.q, self.phi = twin.q, twin.phi
        self.name = "numpy"
        self.present = scene
        layout = twin.layout
        self._layout = layout if layout is not None and layout.moves else None

    def at(self, t: float) -> None:
        """As :meth:`CasadiModelTwin.at`: the scene predicted to time ``t`` from now."""
        if self._layout is not None and self.present is not None:
            self.twin.set_scene(self._layout.predicted(self.present, t))

    def step(self, X, V):
        return self.twin.step(X, V)

    def crashed(self, X, eps_h):
        return self.twin.crashed(X, eps_h)

    def cost(self, fn, X, p):
        return fn(X, np.asarray(p, float))

"""The derivatives iLQG uses, for every scene kind, against finite differences.

For each kind (circles, moving circles, half-planes, capsules and the signed-distance grid in
the plane; spheres, half-spaces and capsules in space) a double integrator with that kind's
run-time obstacles is embedded with a barrier state, and its problem Functions are compared
with central differences at random safe states: ``dyn_jac`` (A, B) with differences of
``dyn``, ``dyn_hess`` (the Hessians of lam'F) with differences of ``dyn_jac``, and the margins'
gradient and Hessian (CasADi, what the barrier's derivatives are made of) with differences of
the NumPy margins (:meth:`~workbench.problem.scene_layout.SceneLayout.numpy_margins`, written
apart from the CasADi ones).

The states keep away from the kinks, where no derivative exists: every margin >= 0.2 (the
crash switch at eps_h and the cap at beta_max stay far, and the signed distance is smooth away
from a centre); a capsule's projection parameter t at least 0.05 from its clamps t = 0, 1;
the grid's cell coordinates at least 0.05 cells from a cell edge. The differences step h
stays below that distance.

Tolerances, per element relative to max(|a|, |b|, 1): first differences with h = 1e-6 err by
h^2 |f'''| ~ 1e-11 plus rounding eps |f| / h ~ 1e-9, so 1e-6; second differences of the
margins with h = 1e-4 err by h^2 |f''''| ~ 1e-7 plus eps |f| / h^2 ~ 1e-7, so 1e-4; the
Hessians of lam'F are first differences of A, B (1e-6).
"""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import workbench as wb
from workbench.problem.models import Model
from workbench.problem.obstacles import Circle
from workbench.problem.scene_kinds import Capsule, HalfSpace, MovingCircle, Sphere
from workbench.problem.scene_layout import SceneLayout
from workbench.problem.sdf_grid import SignedDistanceGrid
from workbench.sampling.problem import SamplingProblem

H1, TOL1 = 1e-6, 1e-6  # first differences
H2, TOL2 = 1e-4, 1e-4  # second differences of the margins
SAFE = 0.2  # smallest margin of a state used
KINK = 0.05  # distance of a capsule's t from 0, 1, of a cell coordinate from an edge


def grid() -> SignedDistanceGrid:
    xs, ys = np.arange(8) * 0.5 - 0.5, np.arange(7) * 0.5 - 0.5
    r = np.hypot(xs[:, None] - 1.3, ys[None, :] - 1.1)
    return SignedDistanceGrid(r - 0.6 + 0.1 * np.sin(3 * xs[:, None]) * ys[None, :],
                              (-0.5, -0.5), 0.5)


# kind: (layout, obstacles, margin form)
KINDS = {
    "circles": (SceneLayout.of(circles=2), [Circle((1.0, 1.2), 0.4)], "squared"),
    "moving": (SceneLayout.of(moving=1), [MovingCircle((1.0, 1.2), 0.4, (0.5, -0.3))],
               "signed_distance"),
    "halfplanes": (SceneLayout.of(halfspaces=2), [HalfSpace((0.6, 0.8), -0.5),
                                                  HalfSpace((-1.0, 0.2), -3.0)], "squared"),
    "capsules": (SceneLayout.of(capsules=1), [Capsule((0.5, 0.5), (2.0, 1.5), 0.3)],
                 "signed_distance"),
    "grid": (SceneLayout.of(grid=(8, 7)), [grid()], "squared"),
    "spheres": (SceneLayout.of(dim=3, spheres=1), [Sphere((1.0, 1.0, 1.0), 0.5)], "squared"),
    "halfspaces": (SceneLayout.of(dim=3, halfspaces=1), [HalfSpace((0.2, -0.4, 0.8), -0.3)],
                   "signed_distance"),
    "capsules_3d": (SceneLayout.of(dim=3, capsules=1),
                    [Capsule((0.5, 0.5, 0.5), (1.5, 2.0, 1.0), 0.4)], "squared"),
}


def double_integrator(layout: SceneLayout, obstacles, h_form: str) -> Model:
    """x = [p, v], u = a (in the plane or in space), Euler steps of 0.1 s."""
    d = layout.dim
    x, u, dt = ca.SX.sym("x", 2 * d), ca.SX.sym("u", d), 0.1
    s = layout.symbol()
    return Model.from_expressions(
        f"di{d}", x, u, ca.vertcat(x[:d] + dt * x[d:], x[d:] + dt * u), dt=dt,
        u_min=-5 * np.ones(d), u_max=5 * np.ones(d), h=layout.margins(x[:d], s, h_form),
        position=tuple(range(d)), scene=s, scene_value=list(obstacles), scene_layout=layout)


def away_from_kinks(layout: SceneLayout, scene: np.ndarray, p: np.ndarray, h_form: str) -> bool:
    if np.min(layout.numpy_margins(p[None], scene, h_form)) < SAFE:
        return False
    d = layout.dim
    for b in layout.blocks():
        if b.kind.name != "capsules":
            continue
        for S in scene[b.start:b.stop].reshape(b.count, b.width):
            a, ab = S[:d], S[d:2 * d] - S[:d]
            t = (p - a) @ ab / (ab @ ab)
            if min(abs(t), abs(t - 1.0)) < KINK:
                return False
    if layout.grid:
        g = scene[layout.grid_start:]
        cells = (p - g[:2]) / g[2]
        if np.any(np.abs(cells - np.round(cells)) < KINK):
            return False
    return True


@pytest.fixture(scope="module", params=list(KINDS))
def kind(request):
    layout, obstacles, h_form = KINDS[request.param]
    plain = double_integrator(layout, obstacles, h_form)
    model = wb.embed_barrier(plain)
    g = ca.SX.sym("g", model.nx)
    sp = SamplingProblem.from_costs(model, ca.dot(model.x - g, model.x - g),
                                    ca.dot(model.x - g, model.x - g), g)
    rng = np.random.default_rng(list(KINDS).index(request.param) + 40)
    d, scene = layout.dim, plain.scene_value
    pts: list[np.ndarray] = []
    while len(pts) < 4:
        p = rng.uniform(-0.4, 2.6, d)
        if away_from_kinks(layout, scene, p, h_form):
            pts.append(p)
    states = [model.lift(np.concatenate([p, rng.normal(0.0, 0.5, d)])) for p in pts]
    return request.param, plain, sp.problem.functions, states, rng


def central(f, x: np.ndarray, h: float) -> np.ndarray:
    """d f / d x by central differences: (out..., n) for f(x) of any shape."""
    cols = []
    for j in range(x.size):
        e = np.zeros_like(x)
        e[j] = h
        cols.append((np.asarray(f(x + e), float) - np.asarray(f(x - e), float)) / (2 * h))
    return np.stack(cols, axis=-1)


def close(a, b, tol: float) -> bool:
    a, b = np.asarray(a, float), np.asarray(b, float)
    assert a.shape == b.shape
    return bool(np.all(np.abs(a - b) <= tol * np.maximum(np.maximum(np.abs(a), np.abs(b)), 1)))


def controls(kind):
    """Per state: a control and a multiplier lam. Controls are small: a step of 0.1 s must not
    leave the safe set (the barrier state of x_next would then be capped)."""
    _, plain, _, states, rng = kind
    return [(rng.uniform(-0.5, 0.5, plain.nu), rng.normal(0.0, 1.0, x.size)) for x in states]


def test_dyn_jac_equals_finite_differences(kind):
    name, plain, f, states, _ = kind
    scene = plain.scene_value
    dyn = f["dyn"]
    for x, (u, _) in zip(states, controls(kind), strict=True):
        A, B = (np.asarray(m) for m in f["dyn_jac"](x, u, scene))
        fd_a = central(lambda z, u=u: np.asarray(dyn(z, u, scene)).ravel(), x, H1)
        fd_b = central(lambda w, x=x: np.asarray(dyn(x, w, scene)).ravel(), u, H1)
        assert close(A, fd_a, TOL1) and close(B, fd_b, TOL1), name
        assert np.any(np.abs(A[-1, :plain.nx]) > 1e-3), name  # the barrier state is in play


def test_dyn_hess_equals_finite_differences(kind):
    name, plain, f, states, _ = kind
    scene = plain.scene_value
    for x, (u, lam) in zip(states, controls(kind), strict=True):
        fxx, fuu, fux = (np.asarray(m) for m in f["dyn_hess"](x, u, lam, scene))
        jac = f["dyn_jac"]

        def lam_a(z, w):
            return lam @ np.asarray(jac(z, w, scene)[0])

        def lam_b(z, w):
            return lam @ np.asarray(jac(z, w, scene)[1])

        assert close(fxx, central(lambda z, u=u: lam_a(z, u), x, H1), TOL1), name
        assert close(fuu, central(lambda w, x=x: lam_b(x, w), u, H1), TOL1), name
        assert close(fux, central(lambda z, u=u: lam_b(z, u), x, H1), TOL1), name


def margin_parts(kind):
    """(CasADi margins h(p, scene) of the layout, NumPy margins at one position, the used
    margins' indices). An unused slot's margin (~1e16) is left out: differences cannot
    resolve it."""
    name, plain, _, _, _ = kind
    layout, scene = plain.scene_layout, plain.scene_value
    h_form = KINDS[name][2]
    p, s = ca.SX.sym("p", layout.dim), layout.symbol()
    h = layout.margins(p, s, h_form)

    def margins(q):
        return layout.numpy_margins(q[None], scene, h_form)[0]

    used = [i for i in range(h.numel()) if i < len(KINDS[name][1])]
    return p, s, h, margins, used


def test_margin_gradient_equals_differences_of_the_numpy_margins(kind):
    name, plain, _, states, _ = kind
    p, s, h, margins, used = margin_parts(kind)
    grad = ca.Function("margin_gradient", [p, s], [ca.jacobian(h, p)])
    d = plain.scene_layout.dim
    for x in states:
        G = np.asarray(grad(x[:d], plain.scene_value))[used]
        assert close(G, central(margins, x[:d], H1)[used], TOL1), name


def test_margin_hessian_equals_differences_of_the_numpy_margins(kind):
    name, plain, _, states, _ = kind
    p, s, h, margins, used = margin_parts(kind)
    d = plain.scene_layout.dim
    for i in used:
        hess = ca.Function(f"margin_hessian{i}", [p, s], [ca.hessian(h[i], p)[0]])
        for x in states:
            Hc = np.asarray(hess(x[:d], plain.scene_value))
            Hd = central(lambda z, i=i: central(margins, z, H2)[i], x[:d], H2)
            assert close(Hc, Hd, TOL2), (name, i)

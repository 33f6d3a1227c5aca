"""The signed-distance grid in the gradient-based paths: the margin's gradient (CasADi's
derivative of the interpolant) equals the bilinear cell's closed-form gradient, inside cells and
beyond the grid; the compiled iLQG derivatives (CasADi's own code generation of the interpolant
and its derivatives, the scene a run-time input) equal the NumPy/VM twin's; the discrete CBF's
control Jacobian equals finite differences of its constraint.

Tolerances: relative per element, |a - b| <= RTOL max(|a|, |b|, 1).
"""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from workbench.ilqg import make_passes
from workbench.ilqg.twin import PassesTwin
from workbench.problem.barrier import embed_barrier
from workbench.problem.costs import quadratic_tracking
from workbench.problem.dcbf import discrete_cbf
from workbench.problem.models import double_integrator
from workbench.problem.obstacles import Circle
from workbench.problem.problem import Problem
from workbench.problem.scene_layout import SceneLayout
from workbench.problem.sdf_grid import SignedDistanceGrid

SHAPE, ORIGIN, RES = (16, 12), (-0.4, -0.2), 0.3
LAYOUT = SceneLayout.of(circles=1, grid=SHAPE)
T = 25


def rel(a, b) -> np.ndarray:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return np.abs(a - b) / np.maximum(np.maximum(np.abs(a), np.abs(b)), 1.0)


@pytest.fixture(scope="module")
def model():
    rng = np.random.default_rng(77)
    grid = SignedDistanceGrid(rng.uniform(0.2, 3.0, SHAPE), ORIGIN, RES)
    return double_integrator(scene_layout=LAYOUT, obstacles=[grid, Circle((3.0, 2.5), 0.3)],
                             u_limit=5.0), grid


def cell_gradient(grid: SignedDistanceGrid, P: np.ndarray) -> np.ndarray:
    """d margin / d position of the bilinear form of each point's cell; beyond the grid the
    nearest grid point's value: the gradient across the boundary is 0."""
    nx, ny = grid.shape
    V = grid.values
    raw = (P - np.asarray(grid.origin)) / grid.resolution
    u = np.clip(raw, 0, [nx - 1, ny - 1])
    i = np.clip(np.floor(u[:, 0]), 0, nx - 2).astype(int)
    j = np.clip(np.floor(u[:, 1]), 0, ny - 2).astype(int)
    a, b = u[:, 0] - i, u[:, 1] - j
    gx = (1 - b) * (V[i + 1, j] - V[i, j]) + b * (V[i + 1, j + 1] - V[i, j + 1])
    gy = (1 - a) * (V[i, j + 1] - V[i, j]) + a * (V[i + 1, j + 1] - V[i + 1, j])
    inside = (raw >= 0) & (raw <= [nx - 1, ny - 1])
    return np.where(inside, np.c_[gx, gy], 0.0) / grid.resolution


def test_the_margin_gradient_is_the_cells(model):
    m, grid = model
    rng = np.random.default_rng(3)
    x0, x1, y0, y1 = grid.extent()
    P = np.r_[np.c_[rng.uniform(x0, x1, 60), rng.uniform(y0, y1, 60)],
              np.c_[rng.uniform(x0 - 2, x0, 10), rng.uniform(y0, y1, 10)],  # beyond the sides
              np.c_[rng.uniform(x1, x1 + 2, 10), rng.uniform(y1, y1 + 2, 10)]]
    x, s = m.x, m.scene
    J = ca.Function("J", [x, s], [ca.jacobian(m.h[-1], x)])
    got = np.array([np.asarray(J(np.r_[p, 0.0, 0.0], m.scene_value)).ravel()[:2] for p in P])
    want = cell_gradient(grid, P)
    assert rel(got, want).max() <= 1e-12
    assert np.all(got[:60] != 0.0) and np.all(got[60:70, 0] == 0) and np.all(got[70:] == 0)


def test_compiled_ilqg_derivatives_equal_the_twin(model):
    m, _ = model
    emb = embed_barrier(m)
    cost = quadratic_tracking(emb, Q=[10, 10, 1, 1], R=[1e-3, 1e-3], S=[100, 100, 10, 10],
                              q_beta=1e-2, s_beta=0.05)
    problem = Problem.build(emb, cost)
    fast = make_passes(problem, T, "compiled")
    if isinstance(fast, PassesTwin):
        pytest.skip("no C compiler")
    slow = PassesTwin(problem, T)
    rng = np.random.default_rng(11)
    x_ref = np.c_[np.linspace(0.0, 3.5, T + 1), np.linspace(0.2, 2.0, T + 1),
                  np.zeros((T + 1, 2))]
    P = cost.params(T, x_ref=x_ref, beta_ref=emb.lift(x_ref[-1])[4:])
    # states on and beyond the grid (positions from -1 to 4.6 m)
    X = np.array([emb.lift(np.r_[rng.uniform(-1.0, 4.6), rng.uniform(-0.8, 3.6),
                                 rng.normal(0, 1, 2)]) for _ in range(T + 1)])
    U = rng.normal(0.0, 2.0, (T, 2))
    d_f = {k: np.array(v) for k, v in fast.derivatives(X, U, P).items()}  # (buffers reused)
    d_s = slow.derivatives(X, U, P)
    for k in ("A", "B", "lx", "lu", "lxx", "luu", "lux"):
        assert rel(d_f[k], d_s[k]).max() <= 1e-12, k
    assert np.abs(d_s["A"][:, 4, :2]).max() > 0  # the barrier state's gradient in position
    # a new grid of the same shape: the same library, the new grid's derivatives
    other = SignedDistanceGrid(rng.uniform(0.2, 3.0, SHAPE), (0.1, 0.0), 0.25)
    scene = m.scene_vector([other, Circle((3.0, 2.5), 0.3)])
    fast.set_scene(scene)
    slow.set_scene(scene)
    d_f2, d_s2 = fast.derivatives(X, U, P), slow.derivatives(X, U, P)
    assert rel(d_f2["A"], d_s2["A"]).max() <= 1e-12
    assert not np.allclose(d_f2["A"], d_f["A"])


def test_the_discrete_cbf_jacobian_equals_finite_differences(model):
    """Central differences inside a cell are exact up to rounding (the constraint is
    polynomial in u there)."""
    m, _ = model
    cbf = discrete_cbf(m)
    rng = np.random.default_rng(5)
    s = m.scene_value
    for _ in range(10):
        x = np.r_[rng.uniform(0.0, 4.0), rng.uniform(0.0, 3.0), rng.normal(0, 1, 2)]
        u = rng.normal(0.0, 2.0, 2)
        J = np.asarray(cbf.jacobian(x, u, 0.5, s))
        eps = 1e-6
        fd = np.column_stack([(np.asarray(cbf.c(x, u + e, 0.5, s)) -
                               np.asarray(cbf.c(x, u - e, 0.5, s))).ravel() / (2 * eps)
                              for e in eps * np.eye(2)])
        assert np.all(np.abs(J - fd) <= 1e-5 * np.maximum(np.abs(J), 1.0))

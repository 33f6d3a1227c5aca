"""The iLQG passes, K_safe and AL with moving circles: each step is evaluated in the scene
predicted to its time (NumPy oracles step by step); models without moving circles keep the
compiled passes."""

from __future__ import annotations

import numpy as np
import pytest

import workbench as wb
from workbench.ilqg import make_passes
from workbench.ilqg.al import al_problem
from workbench.ilqg.twin import CRASH_PENALTY, PassesTwin
from workbench.problem.costs import quadratic_tracking
from workbench.problem.scene_kinds import MovingCircle
from workbench.problem.scene_layout import SceneLayout

DT, T = 0.05, 16
LAYOUT = SceneLayout.of(circles=1, moving=2)
SCENE = [wb.Circle((3.0, 3.0), 0.4), MovingCircle((1.2, 0.3), 0.3, (-1.5, 0.2)),
         MovingCircle((-2.0, -2.0), 0.2, (0.0, 0.0))]


@pytest.fixture(scope="module")
def moving():
    model = wb.double_integrator(dt=DT, scene_layout=LAYOUT, obstacles=SCENE, u_limit=4.0)
    return model, wb.navigation_costs(wb.embed_barrier(model))


def _close(a, b, rtol=1e-12):
    a, b = np.asarray(a, float), np.asarray(b, float)
    err = np.abs(a - b) / np.maximum(np.maximum(np.abs(a), np.abs(b)), 1.0)
    assert a.shape == b.shape and np.all(err <= rtol), float(err.max())


def test_passes_step_in_the_predicted_scenes(moving):
    _, sp = moving
    problem, m = sp.problem, sp.model
    passes = make_passes(problem, T)
    assert isinstance(passes, PassesTwin)
    with pytest.raises(ValueError, match="compiled iLQG passes hold one scene"):
        make_passes(problem, T, "compiled")
    v = m.scene_value
    passes.set_scene(v)
    U = np.random.default_rng(4).normal(0, 2.5, (T, 2))
    x0 = m.lift(np.array([0.0, 0.3, 0.6, 0.0]), v)
    P = np.tile(m.lift(np.array([2.0, 0.3, 0, 0]), v), (T + 1, 1))
    z = np.zeros((T, 2))
    fw = passes.forward(x0, np.zeros((T + 1, m.nx)), U, z, np.zeros((T, 2, m.nx)), P, 0.0,
                        m.u_min, m.u_max, use_policy=False)
    f = problem.functions
    x, J, crashed = x0, 0.0, False
    for t in range(T):  # oracle: step t in the scene predicted to (t + 1) dt
        u = np.clip(U[t], m.u_min, m.u_max)
        st = LAYOUT.predicted(v, (t + 1) * DT)
        J += float(f["stage"](x, u, P[t]))
        x = np.asarray(f["dyn"](x, u, st)).ravel()
        h = LAYOUT.numpy_margins(x[:2], st)
        crashed_now = bool(np.any(~(h >= 1e-15)))
        J += CRASH_PENALTY if crashed_now else 0.0
        crashed |= crashed_now
        _close(fw.X[t + 1], x)
    J += float(f["term"](x, P[T]))
    assert fw.cost == pytest.approx(J, rel=1e-12)
    assert crashed  # the heading circle is hit: the penalty branch is taken
    d = passes.derivatives(fw.X, fw.U, P)
    for t in (0, T // 2, T - 1):
        A, B = f["dyn_jac"](fw.X[t], fw.U[t], LAYOUT.predicted(v, (t + 1) * DT))
        _close(d["A"][t], np.asarray(A))
        _close(d["B"][t], np.asarray(B))
    # the present scene gives other derivatives (prediction acts)
    A0, _ = f["dyn_jac"](fw.X[T - 1], fw.U[T - 1], v)
    assert not np.allclose(np.asarray(A0), d["A"][T - 1], rtol=1e-6)


def test_models_without_moving_circles_keep_the_compiled_passes():
    still = wb.navigation_costs(wb.embed_barrier(wb.double_integrator(
        obstacles=(wb.Circle((1.0, 1.0), 0.3),))))
    assert make_passes(still.problem, T).name == "compiled"  # (the test machine compiles)
    layout_still = wb.double_integrator(scene_layout=SceneLayout.of(circles=1, halfspaces=1),
                                        obstacles=[wb.Circle((1.0, 1.0), 0.3)])
    p = wb.navigation_costs(wb.embed_barrier(layout_still)).problem
    assert make_passes(p, T).name == "compiled"


def test_ksafe_gains_see_the_velocities(moving):
    _, sp = moving
    fb = wb.ILQGFeedback(sp.model, T, sp.nx)
    assert not fb.compiled  # the compiled law holds one scene
    x0 = sp.model.lift(np.array([0.0, 0.3, 0.6, 0.0]), sp.model.scene_value)
    U = np.tile([0.5, 0.0], (T, 1))
    fb.set_scene(SCENE)
    g = fb.fast_gains(x0, U, None, 1)
    still = [SCENE[0], MovingCircle(SCENE[1].center, 0.3, (0.0, 0.0)), SCENE[2]]
    fb.set_scene(still)
    g0 = fb.fast_gains(x0, U, None, 1)
    assert np.all(np.isfinite(g.K)) and not np.allclose(g.K, g0.K, rtol=1e-6)


def test_al_parameters_and_constraints_per_step(moving):
    model, _ = moving
    cost = quadratic_tracking(model, Q=(1.0, 1.0, 0.1, 0.1), R=(0.1, 0.1), S=(1.0, 1.0, 0.1, 0.1))
    alp = al_problem(model, cost)
    assert alp.problem.model.scene_layout is None  # the inner model has no scene of its own
    v = model.scene_value
    n = T + 1
    P_base = np.zeros((n, alp.n_base_params))
    lam, mu = np.zeros((n, model.nh)), np.ones((n, model.nh))
    P = alp.params(P_base, lam, mu, v)
    for k in (0, 5, T):
        np.testing.assert_array_equal(P[k, -model.n_scene:], LAYOUT.predicted(v, k * DT))
    X = np.column_stack([np.linspace(0, 1.5, n), np.full(n, 0.3), np.zeros((n, 2))])
    C = alp.constraint_values(X, v)
    for k in range(n):
        _close(C[k], -LAYOUT.numpy_margins(X[k, :2], LAYOUT.predicted(v, k * DT))[0])
    fb = wb.ALFeedback(model, T, model.nx)
    fb.set_scene(v)
    _close(fb.constraint_values(X), C)

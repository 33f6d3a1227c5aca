"""Moving circles with velocities: a generated map's true scene per step (positions and current
velocities, bounces included), the plant's crash check on a scene that carries velocities, the
horizon checks that predict (gatekeeper backup, Problem.rollout) against NumPy oracles, and
the plumbing of the paired prediction experiment."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import workbench as wb
from workbench.problem.prediction import step_scenes
from workbench.problem.scene_kinds import MovingCircle
from workbench.problem.scene_layout import SceneLayout
from workbench.sampling.methods.gatekeeper import backup_check_function, braking_backup
from workbench.scenarios import moving_prediction as mp

DT = 0.02


@pytest.fixture(scope="module")
def moving_map():
    return wb.generate(wb.MapFamily(moving=3, speed=0.7), 4)


def test_velocity_scene_gives_true_positions_and_current_velocities(moving_map):
    m = moving_map
    layout = m.scene_layout()
    assert layout == SceneLayout.of(circles=m.n_static, moving=3)
    movers = [i for i, _ in m.moving]
    flips = 0
    for k in range(0, 2000, 3):
        now, nxt = m.velocity_scene_at(k, DT), m.velocity_scene_at(k + 1, DT)
        assert sum(isinstance(o, MovingCircle) for o in now) == 3
        # positions are scene_at's (the plant's truth); static circles unchanged
        truth = m.scene_at(k, DT)
        static = [c for i, c in enumerate(truth) if i not in movers]
        assert list(now[:m.n_static]) == static
        for j, i in enumerate(movers):
            a, b = now[m.n_static + j], nxt[m.n_static + j]
            assert a.center == truth[i].center and a.radius == truth[i].radius
            assert np.hypot(*a.velocity) == pytest.approx(0.7, rel=1e-12)
            fd = (np.array(b.center) - np.array(a.center)) / DT
            if a.velocity == b.velocity:  # no bounce within the step: a forward difference
                np.testing.assert_allclose(fd, a.velocity, rtol=1e-9, atol=1e-9)
            else:  # a bounce: one component reverses
                flips += 1
                assert np.sum(np.array(a.velocity) == -np.array(b.velocity)) >= 1
        np.testing.assert_array_equal(layout.vector(now)[:3 * m.n_static],
                                      wb.scene_vector(static, m.n_static))
    assert flips > 0  # the window covers bounces
    with pytest.raises(ValueError, match=r"velocity_scene_at\.k"):
        m.velocity_scene_at(-1, DT)
    with pytest.raises(ValueError, match=r"velocity_scene\.dt"):
        m.velocity_scene(0.0)


def test_plant_checks_crashes_on_true_positions_with_velocities():
    """A plant standing still while a circle drives at it crashes at the step the true circle
    reaches it, whether the scene carries the velocity or not (velocities are for the
    controllers only)."""
    layout = SceneLayout.of(circles=1, moving=1)
    fixed = wb.Circle((-3.0, 3.0), 0.3)

    def scene(told):
        def at(k):
            c = (2.0 - 1.0 * k * DT, 0.0)
            return [fixed, MovingCircle(c, 0.5, (-1.0, 0.0) if told else (0.0, 0.0))]
        return at

    plant = wb.double_integrator(dt=DT, scene_layout=layout, obstacles=scene(True)(0))

    class Still:
        def initial_state(self, x0):
            return None

        def step(self, state, x, rng):
            return None, np.zeros(2), None

    eps = [wb.closed_loop(Still(), plant, np.zeros(4), 200, np.random.default_rng(0),
                          np.random.default_rng(1), scene=scene(told)) for told in (True, False)]
    # centre at 2 - 0.02 k, radius 0.5: the margin 0 at k = 75 -> the state after step 74
    for ep in eps:
        assert ep.crashed and len(ep.U) == 75
    np.testing.assert_array_equal(eps[0].scenes[:, :3], eps[1].scenes[:, :3])
    np.testing.assert_array_equal(eps[0].scenes[:, 3:5], eps[1].scenes[:, 3:5])
    assert np.all(eps[0].scenes[:, 6] == -1.0) and np.all(eps[1].scenes[:, 6] == 0.0)


def test_gatekeeper_backup_check_predicts_the_moving_circles():
    layout = SceneLayout.of(circles=1, moving=2)
    scene = [wb.Circle((4.0, 4.0), 0.5), MovingCircle((1.5, 0.2), 0.3, (-1.2, 0.4)),
             MovingCircle((-1.0, -1.0), 0.2, (0.0, 0.0))]
    plant = wb.double_integrator(dt=DT, scene_layout=layout, obstacles=scene, u_limit=5.0)
    backup = braking_backup(plant)
    H = 30
    check = backup_check_function(plant, backup, H)
    v = plant.scene_value
    x1 = np.array([0.3, 0.0, 1.0, 0.2])
    got_min, got_xH, _ = (np.asarray(o).ravel() for o in check(x1, v))
    # oracle: roll the backup out, each state's margins in the scene predicted to its time
    f = ca.Function("f", [plant.x, plant.u], [plant.x_next])
    u_of = ca.Function("u", [plant.x], [ca.fmin(ca.fmax(backup.function(plant.x),
                                                        plant.u_min), plant.u_max)])
    x, hs = x1, [np.min(layout.numpy_margins(x1[:2], layout.predicted(v, DT)))]
    for j in range(H):
        x = np.asarray(f(x, u_of(x))).ravel()
        hs.append(np.min(layout.numpy_margins(x[:2], layout.predicted(v, (j + 2) * DT))))
    np.testing.assert_allclose(got_xH, x, rtol=1e-12, atol=1e-12)
    assert got_min[0] == pytest.approx(min(hs), rel=1e-12)
    present = min(np.min(layout.numpy_margins(y[:2], v)) for y in [x1, x])
    assert abs(got_min[0] - present) > 1e-3  # prediction changed the check's margin


def test_rollout_steps_in_the_predicted_scenes():
    layout = SceneLayout.of(circles=1, moving=1)
    scene = [wb.Circle((3.0, 3.0), 0.4), MovingCircle((1.0, 0.0), 0.3, (-0.8, 0.1))]
    model = wb.embed_barrier(wb.double_integrator(dt=DT, scene_layout=layout, obstacles=scene))
    sp = wb.navigation_costs(model)
    U = np.random.default_rng(2).normal(0, 1, (12, 2))
    x0 = model.lift(np.array([0.0, 0.2, 0.3, 0.0]), model.scene_value)
    X = sp.problem.rollout(x0, U)
    S = step_scenes(model, model.scene_value, 12)
    for k in range(12):
        want = np.asarray(sp.functions()["dyn"](X[k], U[k], S[:, k])).ravel()
        np.testing.assert_allclose(X[k + 1], want, rtol=1e-12, atol=0)
        h = layout.numpy_margins(X[k + 1, :2], layout.predicted(model.scene_value,
                                                                 (k + 1) * DT))[0]
        assert X[k + 1, 4] == pytest.approx(np.sum(1.0 / h), rel=1e-12)
    np.testing.assert_array_equal(S[:, 0], layout.predicted(model.scene_value, DT))


def test_prediction_trial_plumbing():
    """Two seeds, a short episode: the counts and tests agree with the per-seed outcomes; a
    circle that does not move makes the arms identical and prediction inert."""
    from scipy.stats import binomtest

    small = wb.MPPIConfig(n_samples=64, horizon=20, sigma=(5.0, 5.0), lam=10.0)
    res = mp.run_trial(mp.TrialConfig(seeds=2, speed=0.7, steps=90, mppi=small))
    for arm in mp.ARMS:
        assert res.crashes[arm] == sum(res.arms[arm].crashed)
    cp, cn = np.array(res.arms["predicted"].crashed), np.array(res.arms["present"].crashed)
    b, c = int(np.sum(cn & ~cp)), int(np.sum(cp & ~cn))
    assert res.discordant == {"only_present_crashed": b, "only_predicted_crashed": c}
    assert res.difference == pytest.approx((b - c) / 2, rel=1e-12)
    assert res.low <= res.difference <= res.high
    assert res.mcnemar_p == (pytest.approx(binomtest(b, b + c, 0.5).pvalue, rel=1e-12)
                             if b + c else 1.0)
    assert 0.0 < res.plan_margin_differs <= 1.0
    still = mp.run_trial(mp.TrialConfig(seeds=1, speed=0.0, steps=40, mppi=small))
    assert still.arms["predicted"] == still.arms["present"]
    assert still.plan_margin_differs == 0.0 and still.plan_margin_diff_mean == 0.0
    with pytest.raises(ValueError, match=r"TrialConfig\.seeds"):
        mp.TrialConfig(seeds=0)

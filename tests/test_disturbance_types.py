"""Disturbance types (the four Gaussian readings, safe-control-gym's impulse, step, uniform and
periodic) against their closed forms, and closed_loop's stop at the goal."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from workbench.problem.models import Model, double_integrator, single_integrator
from workbench.problem.obstacles import Circle
from workbench.sim import DISTURBANCE_MODELS, Disturbance, DisturbanceModel, closed_loop

DT = 0.02
OLD = ("velocity_variance", "velocity_std", "white_noise", "kick")


class _Hold:
    """Applies one control forever; ``goal`` (optional) is the physical goal state."""

    def __init__(self, u, goal=None):
        self.u = np.asarray(u, float)
        if goal is not None:
            self.goal = np.asarray(goal, float)

    def initial_state(self, x0):
        return 0

    def step(self, state, x, rng):
        return state + 1, self.u, {}


def _old_w(model: str, level: float, xi: np.ndarray) -> np.ndarray:
    """The four readings as written before the time-dependent types existed."""
    if model == "velocity_variance":
        return DT * np.sqrt(level) * xi
    if model == "velocity_std":
        return DT * level * xi
    if model == "white_noise":
        return np.sqrt(DT) * np.sqrt(level) * xi
    return np.sqrt(level) * xi


def test_models_and_literal_agree():
    assert DISTURBANCE_MODELS == DisturbanceModel.__args__
    assert set(OLD) | {"impulse", "step", "uniform", "periodic"} == set(DISTURBANCE_MODELS)


# ---------------------------------------------------------------------------------------------
# the four Gaussian readings draw exactly what they drew before


@pytest.mark.parametrize("model", OLD)
def test_old_readings_draw_the_same_numbers_at_every_step(model):
    d = Disturbance(10.0, model, velocity_index=(2, 3))
    rng, ref = np.random.default_rng(7), np.random.default_rng(7)
    for k in range(60):  # the step index changes nothing
        w = d.sample(4, DT, rng, k=k)
        expect = np.zeros(4)
        expect[[2, 3]] = _old_w(model, 10.0, ref.standard_normal(2))
        np.testing.assert_array_equal(w, expect)
    assert rng.bit_generator.state == ref.bit_generator.state


@pytest.mark.parametrize("model", OLD)
def test_old_readings_give_bit_identical_episodes(model):
    plant = double_integrator(u_limit=5.0)
    u = np.array([1.0, -0.5])
    ep = closed_loop(_Hold(u), plant, np.zeros(4), 80, np.random.default_rng(0),
                     np.random.default_rng(3), Disturbance(10.0, model))
    ref, x, X = np.random.default_rng(3), np.zeros(4), [np.zeros(4)]
    for _ in range(80):  # Euler: p + dt v, v + dt u, then w on the velocities
        x = np.concatenate([x[:2] + DT * x[2:], x[2:] + DT * u])
        x[2:] = x[2:] + _old_w(model, 10.0, ref.standard_normal(2))
        X.append(x.copy())
    np.testing.assert_array_equal(ep.X, np.array(X))


# ---------------------------------------------------------------------------------------------
# safe-control-gym's types against their closed forms


def _scg_impulse(k: int, offset: int, duration: int, decay: float, magnitude: float) -> float:
    """safe-control-gym's ImpulseDisturbance as its definition reads (peak at
    int(offset + duration / 2), nonzero while |k - peak| < duration / 2)."""
    if k < offset:
        return 0.0
    peak = int(offset + duration / 2)
    off = abs(k - peak)
    return magnitude * decay**off if off < duration / 2 else 0.0


@pytest.mark.parametrize(("duration", "decay"), [(1, 1.0), (3, 0.5), (5, 0.8), (7, 1.0),
                                                 (4, 0.5), (6, 1.0)])
def test_impulse_is_nonzero_only_in_its_window_with_the_decay(duration, decay):
    d = Disturbance(2.0, "impulse", start_step=5, duration=duration, decay=decay,
                    velocity_index=(2, 3))
    rng = np.random.default_rng(1)
    before = rng.bit_generator.state
    W = np.array([d.sample(4, DT, rng, k=k) for k in range(30)])
    assert rng.bit_generator.state == before  # deterministic: no draws
    np.testing.assert_array_equal(W[:, :2], 0.0)
    centre = 5 + (duration - 1) / 2
    expect = np.array([DT * 2.0 * decay ** abs(k - centre) if 5 <= k < 5 + duration else 0.0
                       for k in range(30)])
    np.testing.assert_allclose(W[:, 2], expect, rtol=1e-15, atol=0)
    np.testing.assert_array_equal(W[:, 2], W[:, 3])
    assert np.count_nonzero(W[:, 2]) == duration
    assert np.flatnonzero(W[:, 2])[[0, -1]].tolist() == [5, 5 + duration - 1]
    if decay < 1:  # the peak at the centre (the first of two for an even duration)
        assert np.argmax(W[:, 2]) == int(np.floor(centre))
    scg = np.array([DT * _scg_impulse(k, 5, duration, decay, 2.0) for k in range(30)])
    if duration % 2:  # odd: safe-control-gym's pulse step for step
        np.testing.assert_allclose(W[:, 2], scg, rtol=1e-15, atol=0)
    else:  # even: theirs has duration - 1 steps from start_step + 1
        assert np.count_nonzero(scg) == duration - 1 and scg[5] == 0.0


@pytest.mark.parametrize("level", [3.0, -1.5])
def test_step_is_constant_from_start_step(level):
    d = Disturbance(level, "step", start_step=12, states=(3,))
    rng = np.random.default_rng(1)
    W = np.array([d.sample(4, DT, rng, k=k) for k in range(40)])
    np.testing.assert_array_equal(W[:12], 0.0)
    np.testing.assert_array_equal(W[12:, :3], 0.0)
    np.testing.assert_array_equal(W[12:, 3], DT * level)


def test_uniform_stays_in_its_bounds_and_has_their_mean_and_variance():
    level, low, high, n = 4.0, -0.5, 2.0, 100_000
    d = Disturbance(level, "uniform", low=low, high=high, velocity_index=(2, 3))
    rng, ref = np.random.default_rng(5), np.random.default_rng(5)
    W = np.array([d.sample(4, DT, rng, k=k) for k in range(n)])
    np.testing.assert_array_equal(W[:, :2], 0.0)
    V = W[:, 2:].ravel()
    a, b = DT * level * low, DT * level * high
    assert a <= V.min() and V.max() <= b
    assert V.min() < a + 1e-3 * (b - a) and V.max() > b - 1e-3 * (b - a)  # fills the range
    mean, var = (a + b) / 2, (b - a) ** 2 / 12
    assert abs(V.mean() - mean) < 4 * np.sqrt(var / V.size)
    assert abs(V.var() - var) < 4 * var * np.sqrt(0.8 / V.size)  # var of (U - m)^2: 0.8 var^2
    # the draws are the generator's own uniform(low, high) numbers, scaled
    np.testing.assert_array_equal(W[:3, 2:], DT * level * ref.uniform(low, high, (3, 2)))
    d0 = Disturbance(1.0, "uniform", velocity_index=(2,))  # default: U(-level, level)
    v = np.array([d0.sample(4, DT, rng)[2] for _ in range(20_000)])
    assert -DT <= v.min() and v.max() <= DT and v.min() < -0.99 * DT and v.max() > 0.99 * DT


def test_periodic_matches_the_sine():
    level, f, phase = 2.5, 1.5, 0.7
    d = Disturbance(level, "periodic", frequency=f, phase=phase, velocity_index=(2, 3))
    rng = np.random.default_rng(1)
    before = rng.bit_generator.state
    k = np.arange(300)
    W = np.array([d.sample(4, DT, rng, k=int(i)) for i in k])
    assert rng.bit_generator.state == before
    expect = DT * level * np.sin(2 * np.pi * f * k * DT + phase)
    np.testing.assert_allclose(W[:, 2], expect, rtol=0, atol=1e-16)
    np.testing.assert_array_equal(W[:, 3], W[:, 2])
    np.testing.assert_allclose(W[100:, 2], W[:-100, 2], atol=1e-15)  # 3 periods: 100 steps


def test_closed_loop_hands_the_step_index_to_the_disturbance():
    plant = double_integrator(u_limit=5.0)
    ep = closed_loop(_Hold([0.0, 0.0]), plant, np.zeros(4), 30, np.random.default_rng(0),
                     np.random.default_rng(1), Disturbance(3.0, "step", start_step=10,
                                                           states=("vx",)))
    j = np.arange(31)
    np.testing.assert_allclose(ep.X[:, 2], DT * 3.0 * np.maximum(0, j - 10), atol=1e-15)
    np.testing.assert_array_equal(ep.X[:, [1, 3]], 0.0)
    imp = Disturbance(4.0, "impulse", start_step=5, duration=3, decay=0.5, states=("vy",))
    ep = closed_loop(_Hold([0.0, 0.0]), plant, np.zeros(4), 20, np.random.default_rng(0),
                     np.random.default_rng(1), imp)
    dv = np.diff(ep.X[:, 3])
    np.testing.assert_allclose(dv, [DT * 4.0 * (0.5 if k in (5, 7) else 1.0 if k == 6 else 0.0)
                                    for k in range(20)], atol=1e-15)


@pytest.mark.parametrize(("d", "label"), [
    (Disturbance(10.0), "velocity_variance(10)"),
    (Disturbance(0.5, "kick"), "kick(0.5)"),
    (Disturbance(2.0, "impulse", start_step=100, duration=10), "impulse(2, k=100..109)"),
    (Disturbance(2.0, "impulse", start_step=3, duration=5, decay=0.5),
     "impulse(2, k=3..7, decay=0.5)"),
    (Disturbance(-3.0, "step", start_step=50), "step(-3, k>=50)"),
    (Disturbance(1.0, "uniform"), "uniform(1, [-1, 1])"),
    (Disturbance(2.0, "periodic", frequency=0.5), "periodic(2, f=0.5)"),
    (Disturbance(2.0, "periodic", frequency=0.5, phase=1.0), "periodic(2, f=0.5, phase=1)"),
    (Disturbance(3.0, "step", states=("vx",)), "step(3, k>=0) on vx"),
    (Disturbance(1.0, velocity_index=(2, 3)), "velocity_variance(1) on 2,3"),
])
def test_label_names_the_disturbance(d, label):
    assert d.label == label


@pytest.mark.parametrize(("kwargs", "field"), [
    ({"model": "gaussian"}, "model"),
    ({"model": "uniform", "level": -1.0}, "level"),
    ({"model": "velocity_variance", "level": -1.0}, "level"),
    ({"model": "impulse", "start_step": -1}, "start_step"),
    ({"model": "step", "start_step": 2.0}, "start_step"),
    ({"model": "impulse", "duration": 0}, "duration"),
    ({"model": "impulse", "decay": 0.0}, "decay"),
    ({"model": "impulse", "decay": 1.5}, "decay"),
    ({"model": "uniform", "low": 1.0, "high": 0.5}, "high"),
    ({"model": "uniform", "low": np.nan}, "low"),
    ({"model": "periodic", "frequency": 0.0}, "frequency"),
    ({"model": "periodic", "phase": np.inf}, "phase"),
    # validated whatever the model
    ({"model": "step", "duration": 0}, "duration"),
    ({"model": "kick", "frequency": -1.0}, "frequency"),
])
def test_bad_fields_are_named(kwargs, field):
    kwargs = {"level": 1.0, **kwargs}
    with pytest.raises(ValueError, match=rf"^Disturbance\.{field} = "):
        Disturbance(**kwargs)


@pytest.mark.parametrize(("model", "unread"), [
    ("step", {"duration": 20, "decay": 0.5, "frequency": 3.0}),
    ("impulse", {"frequency": 2.0, "low": 0.0, "phase": 1.0}),
    ("kick", {"start_step": 5, "duration": 3, "low": 0.0, "high": 3.0}),
    ("velocity_variance", {"start_step": 5, "frequency": 2.0}),
    ("periodic", {"start_step": 7, "decay": 0.5, "duration": 4}),
    ("uniform", {"start_step": 7, "frequency": 2.0}),
])
def test_fields_a_model_does_not_read_change_nothing(model, unread):
    base = {"start_step": 3, "duration": 2} if model == "impulse" else {}
    d0 = Disturbance(1.5, model, velocity_index=(1,), **base)
    d1 = Disturbance(1.5, model, velocity_index=(1,), **base, **unread)
    r0, r1 = np.random.default_rng(4), np.random.default_rng(4)
    for k in range(12):
        np.testing.assert_array_equal(d0.sample(2, DT, r0, k=k), d1.sample(2, DT, r1, k=k))
    assert d0.label == d1.label


def test_bad_step_index_is_named():
    with pytest.raises(ValueError, match=r"^k = -1 is invalid"):
        Disturbance(1.0, "step", velocity_index=(0,)).sample(2, DT, np.random.default_rng(0),
                                                            k=-1)


def test_signed_levels_on_an_own_model_still_need_named_states():
    x, u = ca.SX.sym("x", 1), ca.SX.sym("u", 1)
    plant = Model.from_expressions("scalar", x, u, x + 0.1 * u, dt=0.1, u_min=[-1], u_max=[1])
    with pytest.raises(ValueError, match=r"^Disturbance\.states = None"):
        Disturbance(-1.0, "step").indices(plant)


# ---------------------------------------------------------------------------------------------
# closed_loop: stop at the goal


def test_stops_at_the_first_step_within_the_goal_distance():
    plant = double_integrator(u_limit=5.0)
    goal, a, r = np.array([1.0, 0.0, 0.0, 0.0]), 1.0, 0.05
    # Euler from rest under constant a: p_k = dt^2 a k (k - 1) / 2
    k = np.arange(1, 200)
    first = int(k[np.abs(DT**2 * a * k * (k - 1) / 2 - 1.0) <= r][0])
    assert first == 70
    ep = closed_loop(_Hold([a, 0.0], goal=goal), plant, np.zeros(4), 200,
                     np.random.default_rng(0), np.random.default_rng(1), stop_at_goal=r)
    assert ep.reached_goal and ep.goal_step == first and len(ep.X) == first + 1
    assert len(ep.U) == first and not ep.crashed
    assert np.linalg.norm(ep.X[-1, :2] - goal[:2]) <= r < np.linalg.norm(ep.X[-2, :2] - goal[:2])
    # the goal as a position, given explicitly, to a controller without one: the same stop
    ep2 = closed_loop(_Hold([a, 0.0]), plant, np.zeros(4), 200, np.random.default_rng(0),
                      np.random.default_rng(1), stop_at_goal=r, goal=[1.0, 0.0])
    assert ep2.goal_step == first
    np.testing.assert_array_equal(ep2.X, ep.X)


def test_without_stop_at_goal_all_steps_run():
    plant = single_integrator(u_limit=5.0)
    ctrl = _Hold([1.0, 0.0], goal=[1.0, 0.0])
    ep = closed_loop(ctrl, plant, np.zeros(2), 100, np.random.default_rng(0),
                     np.random.default_rng(1))
    assert len(ep.X) == 101 and not ep.reached_goal and ep.goal_step is None
    ep = closed_loop(ctrl, plant, np.zeros(2), 100, np.random.default_rng(0),
                     np.random.default_rng(1), stop_at_goal=0.11)
    assert ep.reached_goal and ep.goal_step == 45  # |0.02 k - 1| <= 0.11 first at k = 45


def test_a_crash_before_the_goal_is_a_crash():
    plant = single_integrator(obstacles=(Circle((0.5, 0.0), 0.11),), u_limit=5.0)
    ep = closed_loop(_Hold([1.0, 0.0], goal=[1.0, 0.0]), plant, np.zeros(2), 100,
                     np.random.default_rng(0), np.random.default_rng(1), stop_at_goal=0.11)
    assert ep.crashed and ep.crash_step == 20 and not ep.reached_goal and ep.goal_step is None
    # the goal at the obstacle's centre: the crash wins on the step (20) that also reaches it
    ep = closed_loop(_Hold([1.0, 0.0], goal=[0.5, 0.0]), plant, np.zeros(2), 100,
                     np.random.default_rng(0), np.random.default_rng(1), stop_at_goal=0.11)
    assert ep.crashed and ep.crash_step == 20 and not ep.reached_goal


def test_stop_at_goal_with_a_distance_of_its_own():
    """``goal_distance`` measures the distance itself, so a plant without a position stops at
    its goal too (x_k = 0.1 k is within 0.05 of 1 first at k = 10); a goal given besides it, or
    the distance without ``stop_at_goal``, is refused."""
    plant = _scalar()
    assert plant.position is None

    def run(**kw):
        return closed_loop(_Hold([1.0]), plant, np.zeros(1), 100, np.random.default_rng(0),
                           np.random.default_rng(1), **kw)

    ep = run(stop_at_goal=0.05, goal_distance=lambda x: abs(float(x[0]) - 1.0))
    assert ep.reached_goal and ep.goal_step == 10 and len(ep.U) == 10 and not ep.crashed
    with pytest.raises(ValueError, match=r"^goal = .* is invalid: is not read with "
                       "goal_distance"):
        run(stop_at_goal=0.05, goal=[1.0], goal_distance=lambda x: 0.0)
    with pytest.raises(ValueError, match=r"^goal_distance = .* given with stop_at_goal"):
        run(goal_distance=lambda x: 0.0)


def _scalar():
    x, u = ca.SX.sym("x", 1), ca.SX.sym("u", 1)
    return Model.from_expressions("scalar", x, u, x + 0.1 * u, dt=0.1, u_min=[-1], u_max=[1])


@pytest.mark.parametrize(("make", "message"), [
    (lambda: closed_loop(_Hold([0.0], goal=[1.0]), _scalar(), [0.0], 5,
                         np.random.default_rng(0), np.random.default_rng(1), stop_at_goal=0.1),
     r"^stop_at_goal = 0.1 is invalid: the plant scalar has no position"),
    (lambda: closed_loop(_Hold([0.0, 0.0]), single_integrator(), np.zeros(2), 5,
                         np.random.default_rng(0), np.random.default_rng(1), stop_at_goal=0.1),
     r"^goal = None is invalid: _Hold has no goal attribute"),
    (lambda: closed_loop(_Hold([0.0, 0.0]), double_integrator(), np.zeros(4), 5,
                         np.random.default_rng(0), np.random.default_rng(1), stop_at_goal=0.1,
                         goal=[1.0, 2.0, 3.0]),
     r"^goal = .* is invalid: must be a state of 4"),
    (lambda: closed_loop(_Hold([0.0, 0.0], goal=[1.0, 0.0]), single_integrator(), np.zeros(2),
                         5, np.random.default_rng(0), np.random.default_rng(1), stop_at_goal=0.0),
     r"^stop_at_goal = 0\.? is invalid: must be a finite number > 0"),
    (lambda: closed_loop(_Hold([0.0, 0.0]), single_integrator(), np.zeros(2), 5,
                         np.random.default_rng(0), np.random.default_rng(1), goal=[1.0, 0.0]),
     r"^goal = .* is invalid: is only read with stop_at_goal"),
])
def test_bad_goal_settings_are_named(make, message):
    with pytest.raises(ValueError, match=message):
        make()

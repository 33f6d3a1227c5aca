"""Obstacles as run-time inputs: one compiled problem serves every scene, and a scene given at
run time gives exactly what a model built with those circles gives (the oracle)."""

from __future__ import annotations

import numpy as np
import pytest

import workbench as wb
from workbench.problem.obstacles import INERT_CENTER, scene_circles
from workbench.sampling.kernels.constants import SamplerConstants
from workbench.sampling.sampler import Sampler

MAP = (wb.Circle((1.0, 1.2), 0.4), wb.Circle((2.2, 0.6), 0.3))
MOVED = (wb.Circle((1.3, 0.9), 0.5), wb.Circle((2.0, 1.6), 0.25))


def test_scene_vector_fills_inert_slots_and_rejects_what_does_not_fit():
    v = wb.scene_vector(MAP, 4)
    assert v.shape == (12,)
    np.testing.assert_array_equal(v[:6], [1.0, 1.2, 0.4, 2.2, 0.6, 0.3])
    np.testing.assert_array_equal(v[6:], [INERT_CENTER, INERT_CENTER, 0.0] * 2)
    assert scene_circles(v) == MAP
    np.testing.assert_array_equal(wb.scene_vector(np.array([[1.0, 1.2, 0.4]]), 1), [1, 1.2, .4])
    np.testing.assert_array_equal(wb.scene_vector([(1.0, 1.2, 0.4)], 1), [1.0, 1.2, 0.4])
    with pytest.raises(ValueError, match=r"scene.*at most 1 \(scene_capacity\)"):
        wb.scene_vector(MAP, 1)
    with pytest.raises(ValueError, match=r"slot 0.*negative radius"):
        wb.scene_vector(np.array([0.0, 0.0, -1.0]), 1)
    with pytest.raises(ValueError, match=r"scene\[0\]"):
        wb.scene_vector(["circle"], 2)
    model = wb.double_integrator(obstacles=MAP)
    with pytest.raises(ValueError, match=r"scene.*shape"):
        model.scene_vector(np.zeros(5))
    with pytest.raises(ValueError, match=r"scene_capacity"):
        wb.double_integrator(obstacles=MAP, scene_capacity=1)
    with pytest.raises(ValueError, match=r"baked obstacles"):
        wb.double_integrator(obstacles=MAP, scene_capacity=3, runtime_obstacles=False)


def test_margins_in_a_given_scene_equal_a_model_built_with_it(rng):
    model = wb.double_integrator(obstacles=MAP)
    baked = wb.double_integrator(obstacles=MOVED, runtime_obstacles=False)
    assert model.n_scene == 6 and baked.n_scene == 0
    for _ in range(10):
        x = rng.uniform(-1, 3, 4)
        np.testing.assert_array_equal(model.margins(x, MOVED), baked.margins(x))
        emb, emb_b = wb.embed_barrier(model), wb.embed_barrier(baked)
        np.testing.assert_array_equal(emb.lift(x, MOVED), emb_b.lift(x))


def test_inert_slots_change_nothing_that_matters(rng):
    """A model with room for 5 circles holding 2 equals the 2-slot model: margins exactly,
    the barrier state to 1e-12 relative (an inert slot adds below 1e-16)."""
    small = wb.embed_barrier(wb.double_integrator(obstacles=MAP))
    big = wb.embed_barrier(wb.double_integrator(obstacles=MAP, scene_capacity=5))
    for _ in range(10):
        x = rng.uniform(-1, 3, 4)
        np.testing.assert_array_equal(big.margins(x)[:2], small.margins(x))
        assert np.all(big.margins(x)[2:] > 1e15)
        np.testing.assert_allclose(big.lift(x), small.lift(x), rtol=1e-12, atol=0)


@pytest.mark.parametrize("backend", ["compiled", "numpy"])
def test_ilqg_in_a_run_time_scene_equals_ilqg_on_the_moved_model(backend):
    """BaS-iLQG takes the scene as a parameter: solving the map's problem in the moved scene
    gives the same iterates, bit for bit, as solving a problem built on the moved circles."""
    weights = wb.TrackingWeights(Q=(1, 1, 0.1, 0.1), R=(0.1, 0.1), S=(10, 10, 1, 1))
    model = wb.embed_barrier(wb.double_integrator(obstacles=MAP))
    oracle = wb.embed_barrier(wb.double_integrator(obstacles=MOVED, runtime_obstacles=False))
    x0, target, T = np.array([0.0, 0.0, 0.0, 0.0]), np.array([3.0, 2.0, 0.0, 0.0]), 30
    x_ref = np.linspace(x0, target, T + 1)
    opts = wb.ILQGOptions(backend=backend, max_iter=15)
    res = {}
    for name, m, scene in (("runtime", model, MOVED), ("oracle", oracle, None)):
        problem = wb.tracking_problem(m, weights)
        P = wb.tracking_params(problem, x_ref, target) if scene is None else None
        if P is None:  # the beta reference of the moved scene (the oracle's own)
            P = wb.tracking_params(wb.tracking_problem(oracle, weights), x_ref, target)
        res[name] = wb.ilqg(problem, x0, np.zeros((T, 2)), P, opts, scene=scene)
    a, b = res["runtime"], res["oracle"]
    assert a.iterations == b.iterations > 1
    np.testing.assert_array_equal(a.X, b.X)
    np.testing.assert_array_equal(a.K, b.K)
    # and the scene matters: the map's own obstacles give another solution
    problem = wb.tracking_problem(model, weights)
    own = wb.ilqg(problem, x0, np.zeros((T, 2)), wb.tracking_params(problem, x_ref, target), opts)
    assert not np.allclose(own.X, a.X)


def test_al_ilqg_and_the_ecbf_filter_take_the_scene():
    model = wb.double_integrator(obstacles=MAP)
    oracle = wb.double_integrator(obstacles=MOVED, runtime_obstacles=False)
    cost = wb.quadratic_tracking(model, Q=[1, 1, 0.1, 0.1], R=[0.1, 0.1], S=[10, 10, 1, 1])
    cost_o = wb.quadratic_tracking(oracle, Q=[1, 1, 0.1, 0.1], R=[0.1, 0.1], S=[10, 10, 1, 1])
    T, x0 = 25, np.zeros(4)
    P = cost.params(T, x_ref=np.tile([3.0, 2.0, 0.0, 0.0], (T + 1, 1)))
    opts = wb.ALOptions(max_outer=3)
    a = wb.al_ilqg(wb.al_problem(model, cost), x0, np.zeros((T, 2)), P, opts, scene=MOVED)
    b = wb.al_ilqg(wb.al_problem(oracle, cost_o), x0, np.zeros((T, 2)), P, opts)
    np.testing.assert_allclose(a.X, b.X, rtol=1e-12, atol=1e-12)
    filt, filt_o = wb.ECBFFilter(model), wb.ECBFFilter(oracle)
    filt.set_scene(MOVED)
    for x, u in (([0.5, 0.5, 1.0, 1.0], [5.0, 5.0]), ([1.6, 0.5, 2.0, -0.5], [-3.0, 8.0])):
        np.testing.assert_array_equal(filt.rows(x)[1], filt_o.rows(x)[1])
        np.testing.assert_allclose(filt(x, u).u, filt_o(x, u).u, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("backend", ["compiled", "numpy"])
def test_sampler_in_a_run_time_scene_equals_a_sampler_built_on_it(backend):
    """The kernels (and the NumPy twin) read the scene like the goal: batches in a new scene
    equal, bit for bit, those of a problem whose model was built with those circles baked in,
    and a scene change builds nothing."""
    sp = wb.navigation_costs(wb.embed_barrier(wb.double_integrator(obstacles=MAP)))
    sp_o = wb.navigation_costs(wb.embed_barrier(
        wb.double_integrator(obstacles=MOVED, runtime_obstacles=False)))
    s, s_o = Sampler(sp, backend), Sampler(sp_o, backend)
    if backend == "compiled" and s.backend != "compiled":
        pytest.skip("no C compiler")
    goal = np.array([3.0, 2.0, 0.0, 0.0])
    rng = np.random.default_rng(4)
    U, K = rng.normal(0, 2, (20, 2)), rng.normal(0, 1, (20, 2, 5))
    kw = dict(sigma=np.array([3.0, 3.0]), lam=2.0, nu_mix=0.0, u_min=sp.model.u_min,
              u_max=sp.model.u_max, crash_cost=1e6)
    c = SamplerConstants(**kw, p=sp.model.lift(goal, MOVED), alpha=50.0,
                         scene=sp.model.scene_vector(MOVED))
    c_o = SamplerConstants(**kw, p=sp_o.model.lift(goal), alpha=50.0)
    start = [0.4, 0.5, 1.0, 0.5]  # heading for the moved circles: some samples crash
    x0, x0_o = sp.model.lift(start, MOVED), sp_o.model.lift(start)
    np.testing.assert_array_equal(x0, x0_o)
    before = wb.build_counts()
    a, b = s.sais(x0, x0, U, K, 37, c, 11), s_o.sais(x0, x0, U, K, 37, c_o, 11)
    for f in vars(a):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)
    assert backend == "numpy" or 0 < a.crashed_real.sum() < 37  # the scene is in play
    a, b = s.mppi(x0, U, 37, c, 12), s_o.mppi(x0, U, 37, c_o, 12)
    np.testing.assert_array_equal(a.S, b.S)
    assert wb.build_counts() == before
    # an empty scene in the constants means the model's own; a wrong size is an error
    own = s.mppi(x0, U, 37, SamplerConstants(**kw, p=c.p), 12)
    assert not np.array_equal(own.S, a.S)
    with pytest.raises(ValueError, match=r"SamplerConstants.scene"):
        s.mppi(x0, U, 37, SamplerConstants(**kw, p=c.p, scene=np.zeros(3)), 12)


def test_controllers_set_scene_and_relift_the_goal():
    sp = wb.navigation_costs(wb.embed_barrier(wb.double_integrator(obstacles=MAP)))
    goal = np.array([3.0, 2.0, 0.0, 0.0])
    ctrl = wb.MPPI(sp, goal, wb.MPPIConfig(n_samples=16, horizon=10))
    np.testing.assert_array_equal(ctrl.consts.p, sp.model.lift(goal))
    ctrl.set_scene(MOVED)
    np.testing.assert_array_equal(ctrl.scene, sp.model.scene_vector(MOVED))
    np.testing.assert_array_equal(ctrl.consts.p, sp.model.lift(goal, MOVED))
    with pytest.raises(ValueError, match=r"at most 2"):
        ctrl.set_scene((*MAP, *MOVED))


class Still:
    """Applies zero control: the plant stays where it is."""

    def initial_state(self, x0):
        return None

    def step(self, state, x, rng):
        return None, np.zeros(2), None


def test_closed_loop_checks_crashes_against_the_moving_scene():
    """A circle of radius 0.5 moves at 0.5 m per step towards a plant resting at the origin
    from x = 3: it touches the plant (margin <= 0) after step k with 3 - 0.5 (k + 1) <= 0.5,
    i.e. the episode crashes at step 4 (state index 5)."""
    plant = wb.single_integrator(obstacles=(wb.Circle((3.0, 0.0), 0.5),))

    def scene(k):
        return [(3.0 - 0.5 * k, 0.0, 0.5)]

    rng = np.random.default_rng
    ep = wb.closed_loop(Still(), plant, np.zeros(2), 20, rng(0), rng(1), scene=scene)
    assert ep.crashed and ep.crash_step == 5 and len(ep.U) == 5
    np.testing.assert_array_equal(ep.scenes[:, 0], [3.0 - 0.5 * k for k in range(6)])
    # the same scenes as a list, and the static scene (never reaches the plant)
    ep2 = wb.closed_loop(Still(), plant, np.zeros(2), 20, rng(0), rng(1),
                         scene=wb.scene_sequence([scene(k) for k in range(30)]))
    assert ep2.crash_step == 5
    ep3 = wb.closed_loop(Still(), plant, np.zeros(2), 20, rng(0), rng(1))
    assert not ep3.crashed and ep3.min_margin == pytest.approx(9.0 - 0.25)
    with pytest.raises(ValueError, match=r"scene\(0\)"):
        wb.closed_loop(Still(), plant, np.zeros(2), 5, rng(0), rng(1), scene=lambda k: MAP)
    baked = wb.single_integrator(obstacles=MAP, runtime_obstacles=False)
    with pytest.raises(ValueError, match=r"no run-time scene"):
        wb.closed_loop(Still(), baked, np.zeros(2), 5, rng(0), rng(1), scene=MAP)

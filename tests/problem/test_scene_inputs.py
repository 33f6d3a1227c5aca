"""Every place a scene is accepted refuses a malformed one with an error naming it, and an unused
slot is inert: never a point obstacle at its centre (radius 0 is not an obstacle, and a scene
vector only takes it in the dedicated unused slot)."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import workbench as wb
from workbench.problem.obstacles import INERT_CENTER, scene_symbol, slot_margins
from workbench.sampling.kernels.constants import SamplerConstants
from workbench.sampling.sampler import Sampler

A = wb.Circle((2.0, 2.0), 0.5)
INERT_SLOT = (INERT_CENTER, INERT_CENTER, 0.0)  # an unused slot
ZEROS = np.zeros(6)  # two slots of radius 0 at the origin: formerly point obstacles there


class Still:
    """Applies zero control."""

    def initial_state(self, x0):
        return None

    def step(self, state, x, rng):
        return None, np.zeros(2), None


def _run(scene, steps=4):
    plant = wb.single_integrator(obstacles=(A,), scene_capacity=2)
    rng = np.random.default_rng
    return wb.closed_loop(Still(), plant, np.array([0.1, 0.0]), steps, rng(0), rng(1),
                          scene=scene)


def test_a_moving_scene_that_returns_none_is_refused_naming_the_step():
    """Before: the episode went on in the plant's own obstacles from step 2 on."""
    with pytest.raises(ValueError, match=r"scene\(2\) = None is invalid: a moving scene must "
                                         r"return the scene of every step"):
        _run(lambda k: None if k == 2 else [(3.0, 0.0, 0.5)])


@pytest.mark.parametrize(("returned", "says"), [
    (A, r"scene\(0\) = Circle.* one Circle is not a scene.*\[circle\]"),
    (np.array([[3.0, 0.0]]), r"scene\(0\) = 'an array of shape \(1, 2\)'.*shape \(n, 3\)"),
    (np.zeros((2, 3, 1)), r"scene\(0\) = 'an array of shape \(2, 3, 1\)'.*shape \(n, 3\)"),
    (5, r"scene\(0\) = 5 is invalid: expected a sequence of Circle"),
    ("abc", r"scene\(0\) = 'abc' is invalid: expected a sequence of Circle"),
    ([(3.0, 0.0)], r"scene\(0\)\[0\] = .* expected a Circle or an \(x, y, radius\) triple"),
    ([(np.nan, 0.0, 0.5)], r"scene\(0\)\[0\] = .*finite"),
    ([(3.0, 0.0, -0.5)], r"scene\(0\)\[0\] = .*radius \(third entry\) must be > 0"),
    ([(3.0, 0.0, 0.0)], r"scene\(0\)\[0\] = .*radius \(third entry\) must be > 0"),
    ([(3.0, 0.0, 0.5)] * 3, r"scene\(0\) = '3 circles'.*at most 2 \(scene_capacity\)"),
    (np.array([3.0, 0.0, np.inf, *INERT_SLOT]), r"scene\(0\) = .*finite"),
    (ZEROS, r"scene\(0\)\[0:3\] \(slot 0\) = .*radius 0 at centre \(0, 0\) would be a point "
            r"obstacle there.*unused slot, exactly \(1e\+08, 1e\+08, 0\)"),
    (np.array([3.0, 0.0, 0.5, 1.0, 1.0, -1.0]), r"scene\(0\)\[3:6\] \(slot 1\).*negative"),
])
def test_a_malformed_moving_scene_is_a_value_error_naming_the_step_and_the_value(returned,
                                                                                 says):
    """Before: a bare Circle or an int raised TypeError, a two-column array IndexError, and a
    radius-0 or all-zero vector ran as point obstacles."""
    with pytest.raises(ValueError, match=says):
        _run(lambda k: returned)


def test_an_all_zero_scene_vector_is_refused_wherever_a_scene_is_taken():
    """Radius 0 outside the unused slot is a point obstacle in every margin expression: no entry
    point takes it (before: each did, and a plant passing the origin crashed or met a barrier
    there)."""
    model = wb.double_integrator(obstacles=(A,), scene_capacity=2)
    emb = wb.embed_barrier(model)
    sp = wb.navigation_costs(emb)
    goal = np.array([3.0, 3.0, 0.0, 0.0])
    entries = {
        "scene_vector": lambda: wb.scene_vector(ZEROS, 2),
        "Model.scene_vector": lambda: model.scene_vector(ZEROS),
        "Model.margins": lambda: model.margins(np.zeros(4) + 0.1, ZEROS),
        "Model.lift": lambda: emb.lift(np.zeros(4) + 0.1, ZEROS),
        "ECBFFilter.set_scene": lambda: wb.ECBFFilter(model).set_scene(ZEROS),
        "MPPI.set_scene": lambda: wb.MPPI(sp, goal, wb.MPPIConfig(
            n_samples=8, horizon=5, backend="numpy")).set_scene(ZEROS),
        "closed_loop(scene=...)": lambda: wb.closed_loop(
            Still(), wb.single_integrator(obstacles=(A,), scene_capacity=2), [0.1, 0.0], 3,
            np.random.default_rng(0), np.random.default_rng(1), scene=ZEROS),
    }
    for name, call in entries.items():
        with pytest.raises(ValueError, match=r"\(slot 0\).*point obstacle"):
            call()
            pytest.fail(f"{name} took an all-zero scene vector")
    # the unused slot itself, and circles, pass
    np.testing.assert_array_equal(model.scene_vector([A]), [2.0, 2.0, 0.5, *INERT_SLOT])
    np.testing.assert_array_equal(model.scene_vector(np.array([2.0, 2.0, 0.5, *INERT_SLOT])),
                                  [2.0, 2.0, 0.5, *INERT_SLOT])


@pytest.mark.parametrize("backend", ["compiled", "numpy"])
def test_the_sampler_refuses_a_radius_0_slot_in_its_constants(backend):
    """SamplerConstants.scene goes straight to the kernels and the twin: it is checked like a
    scene (before: an all-zero vector ran as two point obstacles at the origin)."""
    sp = wb.navigation_costs(wb.embed_barrier(wb.double_integrator(obstacles=(A,),
                                                                   scene_capacity=2)))
    s = Sampler(sp, backend)
    kw = dict(sigma=np.array([3.0, 3.0]), lam=2.0, nu_mix=0.0, u_min=sp.model.u_min,
              u_max=sp.model.u_max, crash_cost=1e6, p=sp.model.lift(np.array([3.0, 3, 0, 0])))
    x0 = sp.model.lift([-0.5, -0.5, 1.0, 1.0])
    U = np.zeros((10, 2))
    with pytest.raises(ValueError, match=r"SamplerConstants.scene\[0:3\] \(slot 0\)"):
        s.mppi(x0, U, 8, SamplerConstants(**kw, scene=ZEROS), 1)
    with pytest.raises(ValueError, match=r"SamplerConstants.scene.*finite"):
        s.mppi(x0, U, 8, SamplerConstants(**kw, scene=np.full(6, np.nan)), 1)
    s.mppi(x0, U, 8, SamplerConstants(**kw, scene=sp.model.scene_vector([A])), 1)


@pytest.mark.parametrize("backend", ["compiled", "numpy"])
def test_an_unused_slot_acts_nowhere_in_the_kernels_and_the_twin(backend):
    """Samples from (-0.5, -0.5) sweep through the origin (where a zero-filled slot put a point
    obstacle) towards a circle B: a model with room for two circles holding B gives the costs of
    the one-slot model holding B (relative 1e-12 per sample: the unused slot adds below 1e-16 to
    the barrier) and the same crash flags."""
    B = wb.Circle((0.9, 0.9), 0.4)
    one = wb.navigation_costs(wb.embed_barrier(wb.double_integrator(obstacles=(B,))))
    two = wb.navigation_costs(wb.embed_barrier(wb.double_integrator(obstacles=(B,),
                                                                    scene_capacity=2)))
    rng = np.random.default_rng(7)
    U = rng.normal(0.0, 2.0, (50, 2))
    K = rng.normal(0.0, 1.0, (50, 2, 5))
    out = {}
    for name, sp in (("one", one), ("two", two)):
        s = Sampler(sp, backend)
        if backend == "compiled" and s.backend != "compiled":
            pytest.skip("no C compiler")
        goal = sp.model.lift(np.array([3.0, 3.0, 0.0, 0.0]))
        c = SamplerConstants(sigma=np.array([3.0, 3.0]), lam=2.0, nu_mix=0.0,
                             u_min=sp.model.u_min, u_max=sp.model.u_max, crash_cost=1e6,
                             p=goal, alpha=50.0)
        x0 = sp.model.lift([-0.5, -0.5, 1.5, 1.5])
        out[name] = (s.sais(x0, x0, U, K, 64, c, 3), s.mppi(x0, U, 64, c, 4))
    (sais1, mppi1), (sais2, mppi2) = out["one"], out["two"]
    np.testing.assert_allclose(mppi2.S, mppi1.S, rtol=1e-12, atol=0)
    for f in ("S_nom", "S_real", "S_hat"):
        np.testing.assert_allclose(getattr(sais2, f), getattr(sais1, f), rtol=1e-12, atol=0,
                                   err_msg=f)
    for f in ("crashed_real", "crashed_nom"):
        np.testing.assert_array_equal(getattr(sais2, f), getattr(sais1, f), err_msg=f)
    assert 0 < sais1.crashed_real.sum() < 64  # B is in play


def test_a_user_circle_scene_without_a_value_starts_with_every_slot_unused():
    """Model.from_expressions with scene_capacity and no scene_value: every slot is the unused
    slot (before: all zeros, a point obstacle at the origin in every slot), and a given value
    is checked as a circle scene."""
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 2)
    s = scene_symbol(2)
    kw = dict(dt=0.1, u_min=[-1, -1], u_max=[1, 1], h=slot_margins(x, s), scene=s,
              scene_capacity=2, position=(0, 1))
    m = wb.Model.from_expressions("mine", x, u, x + 0.1 * u, **kw)
    np.testing.assert_array_equal(m.scene_value, np.tile(INERT_SLOT, 2))
    assert np.all(m.margins(np.array([1e-3, 0.0])) > 1e15)
    m2 = wb.Model.from_expressions("mine", x, u, x + 0.1 * u, scene_value=[A], **kw)
    np.testing.assert_array_equal(m2.scene_value, [2.0, 2.0, 0.5, *INERT_SLOT])
    with pytest.raises(ValueError, match=r"scene_value = .*\(slot 0\).*point obstacle"):
        wb.Model.from_expressions("mine", x, u, x + 0.1 * u, scene_value=ZEROS, **kw)


@pytest.mark.parametrize("circle", [(1.0, 1.0, 0.0), (1.0, 1.0, -1.0)])
def test_a_circle_scene_names_the_triple_whose_radius_is_not_positive(circle):
    """Before: the error named Circle.radius, not which entry of the scene held it."""
    with pytest.raises(ValueError, match=r"^CircleScene\.circles\[1\] = .*radius \(third entry\) "
                                         r"must be > 0"):
        wb.CircleScene((A, circle), start=(0.0, 0.0), goal=(4.0, 0.0))


@pytest.mark.parametrize("scenes", [None, 5, "abc"])
def test_scene_sequence_refuses_what_is_not_a_list_of_scenes(scenes):
    """Before: None and 5 raised a bare TypeError."""
    with pytest.raises(ValueError, match=r"^scenes = .*must be a list of scenes"):
        wb.scene_sequence(scenes)

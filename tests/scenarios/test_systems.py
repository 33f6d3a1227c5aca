"""Every system with every safe-sampling method; the ground robots reach a goal; the double
integrator's set-up is unchanged; goal costs wrap headings; bad names and options name the
field."""

from __future__ import annotations

import dataclasses

import casadi as ca
import numpy as np
import pytest
from method_runs import check_method_runs  # tests/scenarios/method_runs.py

import workbench as wb
from workbench.problem.barrier import BarrierOptions, embed_barrier
from workbench.problem.models import double_integrator
from workbench.sampling.problem import goal_costs, navigation_costs
from workbench.scenarios import SYSTEMS, CircleScene, NavigationScene, System, system
from workbench.scenarios.methods import names
from workbench.scenarios.navigation import navigation_setup
from workbench.sim import Disturbance, closed_loop

SMALL = CircleScene(((5.0, 5.0, 1.0), (3.0, 7.0, 0.8)), start=(1.0, 1.0), goal=(9.0, 9.0))


@pytest.fixture(scope="module")
def navs():
    out = {}
    for name, s in SYSTEMS.items():
        cfg = wb.MPPIConfig(n_samples=64, horizon=20, sigma=s.sigma, lam=s.lam)
        out[name] = navigation_setup(s.scaled(SMALL), system=name, mppi=cfg)
    return out


@pytest.mark.parametrize("method", names())
@pytest.mark.parametrize("name", list(SYSTEMS))
def test_every_method_runs_on_every_system(navs, name, method):
    nav, s = navs[name], SYSTEMS[name]
    assert nav.system is s and nav.plant.nx == len(nav.x0) == len(nav.goal)
    check_method_runs(nav, method, steps=3, level=1.0 * s.level_scale, states=s.disturbed)


@pytest.mark.parametrize("name", ["unicycle", "bicycle"])
def test_ground_robots_reach_the_goal_of_a_small_map_undisturbed(name):
    """The hand-tuned sampler values (N = 256 here) go around a circle on the straight line."""
    scene = CircleScene(((2.5, 2.5, 0.7),), start=(0.5, 0.5), goal=(4.5, 4.5))
    s = SYSTEMS[name]
    nav = navigation_setup(scene, system=name,
                           mppi=wb.MPPIConfig(n_samples=256, sigma=s.sigma, lam=s.lam))
    ep = closed_loop(nav.controller("bas_mppi"), nav.plant, nav.x0, 400,
                     np.random.default_rng(0), np.random.default_rng(1), keep_infos=False)
    d = np.linalg.norm(ep.X[:, :2] - nav.goal[:2], axis=1)
    assert not ep.crashed
    assert np.flatnonzero(d < 0.1).size and d[-1] < 0.2  # measured: see the report


def test_double_integrator_setup_is_the_navigation_studys():
    nav = navigation_setup()
    scene = NavigationScene()
    plant = double_integrator(obstacles=scene.obstacles(), u_limit=scene.u_limit, dt=scene.dt)
    old = navigation_costs(embed_barrier(plant, BarrierOptions()), q_beta=0.01)
    assert nav.problem.fingerprint() == old.fingerprint()
    assert nav.physical_problem().fingerprint() == navigation_costs(
        plant, S=(10.0, 10.0, 1.0, 1.0), q_beta=0.0).fingerprint()
    np.testing.assert_array_equal(nav.x0, [0.5, 0.5, 0.0, 0.0])
    np.testing.assert_array_equal(nav.goal, [9.5, 9.5, 0.0, 0.0])
    assert nav.mppi == wb.MPPIConfig(sigma=(5.0, 5.0), lam=10.0)
    assert nav.system is system("double_integrator") and nav.scene == scene
    assert navigation_setup(q_beta=0.5).problem.weights["q_beta"] == 0.5


def test_goal_costs_wrap_headings_and_weigh_barrier_states():
    s = system("unicycle")
    nav = navigation_setup(s.scaled(SMALL), system=s)
    f = nav.problem.functions()
    g = nav.problem.model.lift(nav.goal)
    x = nav.problem.model.lift(np.array([2.0, 3.0, 0.4]))
    turned = x + np.array([0.0, 0.0, 2 * np.pi, 0.0])
    for fn in ("q", "phi"):
        a, b = float(f[fn](x, g)), float(f[fn](turned, g))
        assert abs(a - b) <= 1e-12 * abs(a)
    # near the goal the heading term is Q_theta e^2 to second order
    e = 1e-3
    near = g + np.array([0.0, 0.0, e, 0.0])
    assert float(f["q"](near, g)) == pytest.approx(s.Q[2] * e**2, rel=1e-6)
    w = nav.problem.weights
    np.testing.assert_array_equal(w["S"], [*s.S, 1.0])  # barrier state weighted s_beta = 1
    np.testing.assert_array_equal(w["angles"], [2])
    phys = nav.physical_problem()
    assert phys.nx == 3 and phys.model.nh == nav.plant.nh
    np.testing.assert_array_equal(phys.weights["Q"], s.Q)
    assert float(phys.functions()["q"](x[:3], g[:3])) == pytest.approx(
        float(f["q"](x, g)) - s.q_beta * (x[3] - g[3]) ** 2, rel=1e-12)
    plain = goal_costs(nav.plant, Q=(1, 1, 1), S=(1, 1, 1), angles=())
    y = np.array([0.0, 0.0, 0.5])
    assert float(plain.functions()["q"](y, np.zeros(3))) == pytest.approx(0.25, rel=1e-15)
    with pytest.raises(ValueError, match=r"^Q = "):
        goal_costs(nav.plant, Q=(1, 1), S=(1, 1, 1))
    with pytest.raises(ValueError, match=r"^S = "):
        goal_costs(nav.plant, Q=(1, 1, 1), S=(1, 1))
    with pytest.raises(ValueError, match=r"^angles = "):
        goal_costs(nav.plant, Q=(1, 1, 1), S=(1, 1, 1), angles=(3,))


def test_quadrotor_map_fits_its_limits_and_its_backup_hovers():
    s = system("planar_quadrotor")
    nav = navigation_setup(system=s)  # the paper's map, scaled
    assert nav.plant.position == (0, 2) and nav.plant.control_names == ("dT1", "dT2")
    for c in nav.scene.obstacles():
        assert 0 <= c.center[0] - c.radius and c.center[0] + c.radius <= 1.8
    for x in (nav.x0, nav.goal):
        assert nav.plant.margins(x).min() > 0
    np.testing.assert_allclose(nav.x0, [0.09, 0, 0.09, 0, 0, 0])
    # the progress measure is the distance in (x, z) (a threshold's default would use x[:2])
    d = ca.Function("d", [nav.plant.x], [nav.progress()])
    assert float(d(np.array([0.0, 5.0, 0.0, 0.0, 0.0, 0.0]))) == pytest.approx(
        np.hypot(1.71, 1.71), rel=1e-12)
    assert navigation_setup().progress() is None
    backup = s.backup(nav.plant, None)
    np.testing.assert_allclose(backup(nav.goal), 0.0, atol=1e-15)  # hovers at rest
    f = ca.Function("f", [nav.plant.x, nav.plant.u], [nav.plant.x_next])
    x = np.array([0.9, 1.0, 1.0, -0.5, 0.2, 1.0])
    for _ in range(60):
        x = np.asarray(f(x, backup(x))).ravel()
    assert np.abs(x[[1, 3]]).max() < 0.02 and abs(x[5]) < 0.1 and abs(x[4]) < 0.05
    # measured: speeds ~0.004 m/s, pitch rate ~0.06 rad/s after 1.2 s


def test_disturbed_states_and_level_scales_resolve_on_each_plant(navs):
    for name, s in SYSTEMS.items():
        idx = Disturbance(1.0, states=s.disturbed).indices(navs[name].plant)
        assert tuple(navs[name].plant.state_names[i] for i in idx) == s.disturbed
    assert system("planar_quadrotor").level_scale == pytest.approx(0.18**2)
    # calibrated on the heading (assumptions §2.6, python -m studies.arena.difficulty)
    assert system("unicycle").disturbed == system("bicycle").disturbed == ("theta",)
    assert (system("unicycle").level_scale, system("bicycle").level_scale) == (0.45, 0.24)
    assert system("double_integrator").disturbed == ("vx", "vy")
    assert system("double_integrator").level_scale == 1.0


def test_unknown_system_and_bad_system_fields_name_the_field():
    with pytest.raises(ValueError, match=r"^system = 'boat' is invalid: unknown system; "
                                         r"allowed values are \('double_integrator'"):
        system("boat")
    with pytest.raises(ValueError, match=r"^system = "):
        navigation_setup(system="boat")
    base = system("unicycle")
    for field, value in (("sigma", (0.0, 1.0)), ("lam", 0.0), ("scale", -1.0),
                         ("q_beta", -1.0), ("disturbed", "px"), ("model", 3),
                         ("cost_form", "other"), ("level_scale", 0.0)):
        with pytest.raises(ValueError, match=rf"^System\.{field} = "):
            dataclasses.replace(base, **{field: value})
    assert isinstance(base, System)


def test_ecbf_gains_of_the_bicycle_come_from_its_expansion_in_the_controls():
    from workbench.scenarios.methods import affine_in_controls

    bike, uni = (navigation_setup(SMALL, system=n).plant for n in ("bicycle", "unicycle"))
    assert affine_in_controls(uni) is uni
    aff = affine_in_controls(bike)
    assert aff.name == "kinematic_bicycle~affine" and aff.nh == bike.nh
    f = ca.Function("f", [bike.x, bike.u], [bike.x_next])
    fa = ca.Function("fa", [aff.x, aff.u], [aff.x_next])
    rng = np.random.default_rng(2)
    for _ in range(20):
        x, u = rng.normal(0, 1, 4), rng.uniform(bike.u_min, bike.u_max)
        lin = np.asarray(f(x, [u[0], 0.0])).ravel()
        lin[2] += bike.dt * x[3] * u[1] / 0.5  # tan(delta) -> delta
        np.testing.assert_allclose(np.asarray(fa(x, u)).ravel(), lin, rtol=1e-13, atol=1e-13)

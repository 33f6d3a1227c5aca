"""A system from any model (system_from_model): the derived defaults against their rules and
closed forms, values given used as given, every registered method built by name on two models
the workbench does not ship and acting on a disturbed episode, entries from a config, and the
errors."""

from __future__ import annotations

import importlib.util
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from workbench.sampling.methods.gatekeeper import braking_backup
from workbench.sampling.weights import importance_weights
from workbench.scenarios.methods import method, names
from workbench.scenarios.model_system import (
    LAMBDA_DRAWS,
    LAMBDA_SHARE,
    calibrate_lambda,
    load_entry,
    resolve_system,
    system_from_model,
)
from workbench.scenarios.navigation import navigation_setup
from workbench.scenarios.systems import SYSTEMS
from workbench.sim import Disturbance, closed_loop

ROOT = Path(__file__).parents[2]
USER_MODELS = ROOT / "examples" / "user_models.py"


def _user_models():
    spec = importlib.util.spec_from_file_location("user_models_for_tests", USER_MODELS)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


um = _user_models()


@pytest.fixture(scope="module")
def point_mass():
    return system_from_model(um.point_mass_3d(), um.POINT_MASS_START, um.POINT_MASS_GOAL)


@pytest.fixture(scope="module")
def arm():
    return system_from_model(um.two_link_arm(), um.ARM_START, um.ARM_GOAL)


def test_derived_defaults_follow_their_rules_on_the_point_mass(point_mass):
    s = point_mass
    assert s.horizon == 40  # round(2 s / 0.05 s)
    np.testing.assert_allclose(s.sigma, [2.0] * 3, rtol=1e-12)  # range 8 / 4
    assert s.disturbed == ("vx", "vy", "vz")  # what the accelerations move in one step
    np.testing.assert_allclose(s.level_scale, (4.0 / 5.0) ** 2, rtol=1e-12)
    dp = np.linalg.norm(um.POINT_MASS_GOAL[:3] - um.POINT_MASS_START[:3])
    np.testing.assert_allclose(s.state_scale[:3], [dp] * 3, rtol=1e-12)  # isotropic
    np.testing.assert_allclose(s.Q[:3], [1 / dp**2] * 3, rtol=1e-12)
    np.testing.assert_allclose(s.Q[3:], 0.1 / np.asarray(s.state_scale[3:]) ** 2, rtol=1e-12)
    np.testing.assert_allclose(s.S, 10 * np.asarray(s.Q), rtol=1e-12)
    np.testing.assert_allclose(s.goal_radius, 0.1 * dp, rtol=1e-12)
    origins = dict(s.origins)
    assert set(origins) >= {"horizon", "sigma", "lam", "Q", "S", "q_beta", "disturbed",
                            "level_scale", "feedback_weights", "goal_radius", "backup"}
    assert all(v != "given" for v in origins.values())


def test_lambda_is_the_share_of_the_first_batches_best_cost_spread(point_mass):
    """lambda = 0.01 x the median over 8 seeded first batches of (1 % quantile - minimum) of
    the costs, recomputed here from batches drawn independently of calibrate_lambda."""
    nav = navigation_setup(system=point_mass)
    from workbench.sampling.mppi import MPPI
    from workbench.sampling.planning import full_state
    c = MPPI(nav.problem, nav.goal, nav.mppi)
    xb = full_state(nav.problem, nav.x0, c.consts.scene)
    spreads, first = [], None
    for seed in range(LAMBDA_DRAWS):
        batch = c.sampler.mppi(xb, c.initial_state().U, nav.mppi.n_samples, c.consts,
                               int(np.random.default_rng(seed).integers(0, 2**63)))
        first = batch if first is None else first
        S = np.sort(batch.S[np.isfinite(batch.S)])
        k = 0.01 * (S.size - 1)  # numpy's linear quantile at 1 %
        spreads.append(S[int(k)] + (k - int(k)) * (S[int(k) + 1] - S[int(k)]) - S[0])
    np.testing.assert_allclose(point_mass.lam, LAMBDA_SHARE * np.median(spreads), rtol=1e-12)
    np.testing.assert_allclose(calibrate_lambda(nav.problem, nav.goal, nav.x0, nav.mppi),
                               point_mass.lam, rtol=1e-12)
    assert calibrate_lambda(nav.problem, nav.goal, nav.x0, nav.mppi, draws=1) == \
        pytest.approx(LAMBDA_SHARE * spreads[0], rel=1e-12)
    # greedy: the weight sits on a handful of the best samples
    assert importance_weights(first.S, point_mass.lam).ess < 0.01 * nav.mppi.n_samples


def test_the_arm_without_a_position_measures_goal_distance_in_scaled_states(arm):
    assert arm.disturbed == ("dq1", "dq2")  # torques move the rates, the angles at O(dt^2)
    nav = navigation_setup(system=arm)
    X = np.array([um.ARM_START, um.ARM_GOAL])
    d = nav.goal_distance(X)
    np.testing.assert_allclose(d[0], np.linalg.norm((um.ARM_GOAL - um.ARM_START)
                                                    / np.asarray(arm.state_scale)), rtol=1e-12)
    assert d[1] == 0.0
    assert nav.progress() is not None  # the threshold rules measure the same distance


def test_values_given_are_used_and_recorded_as_given():
    s = system_from_model(um.point_mass_3d(), um.POINT_MASS_START, um.POINT_MASS_GOAL,
                          sigma=(1.0, 1.5, 2.0), lam=3.0, horizon=25, disturbed=("vz",),
                          level_scale=2.0, goal_radius=0.3)
    assert (s.sigma, s.lam, s.horizon, s.disturbed, s.level_scale, s.goal_radius) == (
        (1.0, 1.5, 2.0), 3.0, 25, ("vz",), 2.0, 0.3)
    o = dict(s.origins)
    assert all(o[k] == "given" for k in ("sigma", "lam", "horizon", "disturbed",
                                         "level_scale", "goal_radius"))
    assert o["Q"] != "given"
    nav = navigation_setup(system=s)
    assert (nav.mppi.sigma, nav.mppi.lam, nav.mppi.horizon) == ((1.0, 1.5, 2.0), 3.0, 25)


@pytest.mark.filterwarnings("error::UserWarning")  # e.g. a calibration episode that crashed
@pytest.mark.parametrize("model_name", ["point_mass", "arm"])
def test_every_registered_method_builds_by_name_steps_and_its_mechanism_acts(
        model_name, request):
    """Each registered method on the model, in closed loop under a disturbance from a start
    beside its constraints: it runs, and its mechanism acts on some step of one of up to
    three disturbed episodes (a mechanism that stays idle in all three fails)."""
    base = request.getfixturevalue(model_name)
    start, level = ((np.array([0.6, -0.1, 1.0, 1.2, 0.0, 0.0]), 30.0)
                    if model_name == "point_mass" else (np.array([0.3, 0.3, 0.5, 0.0]), 3.0))
    sysm = replace(base, scene=replace(base.scene, start=start))  # the derived backup
    nav = navigation_setup(system=sysm)
    nav = replace(nav, mppi=replace(nav.mppi, n_samples=128))
    dist = Disturbance(level * sysm.level_scale, states=sysm.disturbed)
    acted = {}
    for name in names():
        spec = method(name)
        ctrl = nav.controller(name)
        for seed in (3, 5, 7):
            ep = closed_loop(ctrl, nav.plant, nav.x0, 100, np.random.default_rng(seed),
                             np.random.default_rng(seed + 1), dist, check_episode=False)
            assert len(ep.U) > 0 and np.all(np.isfinite(np.asarray(ep.U))), name
            assert ctrl.goal is not None
            if spec.activity is None:
                break
            acted[name] = max(i.stats.activity.get(spec.activity, 0.0) for i in ep.infos)
            if acted[name] > 0:
                break
    assert {k for k, v in acted.items() if not v > 0} == set(), acted


def test_entries_load_from_a_file_or_a_module_and_register_once(tmp_path, monkeypatch):
    entry = f"{USER_MODELS}:arm_system"
    try:
        s = load_entry(entry)
        assert s.name == "two_link_arm" and SYSTEMS["two_link_arm"] is s
        assert resolve_system(entry) is s  # loaded once
        assert resolve_system("two_link_arm") is s
        (tmp_path / "my_arm.py").write_text(
            "import workbench as wb\n"
            "def other():\n    return 3\n")
        monkeypatch.syspath_prepend(str(tmp_path))
        with pytest.raises(ValueError, match=r"other\(\) must return a System"):
            load_entry("my_arm:other")
        with pytest.raises(ValueError, match="has no function 'missing'"):
            load_entry("my_arm:missing")
        with pytest.raises(ValueError, match="cannot import 'no_such_module_xyz'"):
            load_entry("no_such_module_xyz:f")
        with pytest.raises(ValueError, match="does not exist"):
            load_entry("nowhere/none.py:f")
    finally:
        SYSTEMS.pop("two_link_arm", None)


def test_bad_models_and_values_are_refused_with_the_field_named():
    from workbench.problem.barrier import BarrierOptions, embed_barrier
    pm = um.point_mass_3d()
    with pytest.raises(ValueError, match="start"):
        system_from_model(pm, np.zeros(4), um.POINT_MASS_GOAL)
    with pytest.raises(ValueError, match="barrier-embedded"):
        system_from_model(embed_barrier(pm, BarrierOptions()), um.POINT_MASS_START,
                          um.POINT_MASS_GOAL)
    with pytest.raises(ValueError, match="disturbed"):
        system_from_model(pm, um.POINT_MASS_START, um.POINT_MASS_GOAL, disturbed=("wz",))
    no_h = replace(pm, h=pm.h[:0])
    with pytest.raises(ValueError, match=r"model\.h"):
        system_from_model(no_h, um.POINT_MASS_START, um.POINT_MASS_GOAL)
    unbounded = replace(pm, u_min=np.full(3, -np.inf), u_max=np.full(3, np.inf))
    with pytest.raises(ValueError, match=r"sigma.*unbounded control"):
        system_from_model(unbounded, um.POINT_MASS_START, um.POINT_MASS_GOAL, lam=1.0)


def test_a_model_system_refuses_maps():
    from workbench.scenarios.scenes import CircleScene
    s = system_from_model(um.point_mass_3d(), um.POINT_MASS_START, um.POINT_MASS_GOAL,
                          lam=1.0)
    with pytest.raises(ValueError, match="runs on its own constraints"):
        navigation_setup(CircleScene(((3.0, 3.0, 1.0),), (0.5, 0.5), (9.0, 9.0)), system=s)


def test_compare_methods_runs_the_comparison_on_a_system_of_ones_own(tmp_path):
    """From Python with a System that has no entry (in this process), and refused with
    workers; the report says where the settings came from."""
    from workbench.sampling.mppi import MPPIConfig
    from workbench.scenarios.compare import compare_methods
    s = replace(system_from_model(um.two_link_arm(), um.ARM_START, um.ARM_GOAL),
                name="arm_for_compare")
    small = dict(controllers=("bas_mppi", "mppi_crash"), variances=(3.0,), realisations=2,
                 steps=10, sampler=MPPIConfig(n_samples=64, horizon=20, sigma=s.sigma,
                                              lam=s.lam))
    try:
        with pytest.raises(ValueError, match="workers"):
            compare_methods(s, tmp_path / "w", workers=2, **small)
        compare_methods(s, tmp_path / "run", **small)
        report = (tmp_path / "run" / "report.md").read_text()
        assert "two link arm (your model: its own start, goal and constraints)" in report
        assert "## Where the settings came from" in report
        assert "| horizon | round(2 s / dt) within [20, 100] |" in report
    finally:
        SYSTEMS.pop("arm_for_compare", None)


def test_the_gatekeeper_brakes_with_the_derived_backup_or_refuses_one_that_does_not_stop(arm):
    """The arm's default backup (the law derived from the model) stops it, so the gatekeeper
    builds and runs; braking each rate with gain 1/dt (the planar robots' law) does not stop
    the torque-driven arm, and the gatekeeper refuses it by name."""
    assert dict(arm.origins)["backup"].startswith("model_braking_backup")
    nav = navigation_setup(system=arm)
    ctrl = nav.controller("gatekeeper")
    ep = closed_loop(ctrl, nav.plant, nav.x0, 30, np.random.default_rng(1),
                     np.random.default_rng(2), check_episode=False)  # undisturbed: idle
    assert len(ep.U) == 30
    rates = replace(arm, backup=lambda plant, gain: braking_backup(plant, velocity=(2, 3),
                                                                    gain=gain))
    nav = navigation_setup(system=rates)
    with pytest.raises(ValueError, match=r"backup = 'braking' is invalid: does not bring "
                                         r"two_link_arm to rest"):
        nav.controller("gatekeeper").initial_state(nav.x0)
    with pytest.raises(ValueError, match="braking_gain"):
        arm.backup(nav.plant, 2.0)


def test_a_calibration_episode_that_crashes_is_reported(point_mass):
    """From a start 0.4 m before the first sphere moving at it at 1.6 m/s (0.32 m to stop at
    full braking), the undisturbed calibration episode crashes: the threshold it gives holds
    crash costs, and the user is told; from a slower start further away it does not."""
    sysm = replace(point_mass, scene=replace(point_mass.scene,
                                             start=np.array([1.0, -0.1, 1.0, 1.6, 0, 0])))
    nav = navigation_setup(system=sysm)
    nav = replace(nav, mppi=replace(nav.mppi, n_samples=128))
    with pytest.warns(UserWarning, match="calibration episode crashed after"):
        nav.threshold()
    ok = replace(point_mass, scene=replace(point_mass.scene,
                                           start=np.array([0.6, -0.1, 1.0, 1.2, 0, 0])))
    nav = replace(navigation_setup(system=ok), mppi=replace(nav.mppi, n_samples=128))
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        nav.threshold()


def test_a_method_whose_requirement_the_model_lacks_is_refused_with_the_reason():
    """A jerk-driven triple integrator: u reaches the position margin only after three steps,
    beyond the ECBF rows' degree 2, so SAIS with ECBF gains is refused by name; the discrete
    CBF of Shield-MPPI has order 3 and builds."""
    import casadi as ca

    import workbench as wb
    x, u, dt = ca.SX.sym("x", 3), ca.SX.sym("u", 1), 0.05
    m = wb.Model.from_expressions("jerk", x, u, x + dt * ca.vertcat(x[1], x[2], u[0]), dt=dt,
                                  u_min=[-5.0], u_max=[5.0], h=[2.0 - x[0]],
                                  state_names=("p", "v", "a"), control_names=("j",))
    s = system_from_model(m, [0.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    nav = navigation_setup(system=s)
    with pytest.raises(ValueError, match=r"sais_ecbf needs every margin reached by the "
                                         r"controls within two steps.*margins \[0\]"):
        nav.controller("sais_ecbf")
    assert nav.controller("shield_mppi") is not None
    from workbench.filters.ecbf import unreached_margins
    assert unreached_margins(m) == (0,)
    assert unreached_margins(um.point_mass_3d()) == ()  # degree 2 everywhere


def test_tracking_weights_are_sized_for_any_model():
    import workbench as wb
    arm = um.two_link_arm()
    w = wb.TrackingWeights.for_model(arm, state_scale=(1.5, 1.0, 2.0, 2.0), q_beta=0.05)
    np.testing.assert_allclose(w.Q, [1 / 1.5**2, 1.0, 0.25, 0.25], rtol=1e-12)
    np.testing.assert_allclose(w.R, [1e-3 / 9.0] * 2, rtol=1e-12)  # half-width 3 N m
    np.testing.assert_allclose(w.S, 100.0 * np.asarray(w.Q), rtol=1e-12)
    assert w.q_beta == 0.05
    plan, _ = wb.bas_ilqg(arm, x0=um.ARM_START, x_ref=np.linspace(um.ARM_START, um.ARM_GOAL, 41),
                          target=um.ARM_GOAL, weights=w)
    assert plan.X.shape == (41, 5)  # 4 states and the barrier state: the weights fit
    with pytest.raises(ValueError, match="state_scale"):
        wb.TrackingWeights.for_model(arm, state_scale=(1.0, 0.0, 1.0, 1.0))
    di = wb.double_integrator()
    d = wb.TrackingWeights.for_model(di, state_scale=(1, 1, 10**0.5, 10**0.5),
                                     control_scale=(1, 1), terminal=100.0)
    ref = wb.TrackingWeights()  # the double integrator's defaults: Q and S ten times these
    np.testing.assert_allclose(10 * np.asarray(d.Q), ref.Q, rtol=1e-12)
    np.testing.assert_allclose(10 * np.asarray(d.S), ref.S, rtol=1e-12)
    np.testing.assert_allclose(d.R, ref.R, rtol=1e-12)


def test_a_partial_sampler_table_keeps_the_systems_other_settings():
    """``--set sampler.n_samples=256`` on the unicycle changes N and keeps the unicycle's own
    sigma, lambda and horizon (not MPPIConfig's defaults)."""
    from workbench.study.runner import resolve_config
    from workbench.study.spec import registry
    cfg = resolve_config(registry()["sampling-safety"],
                         sets=['system="unicycle"', "sampler.n_samples=256"])
    r, uni = cfg.resolved(), SYSTEMS["unicycle"]
    assert (r.sampler.n_samples, r.sampler.sigma, r.sampler.lam, r.sampler.horizon) == (
        256, uni.sigma, uni.lam, uni.horizon)


def test_compare_methods_runs_each_system_given_under_a_taken_name(tmp_path):
    """Two systems of one name, one after the other, in this process: each run uses its own
    (by its derived settings in the report), and the registry is as before afterwards."""
    from workbench.sampling.mppi import MPPIConfig
    from workbench.scenarios.compare import compare_methods
    small = dict(controllers=("bas_mppi",), variances=(1.0,), realisations=1, steps=5,
                 sampler=MPPIConfig(n_samples=32, horizon=10, sigma=(1.5, 1.5), lam=0.1))
    before = SYSTEMS.get("two_link_arm")  # another test may have registered the examples' arm
    for i, radius in enumerate((0.05, 0.07)):
        s = system_from_model(um.two_link_arm(), um.ARM_START, um.ARM_GOAL, goal_radius=radius)
        compare_methods(s, tmp_path / f"run{i}", **small)
        import json
        ran = json.loads((tmp_path / f"run{i}" / "summary.json").read_text())["config"]
        assert ran["goal_radius"] == radius
        assert SYSTEMS.get("two_link_arm") is before

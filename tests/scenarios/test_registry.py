"""One registry for methods and systems: a toy method added by one module and one registry
line appears in ``workbench list``, builds and runs by name on every built-in system, is tuned
by the tuner, has a marker in the reports and runs through a study; a toy system likewise runs
every registered method. ``workbench list`` names exactly what the registries hold."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from method_runs import check_method_runs  # tests/scenarios/method_runs.py

import workbench as wb
from workbench.problem.catalogue import MODELS
from workbench.scenarios import SYSTEMS, CircleScene, navigation_setup
from workbench.scenarios import methods as registry
from workbench.scenarios.systems import unregister_system
from workbench.scenarios.tuned import ControllerSettings, space
from workbench.study.tuning import TuningBudget, tune

ROOT = Path(__file__).parents[2]
SMALL = CircleScene(((5.0, 5.0, 1.0), (3.0, 7.0, 0.8)), start=(1.0, 1.0), goal=(9.0, 9.0))

# the whole of a new method: its options, its controller and its spec
TOY_METHOD = '''
import dataclasses
from dataclasses import dataclass

import workbench as wb
from workbench.study.tuning import Param


@dataclass(frozen=True)
class ToyOptions:
    lam_scale: float = 1.0


def build(nav, settings):
    opts = settings.options("toy_mppi")
    cfg = dataclasses.replace(nav.mppi, lam=nav.mppi.lam * opts.lam_scale)
    return wb.MPPI(nav.problem, nav.goal, cfg)


SPEC = wb.MethodSpec("toy_mppi", "Toy MPPI", "barrier state, scaled temperature", build,
                     marker="d", options=ToyOptions,
                     tunable=(Param("toy_mppi.lam_scale", 0.1, 10.0),))
'''
# the whole of a new system: a planar single integrator
TOY_SYSTEM = '''
import casadi as ca
import numpy as np

import workbench as wb
from workbench.sampling.feedback import FeedbackWeights


def model(*, obstacles, dt, u_limit, scene_capacity, runtime_obstacles):
    return wb.single_integrator(obstacles=obstacles, u_limit=2.0, dt=dt,
                                scene_capacity=scene_capacity,
                                runtime_obstacles=runtime_obstacles)


def at(point, heading):
    return np.asarray(point, float)


def stop(plant, gain):
    return wb.backup_from_expression(plant, ca.SX.zeros(plant.nu), name="stop")


SYSTEM = wb.System(name="toy_single", label="toy single integrator", model=model, state_at=at,
                   Q=(1.0, 1.0), S=(10.0, 10.0), sigma=(1.0, 1.0), lam=1.0, q_beta=0.01,
                   disturbed=("px", "py"), state_names=("px", "py"), backup=stop,
                   feedback_weights=FeedbackWeights(Q=(500.0, 500.0), R=(1.0, 1.0)))
'''
# one registry line each
REGISTER_METHOD = "wb.register_method(toy_method.SPEC)"
REGISTER_SYSTEM = "wb.register_system(toy_system.SYSTEM)"


@pytest.fixture(scope="module")
def toys(tmp_path_factory):
    """Both toy modules written and registered; unregistered afterwards."""
    where = tmp_path_factory.mktemp("plugins")
    (where / "toy_method.py").write_text(TOY_METHOD)
    (where / "toy_system.py").write_text(TOY_SYSTEM)
    sys.path.insert(0, str(where))
    import toy_method
    import toy_system

    exec(REGISTER_METHOD, {"wb": wb, "toy_method": toy_method})
    exec(REGISTER_SYSTEM, {"wb": wb, "toy_system": toy_system})
    yield where
    registry.unregister("toy_mppi")
    unregister_system("toy_single")
    sys.path.remove(str(where))
    for m in ("toy_method", "toy_system"):
        sys.modules.pop(m, None)


def _nav(name: str):
    s = SYSTEMS[name]
    return navigation_setup(s.scaled(SMALL), system=name,
                            mppi=wb.MPPIConfig(n_samples=64, horizon=20, sigma=s.sigma,
                                               lam=s.lam))


def _list_output(env_extra: dict | None = None) -> str:
    env = {**os.environ, **(env_extra or {})}
    out = subprocess.run([sys.executable, "-m", "workbench.cli", "list"], capture_output=True,
                         text=True, cwd=ROOT, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    return out.stdout


def _section(text: str, title: str) -> list[str]:
    """The first words of the indented lines under the heading starting with ``title``."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(title))
    names = []
    for line in lines[start + 1:]:
        if not line.startswith("  "):
            break
        if not line.startswith("   "):  # wrapped text is indented further
            names.append(line.split()[0] if not line.startswith("  your own") else "your own")
    return names


def test_workbench_list_names_every_method_system_and_model_the_registries_hold():
    text = _list_output()
    assert _section(text, "methods") == list(registry.names())
    assert _section(text, "systems") == list(SYSTEMS)
    assert _section(text, "models") == [*MODELS, "your own"]
    assert len(registry.names()) == 10 and len(SYSTEMS) == 4 and len(MODELS) == 5


def test_the_toy_method_and_system_appear_in_workbench_list_through_the_plugin_variable(toys):
    """A plugin module is the toy module plus its registry line; ``workbench list`` in a new
    process loads it from ``$WORKBENCH_PLUGINS``."""
    (toys / "toy_method_plugin.py").write_text(
        "import workbench as wb\nimport toy_method\n" + REGISTER_METHOD + "\n")
    (toys / "toy_system_plugin.py").write_text(
        "import workbench as wb\nimport toy_system\n" + REGISTER_SYSTEM + "\n")
    text = _list_output({"PYTHONPATH": os.pathsep.join([str(toys), str(ROOT)]),
                         "WORKBENCH_PLUGINS": "toy_method_plugin, toy_system_plugin"})
    assert _section(text, "methods") == list(registry.names())  # the toy included, in order
    assert _section(text, "methods")[-1] == "toy_mppi"
    assert _section(text, "systems") == list(SYSTEMS)
    assert _section(text, "systems")[-1] == "toy_single"


def test_a_plugin_that_cannot_be_imported_is_named():
    out = subprocess.run([sys.executable, "-m", "workbench.cli", "list"], capture_output=True,
                         text=True, cwd=ROOT, timeout=120,
                         env={**os.environ, "WORKBENCH_PLUGINS": "no_such_plugin_module"})
    assert out.returncode != 0
    assert "WORKBENCH_PLUGINS" in out.stderr and "no_such_plugin_module" in out.stderr


@pytest.mark.parametrize("system", ["double_integrator", "unicycle", "bicycle",
                                    "planar_quadrotor"])
def test_the_toy_method_builds_and_runs_on_every_built_in_system(toys, system):
    s = SYSTEMS[system]
    check_method_runs(_nav(system), "toy_mppi", steps=3, level=s.level_scale, states=s.disturbed)


def test_every_built_in_method_and_the_toy_run_on_the_toy_system(toys):
    nav = _nav("toy_single")
    assert nav.plant.nx == 2 and nav.system.name == "toy_single"
    for name in registry.names():
        check_method_runs(nav, name, steps=3, level=1.0, states=("px", "py"))


def test_the_toy_method_is_tuned_and_its_options_reach_the_controller(toys):
    params = space("toy_mppi")
    assert [p.name for p in params] == ["sigma_scale", "lam", "toy_mppi.lam_scale"]
    base = ControllerSettings(wb.MPPIConfig(sigma=(5.0, 5.0), lam=10.0), 0.01,
                              wb.AlphaRule(kappa=0.1), registry.MethodSettings())
    assert base.values("toy_mppi") == {"sigma_scale": 1.0, "lam": 10.0,
                                       "toy_mppi.lam_scale": 1.0}
    nav = _nav("double_integrator")  # fixed sampler: only the toy's own option varies here
    seen = []

    def objective(p: dict[str, float], trial: int) -> float:
        settings = base.with_values("toy_mppi", p)
        ctrl = registry.build(nav, "toy_mppi", settings.methods)
        seen.append((p["toy_mppi.lam_scale"], ctrl.cfg.lam))
        return -abs(np.log(p["toy_mppi.lam_scale"]) - 1.0)

    result = tune(params, objective, TuningBudget(trials=3, episodes=1, seed=0),
                  base.values("toy_mppi"))
    assert len(seen) == 3 and seen[0] == (1.0, 10.0)
    # the tuned option is applied, never accepted and ignored
    assert all(lam == pytest.approx(10.0 * scale, rel=1e-12) for scale, lam in seen)
    assert set(result.best) == {"sigma_scale", "lam", "toy_mppi.lam_scale"}
    assert result.score >= result.start_score and len(result.trials) == 3
    settings = base.with_values("toy_mppi", {"toy_mppi.lam_scale": 2.0})
    assert settings.methods.options("toy_mppi").lam_scale == 2.0


def test_the_toy_method_runs_through_a_study_with_its_marker_in_the_report(toys, tmp_path):
    from studies.sampling_safety import STUDY
    from workbench.study.runner import profile_config
    from workbench.study.runner import run as run_study

    assert registry.markers()["toy_mppi"] == "d"
    assert len(set(registry.markers().values())) == len(registry.names())
    cfg = profile_config(STUDY, "tiny", controllers=("bas_mppi", "toy_mppi"), realisations=1)
    run_study(STUDY, cfg, tmp_path, workers=0, progress=False)
    report = (tmp_path / "report.md").read_text()
    assert "Toy MPPI" in report
    assert (tmp_path / "frontier.png").stat().st_size > 5_000


def test_registering_twice_or_a_bad_spec_names_the_field():
    with pytest.raises(ValueError, match=r"^spec\.name"):
        registry.register(registry.method("bas_mppi"))
    with pytest.raises(ValueError, match=r"^MethodSpec\.name"):
        wb.MethodSpec("Bad Name", "x", "y", lambda nav, s: None, marker="o")
    with pytest.raises(ValueError, match=r"tunable"):
        wb.MethodSpec("bad", "x", "y", lambda nav, s: None, marker="o",
                      tunable=(wb.Param("bad.gain", 0.1, 1.0),))
    with pytest.raises(ValueError, match=r"^controller"):
        registry.method("no_such_method")
    with pytest.raises(ValueError, match=r"^System\.name"):
        wb.register_system(SYSTEMS["unicycle"])


def test_a_method_that_needs_what_the_system_lacks_is_refused_with_the_reason():
    nav = _nav("double_integrator")
    bad = wb.FeedbackWeights(Q=(1.0, 1.0, 1.0), R=(1.0, 1.0))
    with pytest.raises(ValueError, match=r"^controller.*tracking weights"):
        nav.controller("sa_rmppi", weights=bad)


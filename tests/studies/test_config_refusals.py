"""Study configs refuse, when they are built, a disturbance on a state a system does not have
and a value nothing in the run would read (before: the config passed, and every task failed at
run time or the value was recorded and ignored)."""

from __future__ import annotations

import pytest

import workbench as wb
from studies.arena import STUDY
from studies.arena.config import DisturbanceSpec
from workbench.scenarios.scenes import NavigationScene
from workbench.scenarios.systems import _BUILTIN_SYSTEMS
from workbench.study.runner import profile_config


def tiny(**overrides):
    return profile_config(STUDY, "tiny", **overrides)


@pytest.mark.parametrize(("spec", "says"), [
    (DisturbanceSpec(states=("vx",)), r"'unicycle' has no state 'vx'; its states are 0: 'px', "
                                      r"1: 'py', 2: 'theta'"),
    (DisturbanceSpec(states=(3,)), r"'unicycle' has no state 3"),
    (DisturbanceSpec(states=("yaw",)), r"'double_integrator' has no state 'yaw'"),
])
def test_a_disturbance_on_a_state_a_system_lacks_is_refused_at_config_time(spec, says):
    with pytest.raises(ValueError, match=r"^disturbances\[0\]\.states = .*" + says):
        tiny(systems=("double_integrator", "unicycle"), disturbances=(spec,))
    with pytest.raises(ValueError, match=r"^tuning_disturbance\.states = .*" + says):
        tiny(systems=("double_integrator", "unicycle"), tuning_disturbance=spec)


def test_states_every_system_has_pass():
    c = tiny(systems=("double_integrator", "unicycle"),
             disturbances=(DisturbanceSpec(states=("px",)), DisturbanceSpec(states=(0, 1))))
    assert [d.states for d in c.disturbances] == [("px",), (0, 1)]


@pytest.mark.parametrize("states", [(True,), ("",), ("px", "px"), (-1,), (1.5,)])
def test_malformed_states_are_refused(states):
    with pytest.raises(ValueError, match=r"^disturbances\.states = .*state names or indices"):
        DisturbanceSpec(states=states)


@pytest.mark.parametrize(("kw", "field", "readers"), [
    ({"frequency": 2.0}, "frequency", "periodic"),
    ({"start_step": 5}, "start_step", "impulse and step"),
    ({"duration": 5}, "duration", "impulse"),
    ({"model": "step", "duration": 5}, "duration", "impulse"),
    ({"model": "periodic", "start_step": 5}, "start_step", "impulse and step"),
    ({"model": "impulse", "frequency": 2.0}, "frequency", "periodic"),
])
def test_a_field_the_disturbance_type_does_not_read_is_refused(kw, field, readers):
    with pytest.raises(ValueError, match=rf"^disturbances\.{field} = .*not read by the "
                                         rf"disturbance type .*only by {readers}"):
        DisturbanceSpec(**kw)


def test_the_fields_a_type_reads_are_applied():
    d = DisturbanceSpec("impulse", 2.0, start_step=5, duration=3).disturbance(1.0, ("vx",))
    assert (d.start_step, d.duration) == (5, 3)
    assert DisturbanceSpec("step", 2.0, start_step=7).disturbance(1.0, None).start_step == 7
    assert DisturbanceSpec("periodic", 2.0, frequency=2.5).disturbance(1.0, None).frequency == 2.5


def test_each_system_names_the_states_of_its_plant():
    """System.state_names (read by the configs without building the plant) are the built
    plant's, and a system's disturbed states must be among them (the map systems; a system
    built from a user's model takes its names from that model)."""
    for name, sysm in _BUILTIN_SYSTEMS.items():
        plant = sysm.plant(sysm.scaled(NavigationScene()))
        assert sysm.state_names == plant.state_names, name
    from dataclasses import replace
    with pytest.raises(ValueError, match=r"^System\.disturbed = .*'omega' is not a state of "
                                         r"'unicycle'"):
        replace(wb.system("unicycle"), disturbed=("omega",))
    with pytest.raises(ValueError, match=r"^System\.state_names"):
        replace(wb.system("unicycle"), state_names=())


def test_navigation_refuses_illustration_steps_without_the_illustration():
    """Before: illustration_steps = 30 with illustration = false was accepted and nothing read
    it."""
    from studies.navigation.config import StudyConfig

    with pytest.raises(ValueError, match=r"^illustration_steps = 30 is invalid: .*illustration "
                                         r"= false"):
        StudyConfig(illustration=False, illustration_steps=30)
    assert StudyConfig(illustration=True, illustration_steps=30).illustration_steps == 30
    assert not StudyConfig(illustration=False).illustration

"""The arena on a system of one's own, named by its entry as in a config: it runs on its own
scene (the map seed only selects the random streams), a spawned worker loads the entry itself
and gives the same tables, the report names the system's label and decides the declared
comparison; the built-in systems keep their stream keys; tuned values, map families and a goal
radius that nothing would use, and a bad entry are refused naming the field."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest

from studies.arena import STUDY
from studies.arena.config import DecisionSettings
from studies.arena.difficulty import Bench
from studies.arena.tasks import ArenaEpisode, system_key, word
from studies.arena.tuning import check as check_tuning
from workbench.scenarios.maps import MapFamily
from workbench.scenarios.systems import SYSTEMS
from workbench.study import RunStore
from workbench.study.runner import profile_config
from workbench.study.runner import run as run_study

REPO = Path(__file__).resolve().parents[2]
# a file path in an entry is read relative to the working directory (set to the checkout by
# the fixture below; spawned workers inherit it), as a config run from the checkout names it
ENTRY = "examples/user_models.py:point_mass_system"
LABEL = "point mass 3d"


@pytest.fixture(scope="module", autouse=True)
def in_checkout():
    mp = pytest.MonkeyPatch()
    mp.chdir(REPO)
    yield
    mp.undo()


def own(**overrides):
    """The tiny profile on the examples' 3-D point mass: two controllers, one map (seed), two
    realisations, two rounds."""
    base = {"systems": [ENTRY], "controllers": ("bas_mppi", "sa_rmppi"), "test_maps": 1,
            "realisations": 2, "decision": DecisionSettings(rounds=2)}
    return profile_config(STUDY, "tiny", **{**base, **overrides})


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    cfg = own()
    out = {}
    for workers in (0, 1):  # 1: a spawned worker process that loads the entry itself
        out[workers] = tmp_path_factory.mktemp(f"arena_own_{workers}")
        run_study(STUDY, cfg, out[workers], workers=workers, progress=False)
    return cfg, out


def _sorted(df: pd.DataFrame) -> pd.DataFrame:
    return df.sort_values(list(df.columns)).reset_index(drop=True)


def test_a_worker_process_gives_the_same_tables(runs):
    _, out = runs
    for table in ("episodes", "activity"):  # timing is wall-clock
        a, b = (_sorted(RunStore(out[w]).table(table)) for w in (0, 1))
        pd.testing.assert_frame_equal(a, b)
    ep = RunStore(out[0]).table("episodes")
    assert set(ep["system"]) == {ENTRY}
    # its own scene: episodes are labelled by seed, not by a map; round 1 ran a new seed
    assert set(ep["map"]) <= {"own-1000", "own-1001"} and "own-1000" in set(ep["map"])
    first = ep[ep["map"] == "own-1000"]
    assert len(first) == 2 * 2 * 2  # controllers x disturbances x realisations


def test_the_report_names_the_system_and_decides(runs):
    _, out = runs
    report = (out[0] / "report.md").read_text()
    assert f"### {LABEL}, hand" in report  # the recommendation per system
    assert "## Declared comparisons and their verdicts" in report
    rows = [line for line in report.splitlines()
            if line.startswith("| SA-RMPPI (K_safe) vs BaS-MPPI | safety |")]
    assert len(rows) == 2 and all(f"| {LABEL} |" in r for r in rows)
    assert "No generated maps in this run." in report
    assert f"- {LABEL} ({ENTRY}) ran on its own scene, not on the generated maps" in report
    data = json.loads((out[0] / "summary.json").read_text())
    assert data["maps"] == [] and [s["system"] for s in data["scenes"]] == [ENTRY]
    assert {d["system"] for d in data["decisions"]} == {ENTRY}
    assert all(d["looks"] in (1, 2) for d in data["decisions"])


def test_built_in_stream_keys_are_unchanged():
    """The built-in systems keep their place in the registry as their stream word, also once
    an entry is loaded; an entry gets a stable word of its string."""
    own()  # loads and registers the entry's system in this process
    assert [system_key(n) for n in ("double_integrator", "unicycle", "bicycle",
                                    "planar_quadrotor")] == [0, 1, 2, 3]
    assert list(SYSTEMS)[:4] == ["double_integrator", "unicycle", "bicycle", "planar_quadrotor"]
    assert ArenaEpisode("bas_mppi", "unicycle", "corridor", 1003, "kick(1)", "hand",
                        1).stream_key() == (1, 1, 1003, 2071564509, 1)
    assert ArenaEpisode("sa_rmppi", "double_integrator", "spec", 1000,
                        "velocity_variance(50)", "hand", 0).stream_key() == (
        0, 0, 1000, 201734486, 0)
    assert system_key(ENTRY) == word(ENTRY) == 469866316


def test_tuned_values_are_refused_for_an_own_system():
    with pytest.raises(ValueError, match=r"^tunings = 'tuned' is invalid: no tuned values exist "
                       rf"for the system '{ENTRY}'.*use tunings = \[\"hand\"\]"):
        own(systems=["double_integrator", ENTRY], tunings=("hand", "tuned"))
    with pytest.raises(ValueError, match=rf"^systems = '{ENTRY}' is invalid: is a system of "
                       "your own"):
        check_tuning(own())


@pytest.mark.parametrize("overrides, message", [
    ({"systems": ["examples/user_models.py:no_such_system"]},
     r"^systems = 'examples/user_models\.py:no_such_system' is invalid: .*has no function "
     "'no_such_system'"),
    ({"systems": ["examples/no_such_file.py:point_mass_system"]},
     r"^systems = 'examples/no_such_file\.py:point_mass_system' is invalid: the file "
     r"examples/no_such_file\.py does not exist"),
    ({"systems": ["hovercraft"]}, r"^systems = 'hovercraft' is invalid: unknown system"),
    ({"systems": [ENTRY, str(REPO / ENTRY)]},
     r"^systems = '/.*/examples/user_models\.py:point_mass_system' is invalid: must not repeat "
     "a system"),
    ({"systems": ["double_integrator", ENTRY],
      "families": (MapFamily("spec"), MapFamily("corridor"))},
     r"^families = .* runs on its own scene.*takes one static map family"),
    ({"systems": ["double_integrator", ENTRY], "families": (MapFamily("spec", moving=2),)},
     r"^families = .*takes one static map family"),
    ({"families": (MapFamily("corridor"),)}, r"^families = .*no system would use this map"),
    ({"goal_radius": 0.3}, r"^goal_radius = 0\.3 is invalid: .*its own goal radius"),
])
def test_bad_systems_and_unused_values_are_refused_naming_the_field(overrides, message):
    with pytest.raises(ValueError, match=message):
        own(**overrides)


def test_built_in_systems_keep_their_families_and_goal_radius_beside_an_own_one():
    cfg = own(systems=[ENTRY, "double_integrator"], families=(MapFamily("corridor"),),
              goal_radius=0.3)
    assert cfg.systems == ("double_integrator", ENTRY)  # registered names first, as before
    with pytest.raises(ValueError, match=r"^system = 'hovercraft' is invalid: unknown system"):
        Bench(cfg, "hovercraft", (0,))
    assert Bench(cfg, ENTRY, (0,))._where(0).capacity is None  # its own scene: no slots

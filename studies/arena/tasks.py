"""Tasks of the arena: one closed-loop episode per (controller, system, map, disturbance,
tuning, realisation).

Common random numbers: an episode's stream key is (system, map family, map seed, disturbance,
realisation), not the controller or the tuning, so in realisation j every controller meets the
same plant disturbances (``ctx.rng(1)``) and draws from the same sampler stream (``ctx.rng(0)``).

A system is a registered name or an entry (``"path/file.py:function"``, ``"module:function"``)
that each worker loads itself (:func:`~studies.arena.episodes.arena_system`). A system built
from a model runs on its own scene: its map seed only selects the random streams, and its
episodes are labelled ``own-<seed>`` instead of a map (assumptions §12.4).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, replace

import numpy as np

from studies.arena.config import RESULT_VERSION, ArenaConfig, DisturbanceSpec
from studies.arena.episodes import (
    Controls,
    Where,
    arena_system,
    capacity,
    own_scene,
    run_episode,
)
from workbench.scenarios.maps import FAMILIES, LAYOUT_FAMILIES, MapFamily
from workbench.scenarios.methods import slowest_first
from workbench.scenarios.methods.settings import fingerprint as settings_data
from workbench.scenarios.systems import SYSTEMS, definition
from workbench.scenarios.tuned import ControllerSettings, check_usable, tuned
from workbench.study import TaskContext, TaskOutput
from workbench.study.latency import step_table
from workbench.study.spec import Declaration
from workbench.validation import fail


def word(text: str) -> int:
    """A stable 31-bit stream word for a label."""
    return int(hashlib.sha256(text.encode()).hexdigest()[:8], 16) >> 1


def system_key(name: str) -> int:
    """A system's word in the stream keys: its place in the registry for a registered name
    (the built-in systems keep their streams), a stable word of the entry string for an entry
    (``"path/file.py:function"``: the same entry gives the same streams in every process)."""
    return word(name) if ":" in name else list(SYSTEMS).index(name)


@dataclass(frozen=True)
class ArenaEpisode:
    controller: str
    system: str
    family: str
    map_seed: int
    disturbance: str  # its label
    tuning: str
    realisation: int

    def stream_key(self) -> tuple[int, ...]:
        return (system_key(self.system), FAMILIES.index(self.family),
                self.map_seed, word(self.disturbance), self.realisation)

    def columns(self) -> dict[str, object]:
        place = "own" if own_scene(self.system) else self.family  # no map on its own scene
        return {"controller": self.controller, "system": self.system,
                "map": f"{place}-{self.map_seed}", "family": self.family,
                "map_seed": self.map_seed, "disturbance": self.disturbance,
                "tuning": self.tuning, "realisation": self.realisation}


def hand_settings(config: ArenaConfig, system_name: str) -> ControllerSettings:
    """The hand-tuned settings on a system: the config's sampler (N, T, ...) with the system's
    own sigma and lambda, its q_beta, the config's alpha rule and method options."""
    s = arena_system(system_name)
    sampler = replace(config.sampler, sigma=tuple(s.sigma), lam=float(s.lam))
    return ControllerSettings(sampler, float(s.q_beta), config.rule, config.methods)


def settings(config: ArenaConfig, system_name: str, controller: str,
             tuning: str) -> ControllerSettings:
    base = hand_settings(config, system_name)
    if tuning == "hand":
        return base
    t = tuned(system_name, controller)
    if t is None:
        raise fail("tunings", "tuned", f"no tuned parameters are shipped for ({system_name}, "
                   f"{controller}); run `make tune-arena` or drop 'tuned' from tunings")
    check_usable(t, [f.family for f in config.families], config.map_seeds())
    return base.with_values(controller, t.params)


def controls(config: ArenaConfig, system_name: str, controller: str, tuning: str) -> Controls:
    return Controls(controller, settings(config, system_name, controller, tuning),
                    config.robust, config.feedback, config.calibration_seed)


def family(config: ArenaConfig, name: str) -> MapFamily:
    return next(f for f in config.families if f.family == name)


def where(config: ArenaConfig, system_name: str, family_name: str, seed: int) -> Where:
    fam = family(config, family_name)
    if own_scene(system_name):  # its own scene: no circle slots to size
        return Where(system_name, fam, seed, None)
    return Where(system_name, fam, seed, capacity(fam, config.map_seeds()
                                                  + config.tuning_seeds()
                                                  + config.validation_seeds()))


def disturbance_spec(config: ArenaConfig, label: str) -> DisturbanceSpec:
    return next(d for d in config.disturbances if d.label == label)


def run_task(task: ArenaEpisode, ctx: TaskContext, config: ArenaConfig,
             prepared=None) -> TaskOutput:
    sys_ = arena_system(task.system)
    dist = disturbance_spec(config, task.disturbance).disturbance(sys_.level_scale,
                                                                  sys_.disturbed)
    out = run_episode(where(config, task.system, task.family, task.map_seed),
                      controls(config, task.system, task.controller, task.tuning), dist,
                      config.steps, config.goal_radius, ctx.rng(0), ctx.rng(1), ctx.threads)
    act = out.activity
    return TaskOutput(
        tables={"episodes": {k: np.array([v]) for k, v in out.row().items()},
                "timing": {"mean_step_ms": np.array([out.mean_step_ms]),
                           "mean_cpu_ms": np.array([1e3 * out.step_cpu_s.mean()])},
                "step_times": step_table(out.step_wall_s, out.step_cpu_s),
                "activity": {"mechanism": np.array(list(act), dtype=str),
                             "activity": np.array(list(act.values()), dtype=float)}},
        arrays={"X": out.X, "U": out.U})


@dataclass(frozen=True)
class Plan:
    """Every task a run may need (the run's identity), and by round: round 0's whole grid
    under the key "", round r >= 1's episodes of each declared comparison by its label."""

    tasks: tuple[ArenaEpisode, ...]
    rounds: tuple[dict[str, tuple[ArenaEpisode, ...]], ...]

    def cost_s(self, task: ArenaEpisode) -> float:
        """Rough seconds of one core for an episode (for ``--dry-run``'s estimate)."""
        return EPISODE_SECONDS.get(task.system, max(EPISODE_SECONDS.values()))


# Seconds of one core per episode at the default sizes (N = 1024, T = 100, at most 1000
# steps), set-up and calibration included: the quick profile's 216 double-integrator and
# unicycle episodes took 439 s on 2 workers of a 2-core machine (4.1 s each; most end early,
# at the goal or at a crash). The other systems are assumed to cost the same.
EPISODE_SECONDS = {"double_integrator": 4.1, "unicycle": 4.1, "bicycle": 4.1,
                   "planar_quadrotor": 4.1}


def _sorted(tasks) -> list[ArenaEpisode]:
    # slow controllers first; within one, a (system, map) stays together (cached set-ups)
    order = slowest_first()
    return sorted(tasks, key=lambda t: (order.index(t.controller), t.system, t.family,
                                        t.map_seed, t.tuning, t.disturbance, t.realisation))


def plan(config: ArenaConfig) -> Plan:
    from studies.arena.decisions import members

    grid = [ArenaEpisode(c, s, f.family, m, d.label, t, j)
            for s in config.systems for f in config.families for m in config.round_seeds(0)
            for d in config.disturbances for t in config.tunings for c in config.controllers
            for j in range(config.realisations)]
    rounds: list[dict[str, tuple[ArenaEpisode, ...]]] = [{"": tuple(_sorted(grid))}]
    for r in range(1, config.decision.rounds):
        rounds.append({m.label: tuple(_sorted(
            ArenaEpisode(c, m.system, f.family, seed, m.disturbance, m.tuning, j)
            for c in (m.first, m.second) for f in config.families
            for seed in config.round_seeds(r) for j in range(config.realisations)))
            for m in members(config)})
    tasks = list(dict.fromkeys(t for rd in rounds for group in rd.values() for t in group))
    return Plan(tuple(_sorted(tasks)), tuple(rounds))


def system_values(names: tuple[str, ...]) -> dict:
    """Each system's :func:`~workbench.scenarios.systems.definition`: the values results
    depend on (a change to them must not reuse stored episodes); for a system with a scene of
    its own also its name, goal radius, state scales, start, goal and model."""
    out = {}
    for n in names:
        s = arena_system(n)
        out[n] = definition(s)
        if s.scene is not None:
            m = s.plant(s.scene)
            out[n].update(name=s.name, goal_radius=s.goal_radius, state_scale=s.state_scale,
                          start=list(s.scene.start), goal=list(s.scene.goal),
                          model=[str(m.x_next), str(m.h), list(m.u_min), list(m.u_max), m.dt])
    return out


def fingerprint(config: ArenaConfig) -> dict:
    d = settings_data(config)
    d["system_values"] = system_values(config.systems)
    for k in ("controllers", "systems", "test_maps", "disturbances", "realisations", "tunings",
              "seed", "tuning", "tuning_maps", "tuning_seed", "tuning_disturbance",
              "comparisons", "decision", "validation_maps", "validation_seed"):
        d.pop(k)
    # the circle slots depend on every map of a family: part of what a task computed (on a
    # generated map: a run of systems on their own scenes has none)
    if not all(own_scene(s) for s in config.systems):
        d["capacity"] = {f.family: capacity(f, config.map_seeds() + config.tuning_seeds()
                                            + config.validation_seeds())
                         for f in config.families if f.family not in LAYOUT_FAMILIES}
    if "tuned" in config.tunings:
        d["tuned"] = {f"{s}/{c}": settings_data(settings(config, s, c, "tuned"))
                      for s in config.systems for c in config.controllers}
    return d


def declare(config: ArenaConfig) -> Declaration:
    from studies.arena.decisions import staged

    p = plan(config)
    return Declaration(p.tasks, run_task, fingerprint(config), RESULT_VERSION, p,
                       staged(config, p.rounds))

"""The arena's fair tuning: one task per (system, controller), each the same budget of optuna
trials on the same training episodes, maximising one declared objective, then a check on
held-out validation episodes that decides what is shipped.

Three disjoint map ranges (checked by :class:`~studies.arena.config.ArenaConfig`): training
maps (``tuning_maps`` from ``tuning_seed``), validation maps (``validation_maps`` from
``validation_seed``) and the arena's test maps. Each trial runs ``tuning.episodes`` training
episodes, episode e on training map e mod (number of training maps), so every trial sees
every training map. After the search the hand-tuned point and the best ``tuning.finalists``
trials that beat it on training are scored on ``tuning.validation`` validation episodes; the
finalist best on validation is shipped if it beats the hand point there, else the hand point is
shipped, marked ``"kept": "hand"``.

Common random numbers: training episode e of every trial, for every controller of a system,
has the same map, plant disturbances and sampler stream (keyed by the system and e only);
validation episode v likewise (a stream of its own), so every candidate meets the same
validation episodes.

``make tune-arena`` runs this study and writes its result, with its provenance, as the shipped
defaults (:mod:`workbench.scenarios.tuned`), read by the arena's ``tuned`` rows. Each entry
records the hash of its system's definition as the run defined it (from the run's stored
fingerprint, :func:`system_hashes`), so the arena refuses it once the system is redefined.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from studies.arena.config import RESULT_VERSION, ArenaConfig
from studies.arena.episodes import Controls, Where, arena_system, capacity, run_episode
from studies.arena.tasks import family, hand_settings, system_values
from workbench.scenarios.methods import names
from workbench.scenarios.systems import SYSTEMS, definition_hash
from workbench.scenarios.tuned import (
    RERUN,
    Evaluation,
    MapSeeds,
    Tuned,
    TunedFileError,
    shipped,
    space,
    write,
)
from workbench.study import TaskContext, TaskOutput, to_jsonable
from workbench.study.folder import MANIFEST, read_json
from workbench.study.spec import Declaration, Summary
from workbench.study.tasks import seed_sequence
from workbench.study.tuning import select, tune
from workbench.validation import fail

OBJECTIVE = ("success rate (goal reached without a crash) minus 0.01 x the mean final distance "
             "to the goal in map units (metres divided by the system's map scale)")
TRAINING_STREAM, VALIDATION_STREAM = 1_000_003, 1_000_033  # stream words of the episodes


def objective_value(success, final_error_map_units) -> float:
    """:data:`OBJECTIVE` of a set of episodes: the mean of ``success`` (1 for an episode that
    reached the goal without a crash) minus 0.01 x the mean final distance to the goal in map
    units. The tuning and the arena's test scores both use this."""
    s = np.asarray(success, dtype=float)
    e = np.asarray(final_error_map_units, dtype=float)
    if s.ndim != 1 or s.size == 0 or s.shape != e.shape:
        raise fail("success", s.shape, f"must be a non-empty 1-D array shaped like "
                   f"final_error_map_units {e.shape}")
    return float(np.mean(s) - 0.01 * np.mean(e))


@dataclass(frozen=True)
class TuningTask:
    system: str
    controller: str

    def stream_key(self) -> tuple[int, int]:
        return list(SYSTEMS).index(self.system), names().index(self.controller)


def training(config: ArenaConfig) -> list[tuple[str, int]]:
    """The training maps: (family, seed) for every family and every tuning seed."""
    return [(f.family, s) for s in config.tuning_seeds() for f in config.families]


def validation(config: ArenaConfig) -> list[tuple[str, int]]:
    """The validation maps: (family, seed) for every family and every validation seed."""
    return [(f.family, s) for s in config.validation_seeds() for f in config.families]


def where(config: ArenaConfig, system_name: str, family_name: str, seed: int) -> Where:
    """A system on a training or validation map; the kernels' circle slots cover the test,
    training and validation maps of the family."""
    fam = family(config, family_name)
    seeds = config.map_seeds() + config.tuning_seeds() + config.validation_seeds()
    return Where(system_name, fam, seed, capacity(fam, seeds))


def episodes_score(config: ArenaConfig, task: TuningTask, maps: list[tuple[str, int]],
                   episodes: int, stream: int, threads: int = 1):
    """``params -> objective_value`` over ``episodes`` episodes of the task's system under the
    tuning disturbance, episode e on ``maps[e mod len(maps)]`` with streams keyed by the
    system, ``stream`` and e (never by the controller or the parameters)."""
    base = hand_settings(config, task.system)
    spec = arena_system(task.system)
    dist = config.tuning_disturbance.disturbance(spec.level_scale, spec.disturbed)
    key = list(SYSTEMS).index(task.system)

    def score(params: dict[str, float]) -> float:
        c = Controls(task.controller, base.with_values(task.controller, params), config.robust,
                     config.feedback, config.calibration_seed)
        success, error = [], []
        for e in range(episodes):
            fam, seed = maps[e % len(maps)]
            ss = seed_sequence(config.seed, (key, stream, e))
            rc, rp = (np.random.default_rng(s) for s in ss.spawn(2))
            out = run_episode(where(config, task.system, fam, seed), c, dist, config.steps,
                              config.goal_radius, rc, rp, threads)
            success.append(out.success)
            error.append(out.final_error / spec.scale)
        return objective_value(success, error)

    return score


def objective_of(config: ArenaConfig, task: TuningTask, threads: int = 1):
    """The training objective ``(params, trial) -> score`` and the hand-tuned start."""
    score = episodes_score(config, task, training(config), config.tuning.episodes,
                           TRAINING_STREAM, threads)
    return (lambda params, trial: score(params)), hand_settings(config, task.system).values(
        task.controller)


def validation_of(config: ArenaConfig, task: TuningTask, threads: int = 1):
    """The validation score ``params -> score`` (the same episodes for every candidate)."""
    return episodes_score(config, task, validation(config), config.tuning.validation,
                          VALIDATION_STREAM, threads)


def run_task(task: TuningTask, ctx: TaskContext, config: ArenaConfig,
             prepared=None) -> TaskOutput:
    objective, start = objective_of(config, task, ctx.threads)
    res = tune(space(task.controller), objective, config.tuning, start, description=OBJECTIVE)
    sel = select(res, validation_of(config, task, ctx.threads), config.tuning.finalists)
    validated = {t.number: v for t, v in sel.scored}
    t = res.trials
    return TaskOutput(
        tables={"trials": {"trial": np.array([x.number for x in t]),
                           "score": np.array([x.score for x in t]),
                           "validation": np.array([validated.get(x.number, np.nan)
                                                   for x in t]),
                           "params": np.array([json.dumps(x.params) for x in t], dtype=str)},
                "best": {"kept": np.array([sel.kept], dtype=str),
                         "params": np.array([json.dumps(sel.params)], dtype=str),
                         "hand": np.array([json.dumps(sel.start.params)], dtype=str),
                         "tuned": np.array([json.dumps(sel.candidate.params)], dtype=str),
                         "trial": np.array([sel.candidate.number]),
                         "training_hand": np.array([sel.start.score]),
                         "training_tuned": np.array([sel.candidate.score]),
                         "validation_hand": np.array([sel.start_validation]),
                         "validation_tuned": np.array([sel.candidate_validation])}})


def plan(config: ArenaConfig) -> tuple[TuningTask, ...]:
    return tuple(TuningTask(s, c) for s in config.systems for c in config.controllers)


def fingerprint(config: ArenaConfig) -> dict:
    d = asdict(config)
    d["system_values"] = system_values(config.systems)
    for k in ("controllers", "systems", "test_maps", "test_seed", "disturbances",
              "realisations", "tunings", "comparisons", "decision"):
        d.pop(k)
    seeds = config.map_seeds() + config.tuning_seeds() + config.validation_seeds()
    d["capacity"] = {f.family: capacity(f, seeds) for f in config.families}  # test maps too
    return d


def check(config: ArenaConfig) -> None:
    """What a tuning run needs beyond a valid arena config: a validation step, and enough
    episodes for every trial to see every training map and every candidate every validation
    map."""
    for s in config.systems:  # tuned values are shipped for the built-in systems only
        if ":" in s:
            raise fail("systems", s, "is a system of your own: the arena's tuning runs on "
                       "generated maps and ships values for the built-in systems only; its "
                       "controllers keep the hand-tuned settings (tunings = [\"hand\"])")
    b = config.tuning
    if b.validation < 1:
        raise fail("tuning.validation", b.validation, "must be >= 1: the arena's tuning "
                   "validates the hand point and the finalists on held-out maps")
    for name, n, maps in (("tuning.episodes", b.episodes, training(config)),
                          ("tuning.validation", b.validation, validation(config))):
        if n < len(maps):
            raise fail(name, n, f"must be at least the number of its maps ({len(maps)}: "
                       f"seeds x families) so that every map is run")


def declare(config: ArenaConfig) -> Declaration:
    check(config)
    return Declaration(plan(config), run_task, fingerprint(config), RESULT_VERSION)


def _maps(config: ArenaConfig, seeds: tuple[int, ...]) -> tuple[MapSeeds, ...]:
    return tuple(MapSeeds(f.family, seeds) for f in config.families)


def system_hashes(run_dir: Path | str) -> dict[str, str]:
    """The :func:`~workbench.scenarios.systems.definition_hash` of each system of the tuning
    run in ``run_dir``, from the system values of the fingerprint its manifest holds: the
    definitions its tasks were computed with, even if a system has been redefined since."""
    path = Path(run_dir) / MANIFEST
    advice = "ship a finished run of `make tune-arena`"
    data = read_json(path, "run's manifest", advice)
    values = (data.get("fingerprint") or {}).get("system_values") \
        if isinstance(data, dict) else None
    if not isinstance(values, dict) or not all(isinstance(v, dict) for v in values.values()):
        raise TunedFileError(f"{path}: its fingerprint holds no system values (the definitions "
                             f"the run tuned on); {advice}")
    return {name: definition_hash(v) for name, v in values.items()}


def tuned_entries(config: ArenaConfig, store) -> list[Tuned]:
    """The run's result per (system, controller) as shipped entries with their provenance."""
    hashes = system_hashes(store.root)
    out = []
    for _, r in store.table("best").iterrows():
        out.append(Tuned(
            r["system"], r["controller"], str(r["kept"]), json.loads(r["params"]),
            json.loads(r["hand"]), json.loads(r["tuned"]), config.tuning, OBJECTIVE,
            config.tuning_disturbance.label,
            Evaluation(_maps(config, config.tuning_seeds()), config.tuning.episodes,
                       float(r["training_hand"]), float(r["training_tuned"])),
            Evaluation(_maps(config, config.validation_seeds()), config.tuning.validation,
                       float(r["validation_hand"]), float(r["validation_tuned"])),
            hashes[r["system"]]))
    return sorted(out, key=lambda t: (t.system, t.controller))


def _values(params: dict[str, float]) -> str:
    return ", ".join(f"{k} {v:.3g}" for k, v in params.items())


def flag(t: Tuned) -> str:
    """Why the hand point was kept, or "" when the tuned point was."""
    if t.kept == "tuned":
        return ""
    if t.tuned == t.hand:
        return "no trial beat the hand point on training: hand kept"
    hand, tuned = (-np.inf if v is None else v for v in (t.validation.hand, t.validation.tuned))
    worse = tuned < hand
    return ("tuned worse than hand on validation: hand kept" if worse else
            "tuned no better than hand on validation: hand kept")


def summary(finished) -> Summary:
    entries = tuned_entries(finished.config, finished.store)
    lines = tuple(f"{t.system:18s} {t.controller:14s} training {t.start_score:.3f} (hand) -> "
                  f"{t.score:.3f}, validation {t.validation.hand:.3f} -> "
                  f"{t.validation.tuned:.3f}: kept {t.kept} ({_values(t.params)})"
                  for t in entries)
    return Summary({"tuned": [t.as_dict() for t in entries],
                    "budget": to_jsonable(finished.config.tuning)}, entries, lines)


def _maps_text(ev: Evaluation) -> str:
    return "; ".join(f"{m.family} seeds {min(m.seeds)}..{max(m.seeds)}" for m in ev.maps or ())


def report(finished, summ) -> Path:
    from workbench.study import md_table
    from workbench.study.io import atomic_write_text

    rows = [[t.system, t.controller, f"{t.start_score:.3f}", f"{t.score:.3f}",
             f"{t.validation.hand:.3f}", f"{t.validation.tuned:.3f}", t.kept, _values(t.hand),
             _values(t.tuned), flag(t) or "–"] for t in summ.value]
    c = finished.config
    b = c.tuning
    first = summ.value[0] if summ.value else None
    text = ["# Arena tuning", "", finished.run_line, "",
            f"Budget per controller: {b.trials} trials x {b.episodes} training episodes (TPE "
            f"seeded with {b.seed}), then the hand-tuned point and the best {b.finalists} "
            f"trials that beat it on training, each on {b.validation} validation episodes "
            f"(the same for every candidate). The best on validation is shipped if it beats "
            f"the hand point there; otherwise the hand point is shipped (kept: hand).", "",
            f"Objective: {OBJECTIVE}. Disturbance: {c.tuning_disturbance.label}.", "",
            *([f"Training maps: {_maps_text(first.training)}; validation maps: "
               f"{_maps_text(first.validation)}."] if first else []), "",
            *([("Tuned on the system definitions (hashes): " + ", ".join(
                f"{n} {h}" for n, h in dict.fromkeys((t.system, t.system_hash)
                                                     for t in summ.value)) + ".")]
              if first else []), "",
            *md_table(["system", "controller", "training, hand", "training, tuned",
                       "validation, hand", "validation, tuned", "kept", "hand point",
                       "tuned point", "flag"], rows), "",
            "The training score of the tuned point is the best of many noisy estimates and "
            "overstates it; the validation scores are unbiased for the hand point and nearly so "
            "for the tuned one (the best of a few finalists).", ""]
    path = Path(finished.out) / "report.md"
    atomic_write_text(path, "\n".join(text))
    return path


def ship(run_dir: Path | str, path: Path | None = None) -> Path:
    """Write a finished tuning run's results as the shipped defaults (entries for other
    (system, controller) pairs are kept, each with its own provenance). Each entry's
    ``system_hash`` is that of its system as the run defined it (:func:`system_hashes`; a
    summary written before entries carried one gets it from there too)."""
    source = Path(run_dir) / "summary.json"
    data = json.loads(source.read_text(encoding="utf-8"))
    hashes = system_hashes(run_dir)
    new = []
    for e in data["tuned"]:
        name = e.get("system") if isinstance(e, dict) else None
        h = hashes.get(name) if isinstance(name, str) else None
        if h is None:
            raise TunedFileError(f"{source}: entry {e!r} is of no system the run's manifest "
                                 f"defines ({sorted(hashes)}); {RERUN}")
        if e.setdefault("system_hash", h) != h:
            raise TunedFileError(f"{source}: ({e['system']}, {e.get('controller')}) records "
                                 f"system hash {e['system_hash']}, but the run's manifest "
                                 f"defines {e['system']} as {h}; {RERUN}")
        new.append(Tuned.from_dict(e, source))
    try:
        entries = shipped(path)
    except TunedFileError as exc:
        raise TunedFileError(f"cannot add this run's entries to the existing file: {exc}; "
                             f"move that file away to ship this run's entries alone") from exc
    for t in new:
        entries[(t.system, t.controller)] = t
    return write(entries.values(), path)


if __name__ == "__main__":
    import sys

    print(ship(sys.argv[1] if len(sys.argv) > 1 else "reports/arena_tuning"))

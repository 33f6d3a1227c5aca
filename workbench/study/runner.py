"""One runner for every study: resolve the config, prepare, execute, summarise, report.

A run directory ends up holding ``config.toml`` (the resolved config: every size that ran),
``manifest.json`` and the per-task results (:mod:`workbench.study.store`), the tidy tables,
``summary.json`` (a function of the results only), ``run.json`` (the run record) and the
study's ``report.md`` with its figures. Every JSON file is strict JSON: a NaN or infinite number
(e.g. the rate of an empty cell, an ``alpha = inf`` in the manifest's config) is written as
``null``.

Before anything is written, the config, the worker count, the time limit and the scheduler
(format, then a connection within seconds) are checked, and the folder is claimed for this run
(:mod:`workbench.study.folder`): a folder of another config, a folder of someone else's files
and a folder in use by another run are refused with a message saying what to do. The folder
stays locked until the report is written.

``run.json`` describes the invocation that computed tasks: profile, tasks (total, computed,
loaded), ``wall_time_s``, back end, cores and the 1-minute load average at its start and end;
``last_invocation`` holds the same fields for the latest invocation. A rerun that computes
nothing (every task already stored) updates ``last_invocation`` only, so the wall time of the
run that did the work is kept, and the report's run line quotes it.

A run refuses more than :data:`~workbench.validation.MAX_TASKS` tasks (10^7) before computing
anything; each study's config bounds its own sizes when it is built. Status lines (the summary
lines of a finished run) go to the ``workbench.study`` logger at INFO.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import time
import tomllib
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

from workbench.study import config_io
from workbench.study.config_io import ConfigError
from workbench.study.cost_pass import run_pass, stored_pass
from workbench.study.execute import (
    RunResult,
    check_timeout,
    check_workers,
    refuse_mixed,
    run_study,
    scheduler_client,
)
from workbench.study.folder import MANIFEST, RunFolderError, claim, locked
from workbench.study.io import atomic_write_json, atomic_write_text
from workbench.study.report import tasks_phrase
from workbench.study.spec import Declaration, Finished, RegistrationError, StudySpec, Summary
from workbench.study.store import RunStore, study_manifest, tasks_sha256
from workbench.study.summary import to_jsonable
from workbench.study.tasks import Study
from workbench.validation import MAX_TASKS

RUN_FILE = "run.json"
RECORD_KEYS = ("profile", "tasks", "wall_time_s", "backend", "cpu_count", "load_average_1min")
log = logging.getLogger("workbench.study")


@dataclass(frozen=True)
class Outcome:
    """A finished run: the study's summary, the framework's run record and the report's path."""

    summary: Summary
    run: RunResult
    report: Path


def _no_profile_key(layer: dict, where: str, spec: StudySpec) -> None:
    if "profile" in layer:
        raise ConfigError(
            f"{where}: profile = {layer['profile']!r} is not a config key: a profile is a set of "
            f"sizes chosen with --profile NAME ({', '.join(spec.profiles)}); the run records the "
            "profile in run.json and every resolved size in config.toml")


def _user_path(path: Path | str) -> Path:
    """``path`` with a leading ``~`` (or ``~user``) expanded, as the command line does."""
    return Path(os.path.expanduser(str(path)))


def _stored_config(spec: StudySpec, out: Path) -> Any:
    """The config of the run in ``out``: the manifest's, unless it holds a null (the config
    holds no None, :func:`~workbench.study.config_io.to_dict` leaves None out, so a null is an
    inf or NaN that strict JSON could not keep): then the run's config.toml (TOML keeps them)."""
    data = RunStore(out).manifest().get("config")
    if not isinstance(data, dict):
        raise RunFolderError(f"{out / MANIFEST} holds no config: it is not a run's manifest; "
                             f"rerun the study into {out} to rewrite it, or delete the folder")
    toml = out / "config.toml"
    if _has_null(data) and toml.is_file():
        data = tomllib.loads(toml.read_text())
    return config_io.load(spec.config_type, data)


def _has_null(obj: Any) -> bool:
    if obj is None:
        return True
    if isinstance(obj, dict):
        return any(_has_null(v) for v in obj.values())
    if isinstance(obj, list):
        return any(_has_null(v) for v in obj)
    return False


def resolve_config(spec: StudySpec, profile: str | None = None, config: Path | None = None,
                   sets: list[str] | tuple[str, ...] = ()) -> Any:
    """The validated config from its layers: the config dataclass's defaults <- the profile's
    TOML file (``profile``; the study's default profile when neither a profile nor a config
    file is given) <- the config file <- each ``key=value`` of ``sets``."""
    layers = []
    if profile is None and config is None:
        profile = spec.default_profile
    if profile is not None:
        if profile not in spec.profiles:
            raise ConfigError(f"--profile {profile!r} is invalid: study {spec.name!r} has the "
                              f"profiles {', '.join(spec.profiles)}")
        layers.append(config_io.read_toml(spec.profiles[profile]))
        _no_profile_key(layers[-1], str(spec.profiles[profile]), spec)
    if config is not None:
        layers.append(config_io.read_toml(config))
        _no_profile_key(layers[-1], str(config), spec)
    layers.append(config_io.parse_sets(sets, spec.aliases))
    _no_profile_key(layers[-1], "--set", spec)
    return config_io.load(spec.config_type, config_io.merge(*layers), aliases=spec.aliases)


def profile_config(spec: StudySpec, profile: str, **overrides: Any) -> Any:
    """The config of a profile with fields replaced (and checked again) by ``overrides``."""
    return dataclasses.replace(resolve_config(spec, profile), **overrides)


def declare(spec: StudySpec, config: Any, prepared: Any = None) -> tuple[Study, Any]:
    """The framework's :class:`~workbench.study.Study` for ``config`` and the study's plan.
    ``prepared`` is bound into the task function when the study prepares something. A value
    the study's ``tasks`` refuses (a ValueError, e.g. a tuned pair that is not shipped) is a
    :class:`ConfigError` naming the study; so is a ``tasks`` that returns no Declaration."""
    try:
        d = spec.fn("tasks")(config)
    except ConfigError:
        raise
    except ValueError as exc:  # the study's own checks of the config (validation.fail)
        raise ConfigError(f"study {spec.name!r}: {exc}") from exc
    if not isinstance(d, Declaration):
        raise RegistrationError(f"study {spec.name!r}: tasks returned {type(d).__name__}, "
                                "expected a workbench.study.spec.Declaration")
    if len(d.tasks) > MAX_TASKS:
        raise ConfigError(f"study {spec.name!r}: the config gives {len(d.tasks)} tasks, above "
                          f"the limit {MAX_TASKS}; lower its counts (realisations, seeds, "
                          "episodes, ...)")
    bound = {"config": config} if spec.prepare is None else {"config": config,
                                                            "prepared": prepared}
    run_task = partial(d.run_task, **bound)
    study = Study(spec.store_name, d.tasks, run_task, seed=config.seed,
                  config=config_io.to_dict(config), fingerprint=d.fingerprint, version=d.version,
                  stages=d.stages)
    return study, d.plan


def dry_manifest(spec: StudySpec, config: Any) -> dict:
    """What a run would record before computing anything (study, version, seed, config,
    fingerprint, task count and a hash of the task ids)."""
    return study_manifest(declare(spec, config)[0])


def _prepared(spec: StudySpec, config: Any, out: Path) -> tuple[Study, Finished]:
    """Prepare (once, here) and declare: the Study and what its summary and report read."""
    prepared = spec.fn("prepare")(config, out) if spec.prepare is not None else None
    study, plan = declare(spec, config, prepared)
    return study, Finished(config, out, RunStore(out), plan,
                           dict(zip(study.tasks, study.task_ids(), strict=True)), prepared)


def _cost_pass(spec: StudySpec, study: Study, finished: Finished) -> None:
    """Measure the study's cost pass once per run, here, after every task has finished (kept
    when the folder already holds one for these tasks)."""
    if spec.cost is None or stored_pass(finished) is not None:
        return
    plan = spec.fn("cost")(finished)
    log.info("cost pass: %d methods, %d rounds (%s)", len(plan.runs), plan.rounds, plan.what)
    run_pass(plan, finished.out, tasks_sha256(study.task_ids()))


def _summarise(spec: StudySpec, study: Study, finished: Finished) -> Summary:
    summary = spec.fn("summarise")(finished)
    atomic_write_json(finished.out / "summary.json",
                      {"study": study.name, **to_jsonable(summary.data)})
    return summary


def _read_record(out: Path) -> dict | None:
    try:
        record = json.loads((out / RUN_FILE).read_text())
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) else None


def _computed(record: dict | None) -> int:
    try:
        return int(record["tasks"]["computed"])  # type: ignore[index]
    except (KeyError, TypeError, ValueError):
        return 0


def _run_record(spec: StudySpec, out: Path, this: dict) -> dict:
    """run.json: the fields of the invocation that computed tasks (this one, unless it computed
    nothing and an earlier one did) and ``last_invocation`` (this one)."""
    previous = _read_record(out)
    base = this
    if previous is not None and this["tasks"]["computed"] == 0 and _computed(previous) > 0:
        base = {k: previous[k] for k in RECORD_KEYS if k in previous}
    return {"study": spec.name, **base, "last_invocation": this}


def _run_line(record: dict) -> str:
    """The report's line on the run that computed the tasks (from run.json's fields)."""
    try:
        wall, tasks = float(record["wall_time_s"]), record["tasks"]
        computed, total = int(tasks["computed"]), int(tasks["total"])
        where, cpu = record["backend"], record.get("cpu_count")
        load = [math.nan if v is None else float(v)
                for v in (record.get("load_average_1min") or (None, None))][:2]
    except (KeyError, TypeError, ValueError, IndexError):
        return "Report rebuilt from stored results (no run record found)."
    return (f"Wall time {wall:.1f} s ({tasks_phrase(computed, total)}; {where}; {cpu} cores, "
            f"1-min load average {load[0]:.1f} at the start and {load[1]:.1f} at the end: "
            "wall-clock step times grow with the load; costs per step are CPU time, which "
            "does not).")


def run(spec: StudySpec, config: Any, out: Path | str | None = None, *, workers: int = 2,
        scheduler: str | None = None, progress: bool = True, profile: str | None = None,
        task_timeout_s: float | None = None, allow_mixed: bool = False) -> Outcome:
    """Run (or continue) a study in ``out`` (default: the study's folder under reports/).

    task_timeout_s: time limit of one task in seconds (None: none; a task over it is recorded
    as an error). allow_mixed: reuse stored tasks computed by other code or another evaluator.
    Raises :class:`~workbench.study.config_io.ConfigError` (a
    :class:`~workbench.study.folder.RunFolderError` for a folder of another run, of someone
    else's files or in use; a :class:`~workbench.study.scheduler.SchedulerError`) before
    anything is written; :class:`~workbench.study.execute.TasksFailed` listing the tasks that
    raised (a timed-out task is one; tracebacks in errors.json);
    :class:`~workbench.study.StudyInterrupted` on Ctrl-C (rerun to continue);
    :class:`~workbench.study.io.StorageError` when a file cannot be written."""
    if not isinstance(config, spec.config_type):
        raise ConfigError(f"config = {type(config).__name__} is invalid: study {spec.name!r} "
                          f"takes a {spec.config_type.__name__}")
    try:
        check_workers(workers)
        check_timeout(task_timeout_s)
    except ValueError as exc:  # before anything is written, as a config error
        raise ConfigError(str(exc)) from exc
    t0, load0 = time.perf_counter(), os.getloadavg()[0]
    assert spec.default_out is not None  # set by StudySpec.__post_init__
    out = _user_path(out or spec.default_out)
    dry = declare(spec, config)[0]
    with scheduler_client(scheduler) as (client, _), claim(out, study_manifest(dry)):
        if not allow_mixed:  # before the study prepares anything
            refuse_mixed(dry, out)
        atomic_write_text(out / "config.toml", config_io.dump(
            config, header=f"resolved config of this run; rerun: workbench run {spec.name} "
                           f"--config {out / 'config.toml'} --out {out}"))
        study, finished = _prepared(spec, config, out)
        result = run_study(study, out, workers=workers, scheduler=client, progress=progress,
                           task_timeout_s=task_timeout_s, allow_mixed=allow_mixed)
        result.raise_for_errors()
        _cost_pass(spec, study, finished)
        summary = _summarise(spec, study, finished)
        where = f"scheduler {scheduler}" if scheduler else f"{workers} workers"
        this = {"profile": profile, "tasks": {"total": result.n_tasks,
                                              "computed": result.computed,
                                              "loaded": result.loaded},
                "wall_time_s": time.perf_counter() - t0, "backend": where,
                "cpu_count": os.cpu_count(), "load_average_1min": (load0, os.getloadavg()[0])}
        record = _run_record(spec, out, this)
        atomic_write_json(out / RUN_FILE, record)
        report = spec.fn("report")(dataclasses.replace(finished, run_line=_run_line(record)),
                                   summary)
    for line in summary.lines:
        log.info("%s", line)
    return Outcome(summary, result, Path(report))


def rebuild_report(spec: StudySpec, out: Path | str) -> Path:
    """Rebuild summary.json and report.md of a finished run from its stored results (nothing
    is computed; run.json, the record of the run, is left as it is). The config is the
    manifest's (the run's config.toml where the manifest holds null for an inf or NaN)."""
    out = _user_path(out)
    if not (out / MANIFEST).is_file():
        raise ConfigError(f"{out}: no readable manifest.json; run `workbench run {spec.name} "
                          f"--out {out}` first")
    with locked(out):
        try:
            config = _stored_config(spec, out)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{out / 'config.toml'}: {exc}; the run's config.toml was "
                              "edited or cut short: restore it, or rerun the study") from exc
        study, finished = _prepared(spec, config, out)
        wanted = study.stage(finished.store.outputs_of(finished.ids))
        missing = len(wanted) - len(finished.store.finished(finished.ids[t] for t in wanted))
        if missing:
            raise ConfigError(f"{out}: {missing} of {len(wanted)} tasks are not finished; "
                              f"`workbench run {spec.name} --config {out / 'config.toml'} "
                              f"--out {out}` completes them")
        summary = _summarise(spec, study, finished)
        record = _read_record(out) or {}
        return Path(spec.fn("report")(dataclasses.replace(finished, run_line=_run_line(record)),
                                      summary))

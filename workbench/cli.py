"""The ``workbench`` command: list, run, show-config, report.

Studies come from the registry (:func:`workbench.study.spec.registry`: the modules listed in
``studies/registry.py`` and in ``$WORKBENCH_STUDIES``, each defining ``STUDY``). A run's config
is resolved in layers, then checked before any work starts (:mod:`workbench.study.runner`):
the config dataclass's defaults <- the profile's TOML file (``--profile``; the study's default
profile when neither --profile nor --config is given) <- ``--config FILE`` <- each
``--set key=value`` (dotted keys for nested fields, values as TOML literals).

Every path argument (``--config``, ``--out``, ``--root``, a report's FOLDER) has a leading ``~``
or ``~user`` expanded when the command line is parsed, so the checks and the writes use the same
path. The library's progress and status lines (loggers ``workbench.*``) are printed by a handler
set up here: INFO and below to stdout, warnings and errors to stderr; ``-q`` keeps only the
warnings and errors.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import sys
import textwrap
from pathlib import Path

from workbench.codegen.toolchain import check_environment
from workbench.study import config_io
from workbench.study.checkout import StudiesLocationError
from workbench.study.config_io import ConfigError
from workbench.study.execute import TasksFailed
from workbench.study.io import StorageError
from workbench.validation import UserError

DESCRIPTION = """\
SAIS Workbench: run the studies, show their configs, build the report site.

A run's config is resolved in layers and checked before any work starts:
  the config dataclass's defaults
  <- the profile's TOML file (--profile; "quick" when neither --profile nor --config is given)
  <- --config FILE
  <- each --set key=value (dotted keys for nested fields, values as TOML literals)
A study plugs in with STUDY = StudySpec(...) in its package, profile TOML files beside it and
one line in studies/registry.py (or its module name in $WORKBENCH_STUDIES).
"""

EPILOG = """\
examples:
  workbench list
  workbench run tracking                              # quick profile, reports/tracking_comparison
  workbench run tracking --profile paper --workers 2
  workbench run tracking --set noise_std=5 --set methods='["bas"]' --out /tmp/bas5
  workbench run tracking --profile full --scheduler tcp://host:8786
  workbench show-config tracking --profile paper > paper.toml   # edit, then:
  workbench run tracking --config paper.toml
  workbench run navigation --profile paper --dry-run  # task count and estimated time
  workbench report                                    # reports/index.html
  workbench report /tmp/bas5                          # /tmp/bas5/report.html (any run folder)

exit status: 0 done; 1 the run could not finish (tasks that raised or timed out are recorded in
OUT/errors.json and retried by a rerun; a file that cannot be written); 2 an input that is not
allowed (config, argument, study registration, environment variable, compiler); 130 interrupted
"""

def registry() -> dict:
    from workbench.study.spec import registry as load

    return load()


def _entry(name: str):
    reg = registry()
    if name not in reg:
        import difflib

        close = difflib.get_close_matches(name, list(reg), n=1)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        raise ConfigError(f"unknown study {name!r}{hint} (studies: {', '.join(reg)})")
    return reg[name]


# --------------------------------------------------------------------------------- logging
class _MessageHandler(logging.Handler):
    """Prints the bare message: INFO and below to the current stdout, warnings to stderr."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            stream = sys.stderr if record.levelno >= logging.WARNING else sys.stdout
            print(self.format(record), file=stream, flush=True)
        except Exception:  # logging must never raise
            self.handleError(record)


_HANDLER = _MessageHandler()
_HANDLER.setFormatter(logging.Formatter("%(message)s"))


@contextlib.contextmanager
def terminal_logging(quiet: bool = False):
    """While a command runs, show the library's log lines (loggers ``workbench.*``) on the
    terminal: INFO and up, or only warnings and errors when ``quiet``. The logger's level and
    handlers are restored afterwards (main() may be called from other code)."""
    logger = logging.getLogger("workbench")
    level, added = logger.level, _HANDLER not in logger.handlers
    if added:
        logger.addHandler(_HANDLER)
    logger.setLevel(logging.WARNING if quiet else logging.INFO)
    try:
        yield
    finally:
        logger.setLevel(level)
        if added:
            logger.removeHandler(_HANDLER)


# ----------------------------------------------------------------------------- subcommands
def cmd_list(args) -> int:
    from workbench.problem.catalogue import MODELS
    from workbench.scenarios import methods
    from workbench.scenarios.systems import SYSTEMS

    reg = registry()
    print("studies (workbench run NAME [--profile P]):")
    for e in reg.values():
        print(f"  {e.name:15s} profiles: {', '.join(e.profiles):18s} -> {e.default_out}")
        print(textwrap.indent(textwrap.fill(e.description, 80), " " * 18))
    print("\nmethods (navigation_setup(system=...).controller(NAME)):")
    for s in methods.methods():
        kind = f"robust, {s.feedback} feedback" if s.robust else "sampling"
        print(f"  {s.name:15s} {s.label} ({kind}): {s.mechanism}")
    print("\nsystems (navigation_setup(system=NAME)):")
    for sysm in SYSTEMS.values():
        print(f"  {sysm.name:18s} {sysm.label}; disturbed states {', '.join(sysm.disturbed)}")
    print("\nmodels:")
    for name, entry in MODELS.items():
        print(f"  {name:18s} " + textwrap.fill(f"{entry.text}; {entry.call}", 78,
                                               subsequent_indent=" " * 21))
    print(f"  {'your own':18s} " + textwrap.fill(
        "any discrete-time CasADi SX model: workbench.Model.from_expressions(name, x, u, "
        "x_next, dt=..., h=...) (README: Bring your own model)", 78,
        subsequent_indent=" " * 21))
    return 0


def cmd_show_config(args) -> int:
    from workbench.study.runner import resolve_config

    entry = _entry(args.study)
    cfg = resolve_config(entry, args.profile, args.config, args.set)
    src = " ".join(["workbench show-config", entry.name] +
                   ([f"--profile {args.profile}"] if args.profile else []) +
                   ([f"--config {args.config}"] if args.config else []) +
                   [f"--set {s}" for s in args.set])
    print(config_io.dump(cfg, header=f"{src}\nresolved config of {entry.config_type.__name__}; "
                                     f"run with: workbench run {entry.name} --config FILE"),
          end="")
    return 0


def cmd_run(args) -> int:
    from workbench.study.execute import check_timeout
    from workbench.study.runner import declare, resolve_config
    from workbench.study.store import study_manifest
    from workbench.validation import writable_dir

    entry = _entry(args.study)
    cfg = resolve_config(entry, args.profile, args.config, args.set)  # fails before any work
    if args.workers < 0:
        raise ConfigError(f"--workers = {args.workers} is invalid: must be >= 0 (0: in this "
                          "process)")
    try:  # checked before a dry run too: a value is used or refused, never ignored
        check_timeout(args.task_timeout)
    except ValueError as exc:
        raise ConfigError(f"--task-timeout {args.task_timeout:g}: {exc}") from exc
    profile = args.profile or (entry.default_profile if args.config is None else None)
    if args.dry_run:
        from workbench.study.io import dumps_json

        declared = declare(entry, cfg)  # once: a large study declares in seconds
        manifest = study_manifest(declared[0])
        print(dumps_json({"profile": profile, **manifest}, indent=1, sort_keys=True))
        out = args.out or entry.default_out
        print(estimate(entry, cfg, manifest["n_tasks"], out, args.workers, args.scheduler,
                       declared), file=sys.stderr)
        staged = staged_estimate(entry, cfg, args.workers, args.scheduler, declared)
        if staged:
            print(staged, file=sys.stderr)
        return 0
    if args.scheduler:  # a malformed or unreachable scheduler fails before --out is created
        from workbench.study.scheduler import check_scheduler

        check_scheduler(args.scheduler)
    try:
        out = writable_dir("--out", args.out or entry.default_out)
    except ValueError as exc:
        raise ConfigError(str(exc)) from exc
    from workbench.study import StudyInterrupted
    from workbench.study.runner import run

    try:
        outcome = run(entry, cfg, out, workers=args.workers, scheduler=args.scheduler,
                      profile=profile, progress=not getattr(args, "quiet", False),
                      task_timeout_s=args.task_timeout, allow_mixed=args.allow_mixed)
    except StudyInterrupted:
        print("interrupted; rerun the same command to continue", file=sys.stderr)
        return 130
    print(f"wrote {outcome.report}")
    from workbench.study.report_site import render_run

    print(f"wrote {render_run(out)}")
    return 0


def _duration(seconds: float) -> str:
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def _record(d: Path, study: str) -> dict | None:
    """run.json of a finished run of ``study`` in ``d`` with a usable time per task."""
    try:
        rec = json.loads((Path(d) / "run.json").read_text())
        ok = (rec.get("study") == study and rec["tasks"]["computed"] > 0
              and rec["wall_time_s"] > 0)
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None
    return rec if ok else None


def _stored(entry, cfg, out: Path, declared=None) -> int:
    """How many of the config's tasks ``out`` already holds a file for (read only: nothing is
    created; a file that later proves corrupt is counted). ``declared``: the config's
    (study, plan) when already declared."""
    from workbench.study.runner import declare

    tasks = Path(out) / "tasks"
    if not tasks.is_dir():
        return 0
    present = {p.stem for p in tasks.glob("*.npz")}
    study = (declared or declare(entry, cfg))[0]
    return len(present.intersection(study.task_ids()))


def estimate(entry, cfg, n_tasks: int, out: Path, workers: int,
             scheduler: str | None, declared=None) -> str:
    """One line for a dry run: the task count, how many are stored already, and the time the
    rest would take, estimated from the last run's wall time per task (run.json in ``out`` or
    in the study's default folder) scaled to ``workers``; "unknown" without such a record."""
    stored = _stored(entry, cfg, out, declared)
    todo = n_tasks - stored
    head = (f"dry run: {n_tasks} tasks" + (f" ({stored} already stored in {out}, {todo} to "
                                            "compute)" if stored else ""))
    for d in dict.fromkeys([Path(out), Path(entry.default_out)]):
        rec = _record(d, entry.name)
        if rec is None:
            continue
        computed, wall = rec["tasks"]["computed"], rec["wall_time_s"]
        backend = str(rec.get("backend", ""))
        then = int(backend.split()[0]) if backend.split()[:1] and backend.split()[0].isdigit() \
            else None
        now = None if scheduler else max(workers, 1)
        per_task = wall / computed * (max(then, 1) if then is not None and now else 1)
        total = todo * per_task / (now or 1)
        where = f"{now} worker{'s' if now != 1 else ''}" if now else f"scheduler {scheduler}"
        profile = rec.get("profile") or "a config file"
        return (f"{head}; estimated {_duration(total)} on {where} (from {d / 'run.json'}: "
                f"{wall:.0f} s for {computed} tasks on {backend or 'unknown back end'}, profile "
                f"{profile}; rough: tasks of another config or a busier machine take longer)")
    return (f"{head}; estimated time unknown (no finished run of {entry.name} in {out} or "
            f"{entry.default_out} to time a task)")


def staged_estimate(entry, cfg, workers: int, scheduler: str | None,
                    declared=None) -> str | None:
    """For a study that runs in rounds (group-sequential): the tasks of its first round and
    of every round, and, when the study's plan has a cost model (``plan.cost_s(task)``:
    seconds of one core per task), the time of each on ``workers``; None for a study
    without rounds."""
    from workbench.study.runner import declare

    study, plan = declared or declare(entry, cfg)
    if study.stages is None:
        return None
    first = study.stage(lambda task: None)
    line = (f"runs in rounds: {len(first)} tasks in the first; {len(study.tasks)} if every "
            "comparison needs every round")
    cost = getattr(plan, "cost_s", None)
    if cost is None:
        return line
    now = None if scheduler else max(workers, 1)
    where = f" on {now} worker{'s' if now != 1 else ''}" if now else ""
    lo, hi = (sum(cost(t) for t in ts) / (now or 3600) for ts in (first, study.tasks))
    unit = _duration if now else (lambda h: f"{h:.1f} core-hours")
    return (f"{line}; estimated {unit(lo)} to {unit(hi)}{where} (the study's cost model: "
            "seconds per task measured on a 2-core machine; rough)")


def _run_study(folder: Path, reg: dict):
    """The study that wrote the run folder ``folder`` (from run.json, else manifest.json)."""
    problems = []
    for name, key in (("run.json", "name"), ("manifest.json", "store_name")):
        path = folder / name
        if not path.is_file():
            continue
        try:
            data = json.loads(path.read_text())
            study = data["study"] if isinstance(data, dict) else None
        except (OSError, ValueError, KeyError) as exc:
            problems.append(f"{path} is unreadable ({type(exc).__name__}: {exc}; truncated?)")
            continue
        found = [e for e in reg.values() if getattr(e, key) == study]
        if found:
            return found[0]
        problems.append(f"{path} names the study {study!r}, which is not registered "
                        f"(studies: {', '.join(reg)})")
    raise ConfigError(f"{folder}: cannot tell which study wrote this folder: "
                      + ("; ".join(problems) or "it holds no manifest.json")
                      + f". Rerun it with `workbench run STUDY --out {folder}`")


def cmd_report(args) -> int:
    from workbench.study.report_site import build_site, render_run
    from workbench.study.runner import rebuild_report

    reg = registry()
    root = Path(args.root)
    target = args.study
    if target is not None and not (isinstance(target, str) and target in reg):
        folder = Path(os.path.expanduser(str(target)))
        if not folder.is_dir():
            raise ConfigError(f"{target!r} is neither a study ({', '.join(reg)}) nor a folder")
        if not ((folder / "manifest.json").is_file() or (folder / "run.json").is_file()):
            print(f"wrote {build_site(folder, reg)}")  # a reports root
            return 0
        entry = _run_study(folder, reg)
        print(f"wrote {rebuild_report(entry, folder)}")
        print(f"wrote {render_run(folder)}")
        return 0
    if target is not None:
        entry = _entry(target)
        out = root / entry.default_out.name
        print(f"wrote {rebuild_report(entry, out)}")
    print(f"wrote {build_site(root, reg)}")
    return 0


# ------------------------------------------------------------------------------ the parser
def user_path(text: str) -> Path:
    """A path argument with a leading ``~`` or ``~user`` expanded (once, here)."""
    p = os.path.expanduser(text)
    if p.startswith("~"):
        user = p[1:].split("/", 1)[0]
        raise argparse.ArgumentTypeError(
            f"{text!r}: cannot expand ~{user}: no such user with a home folder (write the path "
            f"as ./{text} for a folder named {'~' + user!r})")
    path = Path(p)
    # ./~name is a folder named ~name: made absolute so that nothing expands it later
    return path.absolute() if str(path).startswith("~") else path


def _study_names() -> str:
    try:
        return ", ".join(registry())
    except Exception as exc:  # help must work even when a study's cli.py is broken
        return f"(registry unavailable: {exc})"


def _config_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("study", help=f"study name: {_study_names()} (see `workbench list`)")
    p.add_argument("--profile", default=None,
                   help="profile: a TOML file in the study's directory (quick, paper, full; "
                        "`workbench list` shows each study's); default: quick, unless --config "
                        "is given")
    p.add_argument("--config", type=user_path, default=None, metavar="FILE",
                   help="TOML file over the profile (e.g. the output of show-config or a run's "
                        "config.toml)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override one field; dotted keys for nested fields (base.noise_std=5), "
                        "values as TOML literals (5, 1e-3, true, \"after\", [1, 2]); "
                        "repeatable")


def _quiet(p: argparse.ArgumentParser, default) -> None:
    p.add_argument("-q", "--quiet", action="store_true", default=default,
                   help="print only warnings and errors (no progress or status lines)")


def parser() -> argparse.ArgumentParser:
    from workbench import __version__

    ap = argparse.ArgumentParser(
        prog="workbench", description=DESCRIPTION, epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--version", action="version", version=f"workbench {__version__}")
    _quiet(ap, False)
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("list", help="studies, controllers and models",
                       description="List the registered studies (name, profiles, output "
                                   "directory), the navigation controllers and the models.")
    p.set_defaults(fn=cmd_list)

    p = sub.add_parser("run", help="run (or continue) a study",
                       description="Run or continue a study: resolve and check its config, "
                                   "write OUT/config.toml, compute the missing tasks, write the "
                                   "tidy data, summary.json, figures and report.md to OUT. "
                                   "Ctrl-C stops within seconds; the same command continues.",
                       epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    _config_args(p)
    p.add_argument("--workers", type=int, default=2,
                   help="local worker processes (0: in this process; default 2)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="Dask scheduler address (tcp://host:8786) instead of local workers")
    p.add_argument("--out", type=user_path, default=None, metavar="DIR",
                   help="run directory (default: the study's, e.g. reports/tracking_comparison)")
    p.add_argument("--dry-run", action="store_true",
                   help="check the config and print the run's manifest (study, seed, config, "
                        "fingerprint, task count) on stdout and the task count with an "
                        "estimated time on stderr, without computing or writing anything")
    p.add_argument("--task-timeout", type=float, default=None, metavar="SECONDS",
                   help="stop a task that runs longer and record it as an error (retried on "
                        "the next run); default: no limit")
    p.add_argument("--allow-mixed", action="store_true",
                   help="reuse stored tasks computed by other code or another evaluator "
                        "(refused by default)")
    _quiet(p, argparse.SUPPRESS)
    p.set_defaults(fn=cmd_run)

    p = sub.add_parser("show-config", help="print a study's fully resolved config as TOML",
                       description="Print the fully resolved config (every field) as TOML; "
                                   "feeding it back with --config gives the same run.")
    _config_args(p)
    p.set_defaults(fn=cmd_show_config)

    p = sub.add_parser("report", help="build reports/index.html, or one run folder's report",
                       description="Build ROOT/index.html: every study's report (as HTML), "
                                   "figures, summary tables, manifest and config, with the "
                                   "paper's numbers beside ours; readable offline. With STUDY, "
                                   "first rebuild that study's report.md in ROOT from its "
                                   "stored results (nothing is computed). With FOLDER, a run "
                                   "folder anywhere (it holds manifest.json): rebuild its "
                                   "report.md and write FOLDER/report.html; a FOLDER without "
                                   "manifest.json is a reports root, as --root.")
    p.add_argument("study", nargs="?", default=None, metavar="STUDY|FOLDER",
                   help="a study whose report in ROOT to rebuild, or a run folder")
    p.add_argument("--root", type=user_path, default=Path("reports"),
                   help="reports directory (default: reports)")
    _quiet(p, argparse.SUPPRESS)
    p.set_defaults(fn=cmd_report)

    return ap


def _compile_error(exc: BaseException) -> bool:
    """Whether ``exc`` is the code cache's CompileError (a compiler that failed or ran past
    WORKBENCH_COMPILE_TIMEOUT); its module is not imported just to ask."""
    cache = sys.modules.get("workbench.codegen.cache")
    return cache is not None and isinstance(exc, cache.CompileError)


def main(argv: list[str] | None = None) -> int:
    """Run one command; its exit code: 0 done, 1 the run could not finish (tasks that raised
    or timed out, recorded in errors.json and retried by a rerun; a file that cannot be
    written), 2 an input that is not allowed (a config value, an argument, a study's
    registration, an environment variable, the compiler), 130 interrupted. Each failure is a
    message on stderr naming the problem, not a traceback."""
    ap = parser()
    args = ap.parse_args(argv)
    with terminal_logging(getattr(args, "quiet", False)):
        try:
            check_environment()  # a bad WORKBENCH_* value stops here, named
            return args.fn(args)
        except (UserError, StudiesLocationError) as exc:
            print(f"workbench {args.command}: error: {exc}", file=sys.stderr)
            return 2
        except (StorageError, TasksFailed) as exc:  # StorageError names the file
            print(f"workbench {args.command}: error: {exc}", file=sys.stderr)
            return 1
        except Exception as exc:
            if not _compile_error(exc):
                raise
            print(f"workbench {args.command}: error: {exc}", file=sys.stderr)
            return 2


if __name__ == "__main__":
    sys.exit(main())

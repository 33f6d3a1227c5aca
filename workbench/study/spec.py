"""What a study declares: its config, tasks, summary and report (:class:`StudySpec`).

The framework (:mod:`workbench.study.runner`) does everything else once for every study:
resolving the config from its profile files, preparing shared inputs in the coordinating process,
executing the tasks resumably, writing ``config.toml``, ``summary.json``, ``run.json`` and the
report. A study package ``studies/<pkg>/`` holds one ``<profile>.toml`` per profile and defines
``STUDY = StudySpec(...)`` in its ``__init__.py``; one line in ``studies/registry.py`` registers
it (or, for a study outside this repository, the ``WORKBENCH_STUDIES`` environment variable:
comma-separated module names).
"""

from __future__ import annotations

import dataclasses
import importlib
import traceback
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import workbench.environment as environment
from workbench.study.checkout import use_checkout_studies
from workbench.study.config_io import ConfigError
from workbench.validation import fail

if TYPE_CHECKING:
    from workbench.study.cost_pass import CostPlan
    from workbench.study.store import RunStore


class RegistrationError(ConfigError):
    """A study's registration that cannot be used: its module cannot be imported, defines no
    ``STUDY`` or a wrong one, or one of its ``"module:function"`` entry points is missing; the
    message names the study (or module) and what is wrong."""


class PaperRow(NamedTuple):
    """One number of the paper beside ours, for the report site."""

    quantity: str
    paper: str
    ours: str
    note: str = ""


@dataclass(frozen=True)
class Declaration:
    """A study's tasks for one config.

    tasks: frozen task descriptions in dispatch order (slow first); run_task(task, ctx,
    config=..., prepared=...) -> TaskOutput, a module-level function (the framework binds the
    config and, when the study prepares something, the prepared value); fingerprint: every input
    the results depend on beyond the task descriptions (enters each task id); version: bump when
    the meaning of stored results changes; plan: the study's own grouping of its tasks (cells),
    handed back to its summary; stages: for a study that decides between rounds which tasks
    to run (see :meth:`workbench.study.tasks.Study.stage`), None to run every task."""

    tasks: tuple[Any, ...]
    run_task: Callable[..., Any]
    fingerprint: Mapping[str, Any] = field(default_factory=dict)
    version: int = 1
    plan: Any = None
    stages: Callable[..., Any] | None = None


@dataclass(frozen=True)
class Finished:
    """A run whose tasks are all stored: what a study's summary and report read."""

    config: Any
    out: Path
    store: RunStore
    plan: Any
    ids: Mapping[Any, str]  # task -> task id (every declared task; a staged run ran a subset)
    prepared: Any = None
    run_line: str = ""  # wall time, tasks, back end and load: for the report


@dataclass(frozen=True)
class Summary:
    """A study's summary: ``data`` is written as ``summary.json`` (after ``"study"``; it must
    depend only on the results), ``value`` is the study's typed summary for its report, and
    ``lines`` are printed when a run ends."""

    data: Mapping[str, Any]
    value: Any = None
    lines: tuple[str, ...] = ()


@dataclass(frozen=True)
class StudySpec:
    """A study as the framework runs it.

    name: ``workbench run NAME``; description: one line for ``workbench list``; config_type: the
    study's frozen config dataclass (validated in ``__post_init__``, with an integer ``seed``);
    directory: the study's folder, holding one ``<profile>.toml`` per profile.
    tasks(config) -> :class:`Declaration`; summarise(finished) -> :class:`Summary`;
    report(finished, summary) -> path of the report.md it wrote (figures beside it).
    Each function may be given as ``"module:function"``, imported on first use, so that listing
    the studies and checking a config stay fast.
    Optional: prepare(config, out) -> a value computed once per run in the coordinating process
    and handed to every task (a calibration, shared constants; deterministic in the config);
    paper(out) -> [PaperRow] for the report site; aliases: short ``--set`` keys -> dotted keys;
    cost(finished) -> :class:`~workbench.study.cost_pass.CostPlan`: the methods' cost pass,
    measured once per run in the coordinating process after every task has finished
    (:mod:`workbench.study.cost_pass`; the summary reads it with
    :func:`~workbench.study.cost_pass.stored_pass`);
    figure: the headline figure's file name; default_profile; store_name: the name that enters
    task ids (default: the folder's name); default_out: ``reports/<folder name>``.
    """

    name: str
    description: str
    config_type: type
    directory: Path
    tasks: Callable[[Any], Declaration] | str
    summarise: Callable[[Finished], Summary] | str
    report: Callable[[Finished, Summary], Path] | str
    prepare: Callable[[Any, Path], Any] | str | None = None
    paper: Callable[[Path], list[PaperRow]] | str | None = None
    cost: Callable[[Finished], CostPlan] | str | None = None
    aliases: Mapping[str, str] = field(default_factory=dict)
    figure: str | None = None
    default_profile: str = "quick"
    store_name: str = ""
    default_out: Path | None = None

    def __post_init__(self) -> None:
        if not self.name or not self.name.replace("-", "").replace("_", "").isalnum():
            raise fail("StudySpec.name", self.name, "must be letters, digits, - and _")
        if not (isinstance(self.config_type, type) and dataclasses.is_dataclass(self.config_type)):
            raise fail("StudySpec.config_type", self.config_type, "must be a dataclass")
        if "seed" not in {f.name for f in dataclasses.fields(self.config_type)}:
            raise fail("StudySpec.config_type", self.config_type.__name__,
                       "must have an integer field 'seed' (the root of every random stream)")
        directory = Path(self.directory)
        object.__setattr__(self, "directory", directory)
        if not self.profiles:
            raise fail("StudySpec.directory", str(directory), "holds no <profile>.toml file")
        if self.default_profile not in self.profiles:
            raise fail("StudySpec.default_profile", self.default_profile,
                       f"must be one of the profiles {sorted(self.profiles)}")
        for name in ("tasks", "summarise", "report", "prepare", "paper", "cost"):
            value = getattr(self, name)
            if value is None and name in ("prepare", "paper", "cost"):
                continue
            if not (callable(value) or (isinstance(value, str) and value.count(":") == 1)):
                raise fail(f"StudySpec.{name}", value, "must be callable or 'module:function'")
        object.__setattr__(self, "store_name", self.store_name or directory.name)
        object.__setattr__(self, "default_out",
                           Path(self.default_out or Path("reports") / directory.name))

    def fn(self, name: str) -> Callable[..., Any]:
        """The study's function ``name`` (tasks, summarise, report, prepare, paper, cost),
        imported if it was given as ``"module:function"``; ValueError for an optional one
        (prepare, paper, cost) that the study does not declare; :class:`RegistrationError`
        naming the study and the entry point when its module cannot be imported or has no
        such function."""
        value = getattr(self, name)
        if value is None:
            raise fail(f"StudySpec.{name}", None, f"is not declared by study {self.name!r}")
        if isinstance(value, str):
            module, attr = value.split(":")
            where = f"study {self.name!r}: {name} = {value!r}"
            loaded = _import(module, f"{where}: module {module!r}",
                             "fix the entry point in the study's StudySpec")
            value = getattr(loaded, attr, None)
            if not callable(value):
                found = "is not a function" if value is not None else "does not exist"
                raise RegistrationError(f"{where}: {module}.{attr} {found}; the entry point "
                                        "must name a function, as 'module:function'")
        return value

    @property
    def profiles(self) -> dict[str, Path]:
        """Every ``<profile>.toml`` in the study's folder, by profile name."""
        return {p.stem: p for p in sorted(self.directory.glob("*.toml"))}


REGISTRY_MODULE = "studies.registry"
ENVIRONMENT = environment.STUDIES


def registry(modules: list[str] | None = None) -> dict[str, StudySpec]:
    """Every registered study by name: the modules listed in ``studies/registry.py`` (read from
    the checkout beside ``workbench``: :func:`workbench.study.checkout.use_checkout_studies`)
    plus those in ``$WORKBENCH_STUDIES`` (comma-separated), each defining ``STUDY``."""
    if modules is None:
        use_checkout_studies()
        modules = list(importlib.import_module(REGISTRY_MODULE).STUDIES)
        modules += list(environment.modules(ENVIRONMENT))
    out: dict[str, StudySpec] = {}
    where: dict[str, str] = {}
    for name in modules:
        spec = getattr(_import(name, f"study module {name!r} (registered in {REGISTRY_MODULE} "
                               f"or ${ENVIRONMENT})", "fix or remove the registration"),
                       "STUDY", None)
        if not isinstance(spec, StudySpec):
            found = "defines no STUDY" if spec is None else f"has STUDY = {type(spec).__name__}"
            raise RegistrationError(f"study module {name!r} {found}; a registered study "
                                    "module defines STUDY = workbench.study.StudySpec(...)")
        if spec.name in out:
            raise RegistrationError(f"two studies are named {spec.name!r} (modules "
                                    f"{where[spec.name]!r} and {name!r}); each registered "
                                    "study needs its own name")
        out[spec.name], where[spec.name] = spec, name
    return out


def _missing(exc: ImportError, module: str) -> bool:
    """Whether ``exc`` says that ``module`` itself (or a package above it) does not exist."""
    missing = getattr(exc, "name", None)
    return isinstance(exc, ModuleNotFoundError) and missing is not None and (
        module == missing or module.startswith(missing + "."))


def _import(module: str, what: str, fix: str) -> Any:
    """``importlib.import_module(module)``; :class:`RegistrationError` starting with ``what``
    when the module does not exist, or when importing it raises (a ``StudySpec`` refused, a
    typo in its code): the error and the line of the study's code that raised it."""
    try:
        return importlib.import_module(module)
    except Exception as exc:
        if isinstance(exc, ImportError) and _missing(exc, module):
            raise RegistrationError(f"{what} does not exist ({exc}); {fix}") from exc
        raise RegistrationError(f"{what} cannot be imported: {type(exc).__name__}: {exc}"
                                f"{_where(exc)}; {fix}") from exc


def _where(exc: BaseException) -> str:
    """`` at FILE:LINE``: the last line outside the library (and the import machinery) that
    raised ``exc``, or where a syntax error is."""
    if isinstance(exc, SyntaxError) and exc.filename and exc.lineno:
        return f" at {exc.filename}:{exc.lineno}"
    library = str(Path(__file__).resolve().parents[1])
    frames = [f for f in traceback.extract_tb(exc.__traceback__)
              if not f.filename.startswith((library, "<frozen"))]
    return f" at {frames[-1].filename}:{frames[-1].lineno}" if frames else ""

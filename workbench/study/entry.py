"""How a study plugs into the ``workbench`` command line: one :class:`StudyEntry` per study.

A study ``studies/<pkg>/`` joins the registry by adding ``studies/<pkg>/cli.py`` that defines
``ENTRY = StudyEntry(...)`` and one TOML file per profile beside it (``quick.toml``,
``paper.toml``, ...). Nothing else is edited: :func:`discover` imports every ``studies.*.cli``.
Keep ``cli.py`` light (import the study's heavy modules inside ``run``/``report``), so that
``workbench list`` and config errors stay fast.
"""

from __future__ import annotations

import dataclasses
import importlib
import pkgutil
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

from workbench.validation import fail


class PaperRow(NamedTuple):
    """One number of the paper beside ours, for the report site."""

    quantity: str
    paper: str
    ours: str
    note: str = ""


@dataclass(frozen=True)
class StudyEntry:
    """A study as the command line sees it.

    name: ``workbench run NAME``; description: one line for ``workbench list``;
    config_type: the study's frozen config dataclass (fields typed, validated in
    ``__post_init__``); profiles: profile name -> TOML file (:func:`profiles_in`);
    run(config, out, workers, scheduler) -> path of the report.md it wrote (resumable; raise on
    failure); default_out: the run directory when ``--out`` is not given.
    Optional: report(out) -> report.md rebuilt from the stored results without computing;
    declare(config) -> the :class:`~workbench.study.Study` a run would execute (gives the dry-run
    manifest: tasks, fingerprint); paper(out) -> [PaperRow] the paper's numbers beside ours;
    aliases: short ``--set`` keys -> dotted config keys; figure: the headline figure's file name
    in ``out``; default_profile: the profile used when neither --profile nor --config is given.
    """

    name: str
    description: str
    config_type: type
    profiles: Mapping[str, Path]
    run: Callable[[Any, Path, int, str | None], Path]
    default_out: Path
    report: Callable[[Path], Path] | None = None
    declare: Callable[[Any], Any] | None = None
    paper: Callable[[Path], list[PaperRow]] | None = None
    aliases: Mapping[str, str] = field(default_factory=dict)
    figure: str | None = None
    default_profile: str = "quick"

    def __post_init__(self) -> None:
        if not self.name or not self.name.replace("-", "").replace("_", "").isalnum():
            raise fail("StudyEntry.name", self.name, "must be letters, digits, - and _")
        if not (isinstance(self.config_type, type) and dataclasses.is_dataclass(self.config_type)):
            raise fail("StudyEntry.config_type", self.config_type, "must be a dataclass")
        if not self.profiles:
            raise fail("StudyEntry.profiles", self.profiles, "must name at least one TOML file")
        for name, path in self.profiles.items():
            if not Path(path).is_file():
                raise fail(f"StudyEntry.profiles[{name!r}]", str(path), "file does not exist")
        if self.default_profile not in self.profiles:
            raise fail("StudyEntry.default_profile", self.default_profile,
                       f"must be one of the profiles {sorted(self.profiles)}")
        object.__setattr__(self, "default_out", Path(self.default_out))


def profiles_in(directory: Path | str) -> dict[str, Path]:
    """Every ``<profile>.toml`` in a study's directory, by profile name."""
    return {p.stem: p for p in sorted(Path(directory).glob("*.toml"))}


def discover(package: str = "studies") -> dict[str, StudyEntry]:
    """The registry: ``ENTRY`` of every ``<package>.<pkg>.cli`` module, by study name."""
    pkg = importlib.import_module(package)
    out: dict[str, StudyEntry] = {}
    for info in sorted(pkgutil.iter_modules(pkg.__path__), key=lambda m: m.name):
        if not info.ispkg:
            continue
        try:
            mod = importlib.import_module(f"{package}.{info.name}.cli")
        except ModuleNotFoundError as exc:
            if exc.name == f"{package}.{info.name}.cli":
                continue  # a study without a command-line entry (yet)
            raise
        entry = getattr(mod, "ENTRY", None)
        if not isinstance(entry, StudyEntry):
            raise TypeError(f"{mod.__name__}.ENTRY must be a workbench.study.StudyEntry")
        if entry.name in out:
            raise ValueError(f"two studies are named {entry.name!r}")
        out[entry.name] = entry
    return out

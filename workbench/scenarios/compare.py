"""Compare the registered methods on any system from one call: the sampling-safety study
(every method on one sampler, paired by realisation) on a registered system or on a
:class:`~workbench.scenarios.systems.System` of your own."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from workbench.scenarios.systems import SYSTEMS, System
from workbench.validation import fail


def compare_methods(system: System | str, out: Path | str, *, workers: int = 0,
                    progress: bool = False, **config: Any):
    """Run (or continue) the sampling-safety comparison on ``system`` in the folder ``out``
    and return the run's outcome (its report is ``out/report.md``; rerunning continues).

    ``system``: a registered name, a ``"module:function"`` entry, or a System
    (:func:`~workbench.scenarios.model_system.system_from_model`). A System without an
    ``entry`` exists only in this process: it is registered under its name for the run
    (replacing, until the run ends, a system of that name registered before) and runs with
    ``workers=0`` (give it an entry to use worker processes). ``config``: the study's other fields
    (``controllers``, ``variances``, ``realisations``, ``steps``, ``sampler``, ...; see
    ``workbench show-config sampling-safety``)."""
    from workbench.study.runner import run
    from workbench.study.spec import registry

    spec = registry()["sampling-safety"]
    if isinstance(system, System) and system.entry is None:
        if workers:
            raise fail("workers", workers, f"the system {system.name!r} has no entry "
                       "('module:function') to rebuild it in worker processes: use "
                       "workers=0 or build it with system_from_model(..., entry=...)")
        # registered under its name for this run only (in this process); a system of that
        # name registered before (e.g. an earlier version of yours) is put back afterwards
        before = SYSTEMS.pop(system.name, None)
        SYSTEMS[system.name] = system
        try:
            return run(spec, spec.config_type(system=system.name, **config), out,
                       workers=workers, progress=progress)
        finally:
            SYSTEMS.pop(system.name, None)
            if before is not None:
                SYSTEMS[system.name] = before
    if isinstance(system, System):
        name = system.entry
    elif isinstance(system, str):
        name = system
    else:
        raise fail("system", type(system).__name__, "must be a System, a registered name or "
                   "'module:function'")
    return run(spec, spec.config_type(system=name, **config), out, workers=workers,
               progress=progress)


__all__ = ["compare_methods"]

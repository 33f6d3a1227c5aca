"""Methods and systems of your own, loaded by name: every module named in
``$WORKBENCH_PLUGINS`` (comma-separated module names, importable from ``sys.path``) is imported
once, after the built-in methods are registered, and registers what it declares
(``register_method(MethodSpec(...))``, ``register_system(System(...))``). Spawned study workers
inherit the variable, so a study runs a plugin's methods with any number of workers."""

from __future__ import annotations

import importlib

import workbench.environment as environment
from workbench.study.config_io import ConfigError
from workbench.validation import fail

ENV = environment.PLUGINS


def plugin_modules() -> tuple[str, ...]:
    """The module names in ``$WORKBENCH_PLUGINS`` (empty entries skipped)."""
    try:
        return environment.modules(ENV)
    except environment.EnvironmentVariableError as exc:
        raise ConfigError(str(exc)) from None


def load_plugins() -> tuple[str, ...]:
    """Import every module of :func:`plugin_modules`; a module that cannot be imported is a
    :class:`~workbench.study.config_io.ConfigError` (a ValueError) naming the variable, the
    module and the cause. Returns the names."""
    names = plugin_modules()
    for name in names:
        try:
            importlib.import_module(name)
        except ImportError as exc:
            raise ConfigError(str(fail(ENV, name, f"cannot be imported ({exc}); it must be a "
                                       "module name importable from sys.path (set "
                                       "PYTHONPATH)"))) from exc
    return names

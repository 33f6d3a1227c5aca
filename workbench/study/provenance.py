"""What computed a task: the evaluator, its result-changing settings and a hash of the code.

Three things change a task's numbers without changing its config:

- the evaluator: ``"compiled"`` when the process can build C kernels (a C compiler is found,
  :func:`workbench.codegen.toolchain.find_toolchain`), ``"fallback"`` when it cannot (no
  compiler, or ``WORKBENCH_NO_CODEGEN`` on) and the samplers use the NumPy/CasADi evaluation,
  which draws its noise from NumPy instead of the kernels' generator: the same seed gives other
  episodes, so the two must not share one table (common random numbers would silently break);
- the compiled evaluator's settings (:func:`settings`): ``WORKBENCH_VECTOR_MATH`` (libmvec
  results differ from scalar libm by up to 4 ulp) and the extra compiler flags of
  ``WORKBENCH_CFLAGS``. The kernels' block width (``WORKBENCH_VECTOR_BITS``) and the compiler
  are recorded in the manifest (:func:`describe`) but not compared: results do not depend on
  the block width, and the refused flags keep every compiler's results equal to CasADi's
  evaluation;
- the code: :func:`code_hash` is a SHA-256 over the contents of every ``.py``, ``.c``, ``.h``,
  ``.json`` and ``.toml`` file of the installed ``workbench`` package and of the top-level
  package (or module) that defines the study's task function (``studies`` for the registered
  studies), read from disk, so an uncommitted edit counts. Files are taken in sorted order of
  their path inside the package; ``__pycache__`` and hidden folders are skipped; the hash does
  not depend on where the packages are installed. It is computed once per process and package.

:func:`current` (``{"evaluator", "settings", "code_sha256"}``) is stored with every task,
computed in the process that ran it, and a continued run compares it whole; :func:`describe`
adds details for the manifest (compiler and flags, the environment variables as set, the
packages hashed). Limit: ``"compiled"`` says the process *can* compile;
a model whose operations the C emitter cannot translate falls back for that problem alone (with
a warning); that choice is a function of the code, so the code hash covers it on the same
machine.
"""

from __future__ import annotations

import functools
import hashlib
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import workbench.environment as environment

SUFFIXES = (".py", ".c", ".h", ".json", ".toml")
_HASHES: dict[str, str] = {}


def evaluator() -> str:
    """``"compiled"`` when this process can build C kernels, else ``"fallback"``."""
    from workbench.codegen.toolchain import find_toolchain

    return "compiled" if find_toolchain() is not None else "fallback"


def settings() -> dict[str, Any]:
    """The settings that change a compiled task's numbers: ``vector_math`` (bool) and
    ``cflags`` (the extra flags of ``WORKBENCH_CFLAGS``, a list); empty for the fallback
    evaluator, which none of them affects."""
    if evaluator() != "compiled":
        return {}
    return {"vector_math": environment.switch(environment.VECTOR_MATH, True),
            "cflags": list(environment.words(environment.CFLAGS))}


def evaluator_detail() -> dict[str, Any]:
    """The compiler and flags (or why there is none) and the environment variables that choose
    how kernels are built, as set."""
    from workbench.codegen.toolchain import find_toolchain

    tc = find_toolchain()
    names = (environment.NO_CODEGEN, environment.CC, environment.CFLAGS,
             environment.VECTOR_MATH, environment.VECTOR_BITS)
    env = {k: os.environ.get(k) for k in names}
    return {"toolchain": tc.describe() if tc is not None else None,
            "environment": {k: v for k, v in env.items() if v is not None}}


def task_function(fn: Callable) -> Callable:
    """``fn`` with any ``functools.partial`` layers removed."""
    while isinstance(fn, functools.partial):
        fn = fn.func
    return fn


def code_roots(fn: Callable | None = None) -> tuple[Path, ...]:
    """The installed ``workbench`` package, then the top-level package (a folder) or module (a
    file) that defines ``fn`` when it is another one."""
    roots = [Path(__file__).resolve().parents[1]]  # the workbench package
    if fn is not None:
        fn = task_function(fn)
        name = getattr(fn, "__module__", None) or type(fn).__module__
        top = sys.modules.get(name.split(".")[0])
        where = getattr(top, "__file__", None) if top is not None else None
        if where:
            path = Path(where).resolve()
            root = path.parent if path.name == "__init__.py" else path
            if root not in roots:
                roots.append(root)
    return tuple(roots)


def _files(root: Path) -> list[tuple[str, Path]]:
    if root.is_file():
        return [(root.name, root)]
    out = []
    for folder, dirs, names in os.walk(root):
        dirs[:] = [d for d in dirs if d != "__pycache__" and not d.startswith(".")]
        for name in names:
            if name.endswith(SUFFIXES):
                path = Path(folder) / name
                out.append(((Path(root.name) / path.relative_to(root)).as_posix(), path))
    return sorted(out)


def tree_hash(root: Path | str) -> str:
    """SHA-256 over (path inside the package, SHA-256 of the content) of every source file
    under ``root`` (or of the file ``root``); cached per process."""
    key = str(Path(root).resolve())
    if key not in _HASHES:
        h = hashlib.sha256()
        for rel, path in _files(Path(key)):
            h.update(rel.encode() + b"\0" + hashlib.sha256(path.read_bytes()).digest() + b"\n")
        _HASHES[key] = h.hexdigest()
    return _HASHES[key]


def code_hash(fn: Callable | None = None) -> str:
    """The hash of the code a task function runs: :func:`tree_hash` of each of
    :func:`code_roots`, combined."""
    h = hashlib.sha256()
    for root in code_roots(fn):
        h.update(tree_hash(root).encode() + b"\n")
    return h.hexdigest()


def clear_cache() -> None:
    """Forget the hashes computed so far (the next call reads the files again)."""
    _HASHES.clear()


def current(fn: Callable | None = None) -> dict[str, Any]:
    """What this process would record for a task of ``fn``: evaluator, its :func:`settings`
    and code hash."""
    return {"evaluator": evaluator(), "settings": settings(), "code_sha256": code_hash(fn)}


def describe(fn: Callable | None = None) -> dict[str, Any]:
    """:func:`current` with the details a manifest keeps: compiler, environment switches and
    the packages that were hashed."""
    return {**current(fn), **evaluator_detail(),
            "code_roots": [p.name for p in code_roots(fn)]}

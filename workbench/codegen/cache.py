"""Generate C from CasADi Functions, compile it once, cache it by content, verify it on load.

Cache key: sha256 of the generated C text, the compiler path, version and flags, the CasADi
version and the platform. A build writes the source, compiles to a temporary name in the cache
directory, checks the exit status, and publishes the library with ``os.replace`` followed by a
manifest holding the library's sha256. Loading checks that digest (a corrupted library is rebuilt)
and compares every exported Function with its symbolic twin at seeded points; a mismatch rebuilds
the library and loads the rebuilt file (through a private copy when this process already has the
old one open at that path). Libraries are linked with every symbol resolved
(``-Wl,--no-undefined``) and loaded with RTLD_NOW. Generated code without Functions (the sampler
kernels) is checked by its caller (:mod:`workbench.sampling.kernels.verify`), which asks for a
rebuild.
"""

from __future__ import annotations

import ctypes
import hashlib
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import casadi as ca
import numpy as np

from workbench.codegen.toolchain import Toolchain, find_toolchain
from workbench.validation import fail

VERIFY_RTOL = 1e-12
VERIFY_POINTS = 3


class CompileError(RuntimeError):
    """The C compiler failed; the message carries its output."""


@dataclass(frozen=True, eq=False)
class Library:
    """A loaded shared library and the Functions it exports (kept alive with it)."""

    path: Path
    key: str
    cdll: ctypes.CDLL
    functions: dict[str, ca.Function] = field(repr=False)
    cache_hit: bool


def cache_dir() -> Path:
    """``$WORKBENCH_CACHE_DIR`` or ``~/.cache/sais-workbench/codegen``."""
    env = os.environ.get("WORKBENCH_CACHE_DIR")
    root = Path(env) if env else Path.home() / ".cache" / "sais-workbench" / "codegen"
    root = root.expanduser().resolve()
    if root.exists() and not root.is_dir():
        raise fail("WORKBENCH_CACHE_DIR" if env else "cache directory", str(root),
                   "is an existing file, not a directory (point WORKBENCH_CACHE_DIR elsewhere)")
    return root


def generate_source(functions: list[ca.Function], extra_source: str = "") -> str:
    """C text of the Functions (one translation unit) followed by ``extra_source``."""
    cg = ca.CodeGenerator("wb_gen.c", {"with_header": False})
    for f in functions:
        cg.add(f)
    return cg.dump() + "\n" + extra_source


def _cpu_signature() -> str:
    """CPU model and feature flags: ``-march=native`` code is only valid on the same CPU kind."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        return platform.processor()
    keep = [ln for ln in lines if ln.startswith(("model name", "flags", "Features"))]
    return hashlib.sha256("\n".join(sorted(set(keep))).encode()).hexdigest()


def _sha256_file(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _atomic_write(path: Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name + ".", suffix=".tmp")
    with os.fdopen(fd, "w") as fh:
        fh.write(text)
    os.replace(tmp, path)


# Link so that every symbol must resolve now (libm linked): a library calling a function no
# linked library provides (CasADi emits erfinv(...) for OP_ERFINV, which libm lacks) fails at
# build time with the symbol's name, instead of killing the interpreter when it is first called.
LINK_CHECK_FLAGS = ("-Wl,--no-undefined",) if sys.platform.startswith("linux") else ()
_UNDEFINED = re.compile(r"undefined (?:reference|symbol)[^`'\"]*[`'\"]([A-Za-z_][A-Za-z0-9_]*)")


def _undefined_message(output: str) -> str | None:
    names = sorted(set(_UNDEFINED.findall(output)))
    if not names:
        return None
    return (f"the generated code calls {', '.join(names)}, which no linked library provides: "
            f"the CasADi operation{'s' if len(names) > 1 else ''} {', '.join(names)} cannot be "
            "compiled by the C back end (rewrite the model without it, or set "
            "WORKBENCH_NO_CODEGEN=1 to evaluate with the CasADi virtual machine); nothing was "
            "cached")


def _run_compiler(tc: Toolchain, src: Path, out: Path, extra_flags: tuple[str, ...]) -> None:
    cmd = [tc.cc, *tc.flags, *extra_flags, str(src), "-o", str(out), *LINK_CHECK_FLAGS, "-lm"]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        output = proc.stderr.strip() or proc.stdout.strip()
        undefined = _undefined_message(output)
        if undefined:
            raise CompileError(f"{undefined}\ncompiler command: {' '.join(cmd)}\n{output}")
        raise CompileError(f"C compiler failed (exit {proc.returncode}): {' '.join(cmd)}\n{output}")


_LOADED: dict[str, str] = {}  # path -> sha256 of the file this process dlopened there
_PRIVATE = [0]


def _load_now(lib: Path) -> tuple[ctypes.CDLL, Path]:
    """dlopen with every symbol resolved now (ctypes uses RTLD_NOW): a library with undefined
    symbols raises OSError here instead of aborting the process on its first call (CasADi's
    external() binds lazily). Returns the handle and the path it was loaded from.

    The dynamic loader returns the handle it already has for a path it has loaded before, even
    when the file was replaced since (a rebuilt library would silently stay the old one). A
    path this process has loaded with other contents is therefore loaded through a private copy
    (unlinked by :func:`_release_private` once every handle is open).
    """
    digest = _sha256_file(lib)
    known = _LOADED.get(str(lib))
    path = lib
    if known is not None and known != digest:
        _PRIVATE[0] += 1
        path = lib.with_name(f".{lib.stem}.load-{os.getpid()}-{_PRIVATE[0]}{lib.suffix}")
        shutil.copyfile(lib, path)
    try:
        cdll = ctypes.CDLL(str(path))
    except OSError:
        _release_private(lib, path)
        raise
    _LOADED[str(path)] = digest
    return cdll, path


def _release_private(lib: Path, path: Path) -> None:
    if path != lib:
        try:
            path.unlink()
        except FileNotFoundError:
            pass


def _verify(lib_path: Path, functions: list[ca.Function]) -> dict[str, ca.Function]:
    """Load each Function from the library and compare it with the symbolic one."""
    loaded = {}
    rng = np.random.default_rng(20261122)
    for f in functions:
        ext = ca.external(f.name(), str(lib_path))
        for _ in range(VERIFY_POINTS):
            args = [rng.uniform(-2.0, 2.0, f.size_in(i)) for i in range(f.n_in())]
            ref, got = f.call(args), ext.call(args)
            for r, g in zip(ref, got, strict=False):
                r, g = np.asarray(r, dtype=float), np.asarray(g, dtype=float)
                same_nonfinite = np.array_equal(np.isfinite(r), np.isfinite(g))
                fin = np.isfinite(r)
                close = np.all(np.abs(r[fin] - g[fin]) <= VERIFY_RTOL * np.abs(r[fin]) + 1e-300)
                if not (same_nonfinite and close):
                    raise RuntimeError(f"generated {f.name()} differs from the CasADi VM")
        loaded[f.name()] = ext
    return loaded


_COUNTS = {"generated": 0, "compiled": 0}


def build_counts() -> dict[str, int]:
    """How many libraries this process has generated (``build_library`` calls that got past
    the compiler check: C source written and hashed, a cached library loaded or a new one
    compiled) and how many it compiled. A scene change must leave both unchanged."""
    return dict(_COUNTS)


def build_library(
    stem: str,
    functions: list[ca.Function],
    extra_source: str = "",
    *,
    toolchain: Toolchain | None = None,
    extra_flags: tuple[str, ...] = (),
    root: Path | None = None,
    rebuild: bool = False,
) -> Library | None:
    """Build (or fetch from the cache) the shared library of ``functions`` + ``extra_source``.

    Returns None, with a one-line warning, when no compiler is available: callers then use the
    CasADi virtual machine. Raises :class:`CompileError` with the compiler's message on failure
    (naming the operation when the code calls a function no library provides; nothing is then
    cached). ``rebuild`` ignores a cached library (a caller whose own check of it failed).
    """
    tc = toolchain or find_toolchain()
    if tc is None:
        warnings.warn("workbench: no C compiler found (or WORKBENCH_NO_CODEGEN set); "
                      "using the CasADi virtual machine", RuntimeWarning, stacklevel=2)
        return None
    _COUNTS["generated"] += 1
    source = generate_source(functions, extra_source)
    ident = "\n".join([source, tc.key(), *extra_flags, ca.__version__, platform.platform(),
                       _cpu_signature() if any("native" in f for f in extra_flags) else ""])
    key = hashlib.sha256(ident.encode()).hexdigest()[:20]
    base = root or cache_dir()
    folder = base / f"{stem}-{key}"
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        field = "root" if root is not None else "WORKBENCH_CACHE_DIR"
        raise fail(field, str(base), "cannot hold the code-generation cache: "
                   f"{exc.strerror or exc} ({folder})") from exc
    lib, manifest = folder / f"lib{stem}.so", folder / "manifest.json"
    hit = _published(lib, manifest) and not rebuild
    if not hit:
        _unpublish(lib, manifest)
        _compile_and_publish(tc, source, folder, stem, extra_flags)
    try:
        cdll, loaded = _load_and_verify(lib, functions)
    except (RuntimeError, OSError) as exc:
        if not hit:
            _unpublish(lib, manifest)
            if isinstance(exc, OSError):
                raise CompileError(_undefined_message(str(exc)) or
                                   f"the freshly built {lib} cannot be loaded: {exc}") from exc
            raise
        # stale or corrupted cache (e.g. a library with undefined symbols from an older build)
        _unpublish(lib, manifest)
        _compile_and_publish(tc, source, folder, stem, extra_flags)
        hit = False
        cdll, loaded = _load_and_verify(lib, functions)
    return Library(path=lib, key=key, cdll=cdll, functions=loaded, cache_hit=hit)


def _load_and_verify(lib: Path, functions: list[ca.Function]):
    cdll, path = _load_now(lib)
    try:
        return cdll, _verify(path, functions)
    finally:
        _release_private(lib, path)


def _unpublish(lib: Path, manifest: Path) -> None:
    """Remove a library that failed its checks, so no later run loads it."""
    for p in (manifest, lib):
        try:
            p.unlink()
        except FileNotFoundError:
            pass


def _published(lib: Path, manifest: Path) -> bool:
    try:
        meta = json.loads(manifest.read_text())
        return lib.is_file() and meta.get("sha256") == _sha256_file(lib)
    except (OSError, ValueError):
        return False


def _compile_and_publish(tc, source: str, folder: Path, stem: str, extra_flags) -> None:
    _COUNTS["compiled"] += 1
    src = folder / f"{stem}.c"
    _atomic_write(src, source)
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".lib{stem}.", suffix=".so")
    os.close(fd)
    try:
        _run_compiler(tc, src, Path(tmp), tuple(extra_flags))
        digest = _sha256_file(Path(tmp))
        os.replace(tmp, folder / f"lib{stem}.so")
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    meta = {"sha256": digest, "cc": tc.cc, "cc_version": tc.version,
            "flags": [*tc.flags, *extra_flags], "casadi": ca.__version__}
    _atomic_write(folder / "manifest.json", json.dumps(meta, indent=1))

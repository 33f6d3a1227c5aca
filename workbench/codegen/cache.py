"""Generate C from CasADi Functions, compile it once, cache it by content, check it before and
after loading.

Cache key: sha256 of the generated C text, the compiler path, version and flags, the CasADi
version and the platform. A build writes the source, compiles it to a temporary name in the
cache (the compiler is killed after ``Toolchain.timeout`` seconds, ``WORKBENCH_COMPILE_TIMEOUT``,
default 600), and publishes the library with ``os.replace`` followed by a manifest holding the
cache key and the library's sha256.

Trust model. Loading a shared library runs its code (constructors run at ``dlopen``), so the
cache is private to its user: the cache directory (``$WORKBENCH_CACHE_DIR`` or
``~/.cache/sais-workbench/codegen``), every directory this module creates for it and every entry
folder are mode 0700 and files are written 0600 (libraries 0700). Before use, the cache
directory and the entry folder must be owned by the current user and not writable by group or
others; a directory of ours that others may only read (0755, as made by earlier versions) is
tightened to 0700 with a log line; anything else is refused with an error naming the path. A
cached library is loaded only after its identity is established: the manifest must name this
build's cache key, the library's bytes must hash to the manifest's sha256, and both must be
regular files (no symbolic links) owned by the user and not writable by others. The bytes
hashed are the bytes loaded: they are read once and written to a new private copy that the
loader opens, whose inode must then be among the process's mappings (a library file replaced
after the check never runs; a replaced copy is not used). Copies stay until the process exits.
A stale or altered library is rebuilt without being loaded. The manifest is no signature:
whoever can write into the cache directory can replace a library and its manifest together,
which is why the directory itself must be private.

Floating-point mode. Flags that change floating-point semantics or the process's
floating-point mode, and extra inputs, are refused by name
(:func:`workbench.codegen.toolchain.check_flags`, for ``WORKBENCH_CFLAGS`` and ``extra_flags``
alike); every load runs under :func:`workbench.codegen.fpmode.guard`, so a library whose
start-up code changes flush-to-zero, denormals-are-zero or the rounding direction is undone,
removed from the cache and refused (:class:`~workbench.codegen.fpmode.FloatingPointModeError`).

After loading, every exported Function is compared with CasADi's own evaluation (relative
tolerance per element; non-finite entries must match) at points covering magnitudes 1e-3 to 1e3
with both signs and zero, plus the caller's ``check_ranges`` and ``operating_points``; a mismatch
rebuilds the library and loads the rebuilt bytes. Generated code without Functions (the sampler
kernels) is checked by its caller (:mod:`workbench.sampling.kernels.verify`), which asks for a
rebuild. Libraries are linked with every symbol resolved (``-Wl,--no-undefined``) and loaded
with RTLD_NOW.

Library names (often model names) are reduced to ``[A-Za-z0-9_-]``, at most
:data:`MAX_STEM` characters, and every entry folder must resolve inside the cache directory.
"""

from __future__ import annotations

import atexit
import ctypes
import hashlib
import itertools
import json
import logging
import os
import platform
import re
import signal
import stat
import subprocess
import sys
import tempfile
import warnings
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import casadi as ca
import numpy as np

import workbench.codegen.fpmode as fpmode
import workbench.environment as env
from workbench.codegen.toolchain import Toolchain, check_flags, find_toolchain
from workbench.codegen.toolchain import compile_timeout as _env_timeout
from workbench.validation import as_array, fail, real

CASADI_VERSION: str = ca.__version__  # type: ignore[attr-defined]  # casadi's stub omits it

log = logging.getLogger("workbench.codegen")

VERIFY_RTOL = 1e-12
# Check points of every exported Function: zero, each decade 1e-3 .. 1e3 (a point and its
# negation, per-element random signs), points with per-element log-uniform magnitudes, and
# points drawn in the caller's ranges.
VERIFY_DECADES = tuple(range(-3, 3))  # decade d: magnitudes in [10^d, 10^(d+1)]
VERIFY_MIXED = 8
VERIFY_RANGE_POINTS = 8
MAX_STEM = 64
DIR_MODE, LIB_MODE = 0o700, 0o700  # other files: 0600 (mkstemp)


class CompileError(RuntimeError):
    """The C compiler failed or timed out; the message carries the reason and its output."""


class _Altered(RuntimeError):
    """A library's bytes no longer hash to the digest its identity was established with."""


@dataclass(frozen=True, eq=False)
class Library:
    """A loaded shared library and the Functions it exports (kept alive with it)."""

    path: Path
    key: str
    cdll: ctypes.CDLL
    functions: dict[str, ca.Function] = field(repr=False)
    cache_hit: bool

    @property
    def image(self) -> Path:
        """The file the loader mapped: the private copy of the checked bytes (kept until the
        process exits); read this, not :attr:`path`, to inspect what runs."""
        return Path(self.cdll._name)


def cache_dir() -> Path:
    """``$WORKBENCH_CACHE_DIR`` or ``~/.cache/sais-workbench/codegen`` (resolved; not created)."""
    root = env.path(env.CACHE_DIR)
    if root is not None:
        return root
    root = (Path.home() / ".cache" / "sais-workbench" / "codegen").resolve()
    if root.exists() and not root.is_dir():
        raise fail("cache directory", str(root), "is an existing file, not a directory (point "
                   "WORKBENCH_CACHE_DIR elsewhere)")
    return root


def safe_stem(stem: str) -> str:
    """``stem`` as a file-name component: unchanged when it is 1 to :data:`MAX_STEM` characters
    of ``[A-Za-z0-9_-]``; otherwise other characters become ``_`` and a digest of the original
    is appended (so ``../x``, ``a/b`` and unicode names stay distinct and inside the cache)."""
    if not isinstance(stem, str):
        raise fail("build_library.stem", stem, "must be a string")
    clean = re.sub(r"[^A-Za-z0-9_-]", "_", stem)
    if clean == stem and 0 < len(stem) <= MAX_STEM:
        return stem
    digest = hashlib.sha256(stem.encode("utf-8", "surrogatepass")).hexdigest()[:10]
    return f"{clean[:MAX_STEM - 11]}_{digest}"


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
    try:
        with os.fdopen(fd, "w") as fh:  # mkstemp: mode 0600
            fh.write(text)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


# ---------------------------------------------------------------------------------------------
# the cache is private to its user


def _uid() -> int | None:
    return os.geteuid() if hasattr(os, "geteuid") else None


def _user(uid: int) -> str:
    try:
        import pwd

        return f"user {pwd.getpwuid(uid).pw_name!r} (uid {uid})"
    except (ImportError, KeyError):
        return f"uid {uid}"


def _writable_by(mode: int) -> str:
    return " and ".join(w for w, bit in (("group", stat.S_IWGRP), ("others", stat.S_IWOTH))
                        if mode & bit)


def _check_owner_and_mode(path: Path, st: os.stat_result, field: str, remedy: str) -> None:
    uid = _uid()
    if uid is not None and st.st_uid != uid:
        raise fail(field, str(path), f"is owned by {_user(st.st_uid)}, not by you ({_user(uid)}):"
                   " the code cache must be private to its user, because a library loaded from it"
                   f" runs inside this process; {remedy}")
    mode = stat.S_IMODE(st.st_mode)
    if mode & (stat.S_IWGRP | stat.S_IWOTH):
        raise fail(field, str(path), f"has mode {mode:04o} (writable by {_writable_by(mode)}): "
                   "whoever can write there can replace a cached library with code that runs "
                   f"inside this process; {remedy}")


def _check_dir(path: Path, field: str, *, quiet: bool = False) -> None:
    """Refuse a cache directory that is not private; tighten one of ours that others may only
    read (0755, as earlier versions made them) to 0700 (with a log line unless ``quiet``)."""
    st = os.lstat(path)
    if stat.S_ISLNK(st.st_mode) or not stat.S_ISDIR(st.st_mode):
        raise fail(field, str(path), "is not a directory (a symbolic link or a file); the cache "
                   "never creates those: delete it, or point WORKBENCH_CACHE_DIR elsewhere")
    _check_owner_and_mode(path, st, field, f"check what it holds (or delete it) and run "
                          f"`chmod 700 '{path}'`, or point WORKBENCH_CACHE_DIR at a directory "
                          "of your own")
    mode = stat.S_IMODE(st.st_mode)
    if mode & 0o077:
        os.chmod(path, DIR_MODE)
        log.log(logging.DEBUG if quiet else logging.INFO, "code cache: %s had mode %04o; "
                "tightened to 0700 (the cache is private to its user)", path, mode)


def _private_dirs(path: Path, field: str, *, quiet: bool = False) -> None:
    """Create ``path`` and its missing parents with mode 0700, then check it
    (:func:`_check_dir`)."""
    missing = []
    p = path
    while not os.path.lexists(p) and p != p.parent:
        missing.append(p)
        p = p.parent
    try:
        for d in reversed(missing):
            try:
                d.mkdir(mode=DIR_MODE)
            except FileExistsError:
                continue
            os.chmod(d, DIR_MODE)  # whatever the umask
        _check_dir(path, field, quiet=quiet)
    except OSError as exc:
        raise fail(field, str(path), "cannot hold the code-generation cache: "
                   f"{exc.strerror or exc}") from exc


def _check_file(path: Path, field: str) -> bool:
    """False when ``path`` is absent; raises when it is a link, not a regular file, someone
    else's, or writable by others (it is never loaded then)."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return False
    remedy = f"delete the folder '{path.parent}' (it is rebuilt)"
    if not stat.S_ISREG(st.st_mode):
        raise fail(field, str(path), "is not a regular file (a symbolic link or a special file;"
                   f" the cache never creates those): {remedy}")
    _check_owner_and_mode(path, st, field, remedy)
    return True


def _identity(lib: Path, manifest: Path, key: str, field: str) -> str | None:
    """The library's sha256 when its manifest names ``key`` and its bytes hash to the digest the
    manifest records; None when absent, from another build, or altered (then it is rebuilt)."""
    if not (_check_file(manifest, field) and _check_file(lib, field)):
        return None
    try:
        meta = json.loads(manifest.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(meta, dict) or meta.get("key") != key:
        return None
    digest = meta.get("sha256")
    if not isinstance(digest, str):
        return None
    try:
        return digest if _sha256_file(lib) == digest else None
    except OSError:
        return None


# ---------------------------------------------------------------------------------------------
# compiling


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


def _kill_group(proc: subprocess.Popen) -> None:
    """Kill the compiler and everything it started (cc1, as, ld run in its process group)."""
    try:
        if hasattr(os, "killpg"):
            os.killpg(proc.pid, signal.SIGKILL)
        else:
            proc.kill()
    except (ProcessLookupError, PermissionError):
        pass


def _run_compiler(tc: Toolchain, src: Path, out: Path, extra_flags: tuple[str, ...]) -> None:
    """Run the compiler; killed (with its children) after ``tc.timeout`` seconds."""
    timeout = tc.timeout if tc.timeout is not None else _env_timeout()
    cmd = [tc.cc, *tc.flags, *extra_flags, str(src), "-o", str(out), *LINK_CHECK_FLAGS, "-lm"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        stdout, stderr = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        _kill_group(proc)
        try:
            proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:  # a child left its group and holds the pipes
            pass
        raise CompileError(f"C compiler timed out after {timeout:g} s and was killed (set "
                           "WORKBENCH_COMPILE_TIMEOUT to allow longer; nothing was cached): "
                           f"{' '.join(cmd)}") from None
    except BaseException:  # e.g. KeyboardInterrupt: the compiler is in its own session
        _kill_group(proc)
        proc.wait()
        raise
    if proc.returncode != 0:
        output = stderr.strip() or stdout.strip()
        undefined = _undefined_message(output)
        if undefined:
            raise CompileError(f"{undefined}\ncompiler command: {' '.join(cmd)}\n{output}")
        raise CompileError(f"C compiler failed (exit {proc.returncode}): {' '.join(cmd)}\n{output}")


# ---------------------------------------------------------------------------------------------
# loading: only bytes whose identity is established


_COPIES = itertools.count()
# digest -> (name, device, inode) of the private copy the loader mapped for it; the loader
# returns the handle it has for a name without opening the file again, so a digest loaded once
# is loaded again by that name, and every other load gets a name never used before
_IMAGES: dict[str, tuple[str, int, int]] = {}
_COPY = re.compile(r"\.load-(\d+)-\d+-[0-9a-f]{16}\.so")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # someone else's process
        return True
    return True


def _sweep(folder: Path) -> None:
    """Remove the private copies in ``folder`` left by processes that have ended."""
    for p in folder.glob(".load-*"):
        m = _COPY.fullmatch(p.name)
        if m and int(m.group(1)) != os.getpid() and not _alive(int(m.group(1))):
            _release_image(p)


def _release_all() -> None:
    for name, _, _ in _IMAGES.values():
        _release_image(Path(name))


atexit.register(_release_all)


def _image(data: bytes, lib: Path) -> tuple[Path, os.stat_result]:
    """A private copy of ``data`` for the dynamic loader: a file with a name this process has
    never used, created exclusively (never an existing file or link), mode 0500, in the entry
    folder (which is private), and its status (device, inode). Copies stay while this process
    runs (the loaded file can be inspected); they are removed at exit, or by a later load in
    the folder when the process ended without doing so."""
    _sweep(lib.parent)
    digest = hashlib.sha256(data).hexdigest()
    path = lib.parent / f".load-{os.getpid()}-{next(_COPIES)}-{digest[:16]}{lib.suffix}"
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0),
                 0o500)
    with os.fdopen(fd, "wb") as fh:
        fh.write(data)
        fh.flush()
        return path, os.fstat(fh.fileno())


def _mapped(dev: int, ino: int) -> bool | None:
    """Whether this process maps the file (device, inode), from ``/proc/self/maps``; None where
    that list cannot be read."""
    try:
        lines = Path("/proc/self/maps").read_text().splitlines()
    except OSError:
        return None
    want = (f"{os.major(dev):02x}:{os.minor(dev):02x}", str(ino))
    return any(tuple(ln.split(maxsplit=5)[3:5]) == want for ln in lines)


def _load_now(lib: Path, digest: str) -> tuple[ctypes.CDLL, str]:
    """dlopen the bytes of ``lib`` if they hash to ``digest`` (else :class:`_Altered`, nothing
    loaded), with every symbol resolved now (ctypes uses RTLD_NOW): a library with undefined
    symbols raises OSError here instead of aborting the process on its first call (CasADi's
    external() binds lazily). Returns the handle and the name it was loaded by.

    The bytes are read once and hashed, and those bytes are what the loader maps: they are
    written to a fresh private copy (:func:`_image`), and after the load that copy's inode must
    be among the process's mappings (else :class:`_Altered`, the copy removed), so a file put in
    ``lib``'s place after the check never runs and a replaced copy is never used. Bytes this
    process has loaded before are loaded again by the same name (the loader returns its
    handle). The process's floating-point mode is checked around the load
    (:func:`fpmode.guard`).
    """
    data = lib.read_bytes()
    if hashlib.sha256(data).hexdigest() != digest:
        raise _Altered(f"{lib} changed after its identity was checked; not loaded")
    known = _IMAGES.get(digest)
    if known is not None:
        copy, dev, ino = Path(known[0]), known[1], known[2]
    else:
        copy, st = _image(data, lib)
        dev, ino = st.st_dev, st.st_ino
    try:
        with fpmode.guard(lib):
            cdll = ctypes.CDLL(str(copy))
        if _mapped(dev, ino) is False:
            raise _Altered(f"{copy} (the private copy of {lib}) was replaced before it was "
                           "loaded; what was loaded instead is not used")
    except BaseException:
        if known is None:
            _release_image(copy)
        raise
    _IMAGES[digest] = (str(copy), dev, ino)
    return cdll, str(copy)


def _release_image(copy: Path) -> None:
    try:
        copy.unlink()
    except FileNotFoundError:
        pass


# ---------------------------------------------------------------------------------------------
# checking the loaded Functions against CasADi over the operating range


@dataclass(frozen=True)
class Checks:
    """Extra check points, by input name: ``ranges`` boxes (lo, hi) to sample in,
    ``points`` explicit values (each a mapping name -> value; other inputs are drawn)."""

    ranges: Mapping[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    points: tuple[Mapping[str, np.ndarray], ...] = ()


def _input_sizes(functions: Sequence[ca.Function]) -> dict[str, set[int]]:
    sizes: dict[str, set[int]] = {}
    for f in functions:
        for i in range(f.n_in()):
            sizes.setdefault(f.name_in(i), set()).add(f.numel_in(i))
    return sizes


def _named_value(fld: str, value, sizes: set[int]) -> np.ndarray:
    arr = as_array(fld, value, (None,)) if np.ndim(value) else as_array(fld, value, ())
    if arr.ndim == 1 and any(arr.size != n for n in sizes):
        raise fail(fld, value, f"has {arr.size} entries; the input has "
                   f"{' or '.join(map(str, sorted(sizes)))} (or give one number)")
    return arr


def make_checks(functions: Sequence[ca.Function], check_ranges=None,
                operating_points=None) -> Checks:
    """Validate :func:`build_library`'s ``check_ranges`` (input name -> (lo, hi), numbers or
    one entry per element) and ``operating_points`` (a sequence of input name -> value)."""
    sizes = _input_sizes(functions)
    known = ", ".join(sorted(sizes)) or "none"
    ranges = {}
    if check_ranges is not None:
        if not isinstance(check_ranges, Mapping):
            raise fail("build_library.check_ranges", check_ranges,
                       "must be a mapping input name -> (lo, hi)")
        for name, box in check_ranges.items():
            fld = f"build_library.check_ranges[{name!r}]"
            if name not in sizes:
                raise fail(fld, box, f"names no input of the Functions (inputs: {known})")
            if not (isinstance(box, Sequence) and len(box) == 2):
                raise fail(fld, box, "must be a pair (lo, hi)")
            lo, hi = (_named_value(fld, b, sizes[name]) for b in box)
            if np.any(lo > hi):
                raise fail(fld, box, "needs lo <= hi for every element")
            ranges[name] = (lo, hi)
    points = []
    if operating_points is not None:
        if isinstance(operating_points, Mapping) or not isinstance(operating_points, Sequence):
            raise fail("build_library.operating_points", operating_points,
                       "must be a sequence of mappings input name -> value")
        for k, pt in enumerate(operating_points):
            if not isinstance(pt, Mapping):
                raise fail(f"build_library.operating_points[{k}]", pt,
                           "must be a mapping input name -> value")
            one = {}
            for name, value in pt.items():
                fld = f"build_library.operating_points[{k}][{name!r}]"
                if name not in sizes:
                    raise fail(fld, value, f"names no input of the Functions (inputs: {known})")
                one[name] = _named_value(fld, value, sizes[name])
            points.append(one)
    return Checks(ranges=ranges, points=tuple(points))


def _signed(rng: np.random.Generator, log10_mag: np.ndarray) -> np.ndarray:
    return np.where(rng.random(log10_mag.shape) < 0.5, -1.0, 1.0) * 10.0 ** log10_mag


def check_points(f: ca.Function, checks: Checks | None = None) -> list[list[np.ndarray]]:
    """The points at which the loaded ``f`` is compared with CasADi (deterministic per name):
    zero; for each decade 10^d, d = -3..2, a point with magnitudes in [10^d, 10^(d+1)] and
    per-element random signs, and its negation; :data:`VERIFY_MIXED` points with per-element
    log-uniform magnitudes in [1e-3, 1e3]; and, with ``checks``, the range boxes' corners and
    :data:`VERIFY_RANGE_POINTS` points drawn in them, and the explicit operating points (inputs
    a range or point does not name are drawn as the mixed points are)."""
    checks = checks or Checks()
    rng = np.random.default_rng([20261122, zlib.crc32(f.name().encode())])
    shapes = [f.size_in(i) for i in range(f.n_in())]
    names = [f.name_in(i) for i in range(f.n_in())]

    def mixed():
        return [_signed(rng, rng.uniform(-3.0, 3.0, s)) for s in shapes]

    def shaped(value: np.ndarray, s) -> np.ndarray:
        return np.broadcast_to(value, (s[0] * s[1],)).reshape(s, order="F").copy()

    pts = [[np.zeros(s) for s in shapes]]
    for d in VERIFY_DECADES:
        p = [_signed(rng, rng.uniform(d, d + 1.0, s)) for s in shapes]
        pts += [p, [-a for a in p]]
    pts += [mixed() for _ in range(VERIFY_MIXED)]
    if any(n in checks.ranges for n in names):
        for j in range(VERIFY_RANGE_POINTS + 2):
            p = mixed()
            for i, (n, s) in enumerate(zip(names, shapes, strict=True)):
                if n in checks.ranges:
                    lo, hi = (shaped(b, s) for b in checks.ranges[n])
                    p[i] = lo if j == 0 else hi if j == 1 else rng.uniform(lo, hi)
            pts.append(p)
    for pt in checks.points:
        if any(n in pt for n in names):
            p = mixed()
            for i, (n, s) in enumerate(zip(names, shapes, strict=True)):
                if n in pt:
                    p[i] = shaped(pt[n], s)
            pts.append(p)
    return pts


def _mismatch(ref: np.ndarray, got: np.ndarray) -> int | None:
    """Index of the first element that differs (relative tolerance per element; non-finite
    entries must be equal: the same infinity, or NaN in both), or None."""
    r, g = ref.ravel(order="F"), got.ravel(order="F")
    fin = np.isfinite(r) & np.isfinite(g)
    with np.errstate(invalid="ignore"):
        ok = np.where(fin, np.abs(r - g) <= VERIFY_RTOL * np.maximum(np.abs(r), np.abs(g)),
                      (r == g) | (np.isnan(r) & np.isnan(g)))
    bad = np.flatnonzero(~ok)
    return int(bad[0]) if bad.size else None


def _show(a: np.ndarray) -> str:
    return np.array2string(np.ravel(a, order="F"), precision=4, threshold=8)


def _verify(lib_path: str, functions: list[ca.Function],
            checks: Checks | None = None) -> dict[str, ca.Function]:
    """Load each Function from the library and compare it with the symbolic one at
    :func:`check_points`; RuntimeError naming the Function, output and point on a mismatch."""
    loaded = {}
    for f in functions:
        ext = ca.external(f.name(), str(lib_path))
        for args in check_points(f, checks):
            ref, got = f.call(args), ext.call(args)
            for k, (r, g) in enumerate(zip(ref, got, strict=True)):
                r, g = np.asarray(r, dtype=float), np.asarray(g, dtype=float)
                j = _mismatch(r, g)
                if j is not None:
                    where = ", ".join(f"{f.name_in(i)}={_show(a)}" for i, a in enumerate(args))
                    raise RuntimeError(
                        f"generated {f.name()} differs from CasADi's evaluation: output "
                        f"{f.name_out(k)}[{j}] = {g.ravel(order='F')[j]!r} instead of "
                        f"{r.ravel(order='F')[j]!r} at {where}")
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
    compile_timeout: float | None = None,
    check_ranges: Mapping[str, tuple] | None = None,
    operating_points: Sequence[Mapping[str, object]] | None = None,
) -> Library | None:
    """Build (or fetch from the cache) the shared library of ``functions`` + ``extra_source``.

    Returns None, with a one-line warning, when no compiler is available: callers then use the
    CasADi virtual machine. Raises :class:`CompileError` with the compiler's message on failure
    or when the compiler runs longer than ``compile_timeout`` seconds (default: the toolchain's,
    ``WORKBENCH_COMPILE_TIMEOUT``, 600 s); nothing is then cached. ``rebuild`` ignores a cached
    library (a caller whose own check of it failed). ``check_ranges`` (input name -> (lo, hi))
    and ``operating_points`` (sequence of input name -> value) add points, in the model's
    operating range, at which the loaded Functions are compared with CasADi. ValueError when
    the cache directory is not private to the user (see the module's trust model).
    """
    if compile_timeout is not None:
        compile_timeout = real("build_library.compile_timeout", compile_timeout, 0.0,
                               strict=True)
    checks = make_checks(functions, check_ranges, operating_points)
    extra_flags = check_flags("build_library.extra_flags", tuple(extra_flags))
    name = safe_stem(stem)
    tc = toolchain or find_toolchain()
    if tc is None:
        warnings.warn("workbench: no C compiler found (or WORKBENCH_NO_CODEGEN on); "
                      "using the CasADi virtual machine", RuntimeWarning, stacklevel=2)
        return None
    if compile_timeout is not None or tc.timeout is None:
        tc = replace(tc, timeout=compile_timeout or _env_timeout())
    base, fld = _cache_root(root)
    _COUNTS["generated"] += 1
    source = generate_source(functions, extra_source)
    ident = "\n".join([source, tc.key(), *extra_flags, CASADI_VERSION, platform.platform(),
                       _cpu_signature() if any("native" in f for f in extra_flags) else ""])
    full_key = hashlib.sha256(ident.encode()).hexdigest()
    key = full_key[:20]
    folder = base / f"{name}-{key}"
    if folder.parent != base or not re.fullmatch(r"[A-Za-z0-9_-]+", folder.name):
        raise fail("build_library.stem", stem, f"gives the folder {folder}, outside {base}")
    _private_dirs(folder, f"{fld} entry", quiet=True)
    if folder.resolve().parent != base:
        raise fail(f"{fld} entry", str(folder), "resolves outside the cache directory: delete it")
    lib, manifest = folder / f"lib{name}.so", folder / "manifest.json"
    digest = None if rebuild else _identity(lib, manifest, full_key, f"{fld} file")
    hit = digest is not None
    if digest is None:
        digest = _compile_and_publish(tc, source, folder, name, extra_flags, full_key)
    try:
        cdll, loaded = _load_and_verify(lib, digest, functions, checks)
    except fpmode.FloatingPointModeError:
        _unpublish(lib, manifest)  # a rebuild would do the same: never loaded again
        raise
    except (RuntimeError, OSError) as exc:
        if not hit:
            _unpublish(lib, manifest)
            if isinstance(exc, OSError):
                raise CompileError(_undefined_message(str(exc)) or
                                   f"the freshly built {lib} cannot be loaded: {exc}") from exc
            raise
        # stale cache (e.g. a library with undefined symbols from an older build, or one whose
        # Functions differ from CasADi's): never used again
        log.info("code cache: %s failed its check on load (%s); rebuilding", lib,
                 str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
        _unpublish(lib, manifest)
        digest = _compile_and_publish(tc, source, folder, name, extra_flags, full_key)
        hit = False
        try:
            cdll, loaded = _load_and_verify(lib, digest, functions, checks)
        except fpmode.FloatingPointModeError:
            _unpublish(lib, manifest)
            raise
    return Library(path=lib, key=key, cdll=cdll, functions=loaded, cache_hit=hit)


def _cache_root(root: Path | None) -> tuple[Path, str]:
    """The cache directory (created private, checked) and the name errors give it."""
    if root is None:
        base, fld = cache_dir(), "WORKBENCH_CACHE_DIR"
    else:
        base, fld = Path(root).expanduser().resolve(), "build_library.root"
    _private_dirs(base, fld)
    return base, fld


def _load_and_verify(lib: Path, digest: str, functions: list[ca.Function], checks: Checks):
    cdll, name = _load_now(lib, digest)
    try:
        with fpmode.guard(lib):
            return cdll, _verify(name, functions, checks)
    except BaseException:
        _release_image(Path(name))  # loaded but never used: nothing of it stays on disk
        raise


def _unpublish(lib: Path, manifest: Path) -> None:
    """Remove a library that failed its checks, so no later run loads it."""
    for p in (manifest, lib):
        try:
            p.unlink()
        except FileNotFoundError:
            pass


def _compile_and_publish(tc, source: str, folder: Path, stem: str, extra_flags,
                         key: str) -> str:
    """Compile into the entry folder and publish library then manifest; returns the library's
    sha256. A stale manifest is removed first, so a failed build leaves nothing loadable."""
    _COUNTS["compiled"] += 1
    lib, manifest = folder / f"lib{stem}.so", folder / "manifest.json"
    try:
        manifest.unlink()
    except FileNotFoundError:
        pass
    src = folder / f"{stem}.c"
    _atomic_write(src, source)
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".lib{stem}.", suffix=".so")
    os.close(fd)
    try:
        try:
            _run_compiler(tc, src, Path(tmp), tuple(extra_flags))
        except CompileError:
            _unpublish(lib, manifest)
            raise
        os.chmod(tmp, LIB_MODE)  # the linker creates it with the umask's mode
        digest = _sha256_file(Path(tmp))
        os.replace(tmp, lib)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    meta = {"key": key, "sha256": digest, "cc": tc.cc, "cc_version": tc.version,
            "flags": [*tc.flags, *extra_flags], "casadi": CASADI_VERSION}
    _atomic_write(manifest, json.dumps(meta, indent=1))
    return digest

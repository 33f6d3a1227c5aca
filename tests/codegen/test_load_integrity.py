"""What runs is what was checked: the loader maps the bytes that were hashed (a file swapped in
after the check never runs), and nothing that changes the process's floating-point mode is
built or kept loaded (flags refused by name; a load that changes the mode is undone and
refused)."""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
from pathlib import Path

import numpy as np
import pytest

from workbench.codegen import (
    FloatingPointModeError,
    Toolchain,
    build_library,
    find_toolchain,
    fpmode,
)
from workbench.codegen import cache as cg
from workbench.codegen.toolchain import DEFAULT_FLAGS
from workbench.environment import EnvironmentVariableError

_CONSTRUCTOR = r"""
#include <stdio.h>
#include <stdlib.h>
__attribute__((constructor)) static void wbload_ctor(void) {
    const char* p = getenv("WBLOAD_MARKER");
    if (p) { FILE* f = fopen(p, "a"); if (f) { fputs("constructor ran\n", f); fclose(f); } }
}
"""
_GOOD = "int wbload_answer(void) { return 42; }\n"
_EVIL = _CONSTRUCTOR + "int wbload_answer(void) { return 666; }\n"


@pytest.fixture(autouse=True)
def _compiler():
    if find_toolchain() is None:
        pytest.skip("no C compiler on this machine")


def _replace(path: Path, data: bytes) -> None:
    """Put ``data`` at ``path`` as a new file (the old inode may be mapped)."""
    tmp = path.with_name(path.name + ".new")
    tmp.write_bytes(data)
    os.chmod(tmp, 0o700)
    os.replace(tmp, path)


def _answer(lib) -> int:
    lib.cdll.wbload_answer.restype = ctypes.c_int
    return lib.cdll.wbload_answer()


@pytest.fixture
def cached(tmp_path, monkeypatch):
    """A good library cached under ``fresh`` (a root this process never loaded from), the
    other library's bytes (a constructor that writes ``marker``) and the marker."""
    good = build_library("wbload", [], _GOOD, root=tmp_path / "built")
    evil = build_library("wbload", [], _EVIL, root=tmp_path / "evil")
    fresh = tmp_path / "fresh"
    fresh.mkdir(mode=0o700)
    shutil.copytree(good.path.parent, fresh / good.path.parent.name)
    marker = tmp_path / "marker"
    monkeypatch.setenv("WBLOAD_MARKER", str(marker))
    monkeypatch.setattr(cg, "_IMAGES", {})  # as in a process that has not loaded these bytes
    return fresh, fresh / good.path.parent.name / good.path.name, evil.path.read_bytes(), marker


def test_a_library_swapped_in_after_the_check_never_runs(cached, monkeypatch):
    """The cache file is replaced at the last moment before the loader runs: the bytes that
    were hashed are loaded, the replacement's constructor never runs."""
    root, lib, evil, marker = cached
    real = ctypes.CDLL
    swaps = []

    def swap_then_load(name, *args, **kwargs):
        if not swaps:
            _replace(lib, evil)
            swaps.append(name)
        return real(name, *args, **kwargs)

    monkeypatch.setattr(cg.ctypes, "CDLL", swap_then_load)
    got = build_library("wbload", [], _GOOD, root=root)
    assert swaps and lib.read_bytes() == evil  # the swap happened between check and load
    assert not marker.exists()
    assert got.cache_hit and _answer(got) == 42


def test_the_private_copy_is_checked_after_the_load(cached, monkeypatch):
    """Even the private copy swapped before the loader opens it is caught: the loaded file
    must be the one written from the checked bytes; the replacement is not used."""
    root, lib, evil, _marker = cached
    real = ctypes.CDLL
    swaps = []

    def swap_copy_then_load(name, *args, **kwargs):
        if not swaps and Path(name).name.startswith(".load-"):
            _replace(Path(name), evil)
            swaps.append(name)
        return real(name, *args, **kwargs)

    monkeypatch.setattr(cg.ctypes, "CDLL", swap_copy_then_load)
    got = build_library("wbload", [], _GOOD, root=root)
    assert swaps and _answer(got) == 42 and not got.cache_hit  # refused, rebuilt
    copies = list(lib.parent.glob(".load-*"))  # the refused copy removed, the loaded one kept
    assert len(copies) == 1 and str(copies[0]) != swaps[0]


def test_the_loaded_copy_holds_the_checked_bytes_and_stays_while_loaded(cached, monkeypatch):
    root, lib, _, _ = cached
    real = ctypes.CDLL
    seen = []

    def record(name, *args, **kwargs):
        if Path(name).parent == lib.parent:
            seen.append((name, hashlib.sha256(Path(name).read_bytes()).hexdigest()
                         if Path(name).exists() else None))
        return real(name, *args, **kwargs)

    monkeypatch.setattr(cg.ctypes, "CDLL", record)
    build_library("wbload", [], _GOOD, root=root)
    digest = hashlib.sha256(lib.read_bytes()).hexdigest()
    assert [d for _, d in seen] == [digest] and seen[0][0] != str(lib)
    copy = Path(seen[0][0])
    assert copy.exists() and (copy.stat().st_mode & 0o777) == 0o500
    seen.clear()  # the same bytes again: the loader's handle by that name, no new copy
    again = build_library("wbload", [], _GOOD, root=root)
    assert seen == [(str(copy), digest)] and _answer(again) == 42 and again.image == copy
    assert sorted(lib.parent.glob(".load-*")) == [copy]
    cg._release_all()  # what happens at exit
    assert not copy.exists()


def test_copies_left_by_ended_processes_are_removed(cached, monkeypatch):
    root, lib, _, _ = cached
    stale = lib.parent / f".load-{2**22 + 17}-0-{'0' * 16}.so"  # beyond any pid in use
    stale.write_bytes(b"left over")
    build_library("wbload", [], _GOOD, root=root)
    assert not stale.exists()


# ---------------------------------------------------------------------------------------------
# the floating-point mode


_UPWARD = "#include <fenv.h>\n__attribute__((constructor)) static void wbload_up(void) " \
          "{ fesetround(FE_UPWARD); }\n" + _GOOD
_FTZ = "#include <xmmintrin.h>\n__attribute__((constructor)) static void wbload_ftz(void) " \
       "{ _mm_setcsr(_mm_getcsr() | 0x8040); }\n" + _GOOD  # flush-to-zero, denormals-are-zero


def _subnormals_work() -> bool:
    small = np.array([2.2250738585072014e-308])
    return bool((small * np.array([0.5]))[0] != 0.0 and (np.array([5e-324]) * 1.0)[0] != 0.0)


def test_a_load_that_changes_rounding_is_undone_and_refused(tmp_path):
    assert fpmode.mode() == fpmode.NORMAL
    with pytest.raises(FloatingPointModeError, match=r"^loading .*libwbload_up\.so changed "
                       r"this process's floating-point mode from .*rounding nearest to .*"
                       r"rounding upward; the mode was restored and the library is not used"):
        build_library("wbload_up", [], _UPWARD, root=tmp_path)
    assert fpmode.mode() == fpmode.NORMAL
    assert np.array([1.0]) + np.array([2.0 ** -53]) == 1.0  # round to nearest again
    assert not list(tmp_path.rglob("manifest.json"))  # never loaded again


@pytest.mark.skipif(platform.machine() not in ("x86_64", "AMD64"), reason="x86 MXCSR bits")
def test_a_load_that_sets_flush_to_zero_is_undone_and_refused(tmp_path):
    """What crtfastmath.o (linked by -ffast-math) does when a library loads."""
    assert _subnormals_work()
    with pytest.raises(FloatingPointModeError, match=r"from flush-to-zero off, "
                       r"denormals-are-zero off, rounding nearest to flush-to-zero on, "
                       r"denormals-are-zero on, rounding nearest; the mode was restored"):
        build_library("wbload_ftz", [], _FTZ, root=tmp_path)
    assert _subnormals_work() and fpmode.mode() == fpmode.NORMAL


@pytest.mark.parametrize("flag", [
    "-mdaz-ftz", "/usr/lib/gcc/x86_64-linux-gnu/13/crtfastmath.o", "crtfastmath.o",
    "-Wl,/usr/lib/gcc/x86_64-linux-gnu/13/crtfastmath.o", "-Xlinker", "@more_flags.txt",
    "-lfastmath", "-L/opt/lib", "other.o", "libother.a", "-include", "-nostartfiles",
    "-specs=fast.specs",
])
def test_flags_that_can_change_the_mode_are_refused(monkeypatch, flag):
    monkeypatch.setenv("WORKBENCH_CFLAGS", f"-O2 {flag}")
    with pytest.raises(EnvironmentVariableError,
                       match=rf"^WORKBENCH_CFLAGS = '-O2 {flag}' is invalid: {flag} "
                             r"(is refused|changes floating-point semantics)"):
        find_toolchain()


def test_flags_given_in_code_are_refused_too(tmp_path):
    with pytest.raises(ValueError, match=r"^build_library\.extra_flags = .* -ffast-math "
                                         r"changes floating-point semantics and is refused"):
        build_library("wbload", [], _GOOD, root=tmp_path, extra_flags=("-ffast-math",))
    with pytest.raises(ValueError, match=r"(?s)^Toolchain\.flags = .* -Ofast changes"):
        Toolchain(cc="cc", version="cc 1", flags=(*DEFAULT_FLAGS, "-Ofast"))
    assert not list(tmp_path.rglob("*.so"))


def test_the_kernels_own_flags_pass(tmp_path):
    from workbench.sampling.kernels.flags import kernel_flags

    lib = build_library("wbload_kflags", [], _GOOD, root=tmp_path,
                        extra_flags=kernel_flags("float32"))
    assert _answer(lib) == 42

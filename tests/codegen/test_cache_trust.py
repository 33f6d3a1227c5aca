"""The code cache's trust model: a private cache directory, safe names, identity established
before anything is loaded, the load-time check over the operating range, compile timeouts."""

from __future__ import annotations

import ctypes
import hashlib
import json
import logging
import os
import re
import shutil
import stat
import time
from pathlib import Path
from types import SimpleNamespace

import casadi as ca
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from workbench.codegen import CompileError, Toolchain, build_library, find_toolchain
from workbench.codegen import cache as cg
from workbench.codegen.toolchain import DEFAULT_FLAGS


@pytest.fixture(autouse=True)
def _umask():
    old = os.umask(0o022)  # the usual default: directories 0755 unless made private
    yield
    os.umask(old)


def _replace(path: Path, data: bytes) -> None:
    """Write a file as a new inode (rewriting a library this process has mapped would corrupt
    the mapping)."""
    tmp = path.with_name(path.name + ".new")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def _mode(path: Path) -> int:
    return stat.S_IMODE(os.lstat(path).st_mode)


def _fn(extra=None):
    """y = (sin(x0) x1, x0 x2 / (1 + x1^2)); ``extra(x)`` is added to the first output."""
    x = ca.SX.sym("x", 3)
    y0 = ca.sin(x[0]) * x[1] + (extra(x) if extra is not None else 0)
    return ca.Function("wbtrust_f", [x], [ca.vertcat(y0, x[0] * x[2] / (1 + x[1] ** 2))],
                       ["x"], ["y"])


def _call(lib, x) -> np.ndarray:
    return np.asarray(lib.functions["wbtrust_f"](x), dtype=float).ravel()


def _other_owner(path: Path, monkeypatch) -> None:
    """Make ``path`` someone else's: chown when running as root, else pretend to be another
    user (then every path of the cache is someone else's)."""
    if hasattr(os, "geteuid") and os.geteuid() == 0:
        os.chown(path, 65534, 65534, follow_symlinks=False)
    else:
        monkeypatch.setattr(cg, "_uid", lambda: os.geteuid() + 1)


# ---------------------------------------------------------------------------------------------
# the cache directory is private to its user


def test_cache_directories_and_files_are_private(tmp_path, monkeypatch):
    root = tmp_path / "a" / "b" / "codegen"
    monkeypatch.setenv("WORKBENCH_CACHE_DIR", str(root))
    lib = build_library("wbtrust_private", [_fn()])
    for d in (tmp_path / "a", tmp_path / "a" / "b", root, lib.path.parent):
        assert _mode(d) == 0o700, d
    for p in lib.path.parent.iterdir():
        assert _mode(p) & 0o077 == 0, (p, oct(_mode(p)))
    names = {p.name for p in lib.path.parent.iterdir()}
    copies = {n for n in names if n.startswith(".load-")}  # what this process loaded (0500)
    assert names - copies == {"libwbtrust_private.so", "manifest.json", "wbtrust_private.c"}
    assert len(copies) == 1


@pytest.mark.parametrize("mode", [0o775, 0o757, 0o777, 0o1777])
def test_cache_directory_writable_by_others_is_refused(tmp_path, monkeypatch, mode):
    root = tmp_path / "shared"
    root.mkdir()
    os.chmod(root, mode)
    monkeypatch.setenv("WORKBENCH_CACHE_DIR", str(root))
    with pytest.raises(ValueError, match=rf"^WORKBENCH_CACHE_DIR = '{re.escape(str(root))}' is "
                       rf"invalid: has mode {mode & 0o7777:04o} \(writable by .*chmod 700"):
        build_library("wbtrust_shared", [_fn()])
    assert list(root.iterdir()) == [] and _mode(root) == mode  # nothing written, not "fixed"


def test_cache_directory_of_another_user_is_refused(tmp_path, monkeypatch):
    root = tmp_path / "theirs"
    root.mkdir(mode=0o700)
    _other_owner(root, monkeypatch)
    with pytest.raises(ValueError, match=r"^build_library.root = .* is owned by .*not by you.*"
                       "private to its user"):
        build_library("wbtrust_theirs", [_fn()], root=root)
    assert list(root.iterdir()) == []


def test_readable_cache_directory_of_ours_is_tightened(tmp_path, monkeypatch, caplog):
    root = tmp_path / "old"
    root.mkdir()
    os.chmod(root, 0o755)  # as earlier versions made it
    caplog.set_level(logging.INFO, logger="workbench.codegen")
    lib = build_library("wbtrust_old", [_fn()], root=root)
    assert _mode(root) == 0o700 and _mode(lib.path.parent) == 0o700
    assert any("tightened to 0700" in r.getMessage() for r in caplog.records)


def test_entry_folder_linked_elsewhere_is_refused_before_loading(trust):
    outside = trust.tmp / "outside"
    shutil.copytree(trust.folder, outside)
    trust.plant(outside)
    shutil.rmtree(trust.folder)
    trust.folder.symlink_to(outside, target_is_directory=True)
    with pytest.raises(ValueError, match="not a directory"):
        trust.build()
    assert not trust.marker.exists()


# ---------------------------------------------------------------------------------------------
# names from users stay inside the cache


@pytest.mark.parametrize("stem", ["../../x", "../evil", "..", "a/b", "ABSOLUTE", "ünï cødé",
                                  "x" * 300, ""])
def test_stem_cannot_escape_the_cache_directory(tmp_path, stem):
    root = tmp_path / "sandbox" / "cache"
    stem = str(tmp_path / "absolute" / "x") if stem == "ABSOLUTE" else stem
    before = set(tmp_path.rglob("*"))
    lib = build_library(stem, [_fn()], root=root)
    new = set(tmp_path.rglob("*")) - before
    assert new and all(p == root or root in p.parents or p in root.parents
               for p in new), sorted(new)
    assert lib.path.parent.parent == root
    assert re.fullmatch(r"[A-Za-z0-9_-]{1,64}-[0-9a-f]{20}", lib.path.parent.name)
    assert re.fullmatch(r"lib[A-Za-z0-9_-]{1,64}\.so", lib.path.name)
    np.testing.assert_array_equal(_call(lib, [1.0, 2.0, 3.0]),
                                  np.asarray(_fn()([1.0, 2.0, 3.0])).ravel())


def test_safe_stems_are_kept_and_unsafe_ones_stay_distinct():
    assert cg.safe_stem("ilqg_double_integrator_bas") == "ilqg_double_integrator_bas"
    names = {cg.safe_stem(s) for s in ("a/b", "a_b", "a:b", "a.b", "../a_b", "ä_b")}
    assert len(names) == 6
    assert all(re.fullmatch(r"[A-Za-z0-9_-]{1,64}", n) for n in names)
    with pytest.raises(ValueError, match=r"^build_library\.stem"):
        cg.safe_stem(b"bytes")


@settings(max_examples=300, deadline=None)
@given(st.text(max_size=200))
def test_any_stem_becomes_one_safe_file_name_component(stem):
    name = cg.safe_stem(stem)
    assert re.fullmatch(r"[A-Za-z0-9_-]{1,64}", name)
    assert (name == stem) == (re.fullmatch(r"[A-Za-z0-9_-]{1,64}", stem) is not None)
    assert os.path.dirname(os.path.normpath(f"/cache/{name}-0123")) == "/cache"


# ---------------------------------------------------------------------------------------------
# nothing is loaded before its identity is established: a library whose constructor writes a
# marker file stands for code that must never run

_CONSTRUCTOR = r"""
#include <stdio.h>
#include <stdlib.h>
__attribute__((constructor)) static void wbtrust_ctor(void) {
    const char* p = getenv("WBTRUST_MARKER");
    if (p) { FILE* f = fopen(p, "a"); if (f) { fputs("constructor ran\n", f); fclose(f); } }
}
"""
_GOOD = "int wbtrust_answer(void) { return 42; }\n"
_EVIL = _CONSTRUCTOR + "int wbtrust_answer(void) { return 666; }\n"


@pytest.fixture
def trust(tmp_path, monkeypatch):
    """A cached library (``folder``), the bytes and manifest of another library with a
    constructor (``evil``), the marker it would write, ``build()`` (the cached one again),
    and ``plant(folder)``: the other library's bytes in place, the manifest's digest updated."""
    good = build_library("wbtrust", [], _GOOD, root=tmp_path / "cache")
    evil = build_library("wbtrust", [], _EVIL, root=tmp_path / "evil")  # marker not set yet
    marker = tmp_path / "marker"
    monkeypatch.setenv("WBTRUST_MARKER", str(marker))
    data = evil.path.read_bytes()

    def plant(folder: Path) -> None:
        _replace(folder / good.path.name, data)
        meta = json.loads((folder / "manifest.json").read_text())
        meta["sha256"] = hashlib.sha256(data).hexdigest()
        (folder / "manifest.json").write_text(json.dumps(meta))

    def build():
        lib = build_library("wbtrust", [], _GOOD, root=tmp_path / "cache")
        lib.cdll.wbtrust_answer.restype = ctypes.c_int
        return lib

    return SimpleNamespace(tmp=tmp_path, folder=good.path.parent, lib=good.path, evil=evil,
                           data=data, marker=marker, plant=plant, build=build)


def test_manifest_of_another_build_is_never_loaded(trust):
    """The other library with its own manifest (its digest matches its bytes; its key is
    another build's) copied into the entry: rebuilt, never loaded."""
    for src, dst in ((trust.evil.path, trust.lib),
                     (trust.evil.path.parent / "manifest.json", trust.folder / "manifest.json")):
        _replace(dst, src.read_bytes())
    again = trust.build()
    assert not trust.marker.exists()
    assert not again.cache_hit and again.cdll.wbtrust_answer() == 42


def test_altered_library_bytes_are_never_loaded(trust):
    _replace(trust.lib, trust.data)  # the manifest still records the built library's digest
    again = trust.build()
    assert not trust.marker.exists()
    assert not again.cache_hit and again.cdll.wbtrust_answer() == 42


def test_library_writable_by_others_is_refused_before_loading(trust):
    trust.plant(trust.folder)
    os.chmod(trust.lib, 0o666)
    with pytest.raises(ValueError, match=r"file = .*libwbtrust\.so.* has mode 0666 \(writable "
                       r"by group and others\).*delete the folder"):
        trust.build()
    assert not trust.marker.exists()


def test_library_of_another_user_is_refused_before_loading(trust, monkeypatch):
    trust.plant(trust.folder)
    if not (hasattr(os, "geteuid") and os.geteuid() == 0):
        pytest.skip("needs root to give a file to another user")
    _other_owner(trust.lib, monkeypatch)
    with pytest.raises(ValueError, match=r"file = .*libwbtrust\.so.* is owned by"):
        trust.build()
    assert not trust.marker.exists()


def test_library_that_is_a_link_is_refused_before_loading(trust):
    trust.plant(trust.folder)
    outside = trust.tmp / "outside.so"
    shutil.copy2(trust.lib, outside)
    trust.lib.unlink()
    trust.lib.symlink_to(outside)
    with pytest.raises(ValueError, match=r"libwbtrust\.so.* is not a regular file"):
        trust.build()
    assert not trust.marker.exists()


def test_consistent_library_and_manifest_are_loaded_and_checked(trust):
    """What the trust model cannot tell apart: someone with write access to the (private)
    cache replaces library and digest together; the library is loaded, which is why the
    directory must be private. Kernel-less libraries are then checked by their callers. (This
    process has loaded those bytes before, so the loader hands out that handle again and the
    constructor does not run a second time.)"""
    trust.plant(trust.folder)
    lib = trust.build()
    assert lib.cdll.wbtrust_answer() == 666 and lib.cache_hit


# ---------------------------------------------------------------------------------------------
# the load-time check covers the operating range, not only [-2, 2]

_DIFFERENCES = {
    "x0 > 5": lambda x: ca.if_else(x[0] > 5, 1e-6 * x[0], 0),
    "x1 < -50": lambda x: ca.if_else(x[1] < -50, 1.0, 0),
    "|x2| < 1e-2": lambda x: ca.if_else(ca.fabs(x[2]) < 1e-2, 1e-3, 0),
}


@pytest.mark.parametrize("diff", list(_DIFFERENCES))
def test_cached_library_differing_outside_the_unit_box_is_rebuilt(tmp_path, diff):
    """A library built from a twin that equals the Function for |x| <= 2, put in the cache in
    place of the Function's own (digest updated), fails the check and is rebuilt."""
    f, twin = _fn(), _fn(_DIFFERENCES[diff])
    lib = build_library("wbtrust_twin", [f], root=tmp_path / "cache")
    other = build_library("wbtrust_twin", [twin], root=tmp_path / "twin")
    data = other.path.read_bytes()
    _replace(lib.path, data)
    manifest = lib.path.parent / "manifest.json"
    meta = json.loads(manifest.read_text())
    meta["sha256"] = hashlib.sha256(data).hexdigest()
    manifest.write_text(json.dumps(meta))
    again = build_library("wbtrust_twin", [f], root=tmp_path / "cache")
    assert not again.cache_hit
    for x in ([10.0, -100.0, 1e-3], [-0.5, 0.7, 1.5]):
        np.testing.assert_array_equal(_call(again, x), np.asarray(f(x)).ravel())


@pytest.mark.parametrize("diff", list(_DIFFERENCES))
def test_fresh_library_differing_outside_the_unit_box_is_an_error(tmp_path, monkeypatch, diff):
    """C generated from the twin, checked against the Function: the build fails, nothing is
    cached."""
    f, twin = _fn(), _fn(_DIFFERENCES[diff])
    real = cg.generate_source
    monkeypatch.setattr(cg, "generate_source", lambda fns, extra="": real([twin], extra))
    with pytest.raises(RuntimeError, match=r"generated wbtrust_f differs from CasADi's "
                       r"evaluation: output y\[0\]"):
        build_library("wbtrust_fresh", [f], root=tmp_path)
    assert not list(tmp_path.rglob("*.so")) and not list(tmp_path.rglob("manifest.json"))


def test_caller_ranges_and_points_extend_the_check(tmp_path):
    """A difference in a narrow window of x0 that the generic points miss is caught by the
    caller's operating range or operating point."""
    f = _fn()
    twin = _fn(lambda x: ca.if_else((x[0] > 7.0) * (x[0] < 7.2), 1e-3, 0))
    lib = build_library("wbtrust_window", [f], root=tmp_path / "cache")
    other = build_library("wbtrust_window", [twin], root=tmp_path / "twin")

    def swap():
        data = other.path.read_bytes()
        _replace(lib.path, data)
        manifest = lib.path.parent / "manifest.json"
        meta = json.loads(manifest.read_text())
        meta["sha256"] = hashlib.sha256(data).hexdigest()
        manifest.write_text(json.dumps(meta))

    swap()
    assert build_library("wbtrust_window", [f], root=tmp_path / "cache").cache_hit  # missed
    for extra in ({"check_ranges": {"x": ([7.0, -1.0, -1.0], [7.2, 1.0, 1.0])}},
                  {"operating_points": [{"x": [7.1, 0.5, -0.5]}]}):
        swap()
        again = build_library("wbtrust_window", [f], root=tmp_path / "cache", **extra)
        assert not again.cache_hit, extra
        np.testing.assert_array_equal(_call(again, [7.1, 0.5, -0.5]),
                                      np.asarray(f([7.1, 0.5, -0.5])).ravel())


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"check_ranges": {"z": (0, 1)}}, r"check_ranges\['z'\] = .*names no input.*inputs: x"),
    ({"check_ranges": {"x": (1, 0)}}, r"check_ranges\['x'\] = .*lo <= hi"),
    ({"check_ranges": {"x": ([0, 0], [1, 1])}}, r"check_ranges\['x'\] = .*has 2 entries.*3"),
    ({"check_ranges": {"x": (0, np.inf)}}, r"check_ranges\['x'\] = .*finite"),
    ({"check_ranges": {"x": 5}}, r"check_ranges\['x'\] = .*pair"),
    ({"check_ranges": [("x", 0, 1)]}, r"check_ranges = .*mapping"),
    ({"operating_points": {"x": [1, 2, 3]}}, r"operating_points = .*sequence of mappings"),
    ({"operating_points": [{"x": [1, 2]}]}, r"operating_points\[0\]\['x'\] = .*2 entries"),
    ({"operating_points": [[1, 2, 3]]}, r"operating_points\[0\] = .*mapping"),
    ({"compile_timeout": 0}, r"compile_timeout = .*> 0"),
    ({"compile_timeout": float("nan")}, r"compile_timeout = .*finite"),
    ({"compile_timeout": True}, r"compile_timeout = .*finite"),
])
def test_check_and_timeout_arguments_are_validated(tmp_path, kwargs, message):
    with pytest.raises(ValueError, match=rf"^build_library\.{message}"):
        build_library("wbtrust_args", [_fn()], root=tmp_path, **kwargs)
    assert not list(tmp_path.rglob("*.so"))


def test_check_points_span_magnitudes_and_signs():
    pts = np.stack([p[0].ravel() for p in cg.check_points(_fn())])
    assert np.all(pts[0] == 0)
    mags = np.abs(pts[1:])
    assert mags.min() < 1e-2 and mags.max() > 1e2
    for j in range(3):  # each element: both signs in every decade 1e-3 .. 1e3
        for d in range(-3, 3):
            col = pts[1:, j][(mags[:, j] >= 10.0**d) & (mags[:, j] <= 10.0 ** (d + 1))]
            assert (col > 0).any() and (col < 0).any(), (j, d)


@pytest.mark.parametrize(("ref", "got", "same"), [
    ([1.0, np.inf, np.nan], [1.0, np.inf, np.nan], True),
    ([1.0], [1.0 + 1e-13], True),
    ([0.0], [0.0], True),
    ([1.0], [1.0 + 1e-11], False),
    ([0.0], [1e-300], False),
    ([np.inf], [-np.inf], False),
    ([np.inf], [np.nan], False),
    ([np.nan], [1.0], False),
    ([1e300], [np.inf], False),
])
def test_elementwise_comparison_with_non_finite_values(ref, got, same):
    assert (cg._mismatch(np.array(ref), np.array(got)) is None) == same


# ---------------------------------------------------------------------------------------------
# compiles time out

_HUNG_CC = """#!/bin/sh
if [ "$1" = "--version" ]; then echo "wbtrust-cc 1.0"; exit 0; fi
(sleep 2; touch "$WBTRUST_CHILD") &
sleep 60
"""


@pytest.fixture
def hung_cc(tmp_path, monkeypatch):
    cc = tmp_path / "bin" / "wbtrust-cc"
    cc.parent.mkdir()
    cc.write_text(_HUNG_CC)
    cc.chmod(0o755)
    child = tmp_path / "child-survived"
    monkeypatch.setenv("WBTRUST_CHILD", str(child))
    return SimpleNamespace(cc=cc, child=child)


def test_hung_compiler_is_killed_after_the_timeout(tmp_path, hung_cc):
    tc = Toolchain(cc=str(hung_cc.cc), version="wbtrust-cc 1.0", flags=DEFAULT_FLAGS)
    root = tmp_path / "cache"
    with pytest.raises(CompileError, match=rf"^C compiler timed out after 1\.5 s .*"
                       rf"{re.escape(str(hung_cc.cc))} "):
        build_library("wbtrust_hung", [_fn()], root=root, toolchain=tc, compile_timeout=1.5)
    assert not list(root.rglob("*.so")) and not list(root.rglob("manifest.json"))
    time.sleep(2.5)
    assert not hung_cc.child.exists()  # the compiler's own children were killed too


def test_compile_timeout_from_the_environment(tmp_path, hung_cc, monkeypatch):
    monkeypatch.setenv("WORKBENCH_CC", str(hung_cc.cc))
    monkeypatch.setenv("WORKBENCH_COMPILE_TIMEOUT", "1")
    tc = find_toolchain()
    assert tc.cc == str(hung_cc.cc) and tc.timeout == 1.0
    with pytest.raises(CompileError, match=r"^C compiler timed out after 1 s"):
        build_library("wbtrust_env", [_fn()], root=tmp_path / "cache")


@pytest.mark.parametrize("value", ["0", "-5", "nan", "inf", "ten"])
def test_invalid_compile_timeout_in_the_environment_is_refused(monkeypatch, value):
    monkeypatch.setenv("WORKBENCH_COMPILE_TIMEOUT", value)
    with pytest.raises(ValueError, match=r"^WORKBENCH_COMPILE_TIMEOUT = .*finite number of "
                       "seconds > 0"):
        find_toolchain()

"""Generated C against the CasADi virtual machine; the content-addressed cache and its failures;
compiler overrides, unlinkable operations, swapped libraries."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from workbench.codegen import cache as cg
from workbench.codegen import find_toolchain
from workbench.ilqg.compiled import row_major_functions


def _simple_functions():
    x = ca.SX.sym("x", 3)
    return [ca.Function("wbt_f", [x], [ca.vertcat(ca.sin(x[0]) * x[1], 1 / (x[2] ** 2 + 1),
                                                  ca.fmin(x[0], x[1]))], ["x"], ["y"])]


def test_generated_problem_functions_equal_vm(bas_tracking, rng, tmp_path):
    problem, _ = bas_tracking
    fns = row_major_functions(problem)
    lib = cg.build_library("wbtest_problem", fns, root=tmp_path)
    assert lib is not None and not lib.cache_hit
    for f in fns:
        ext = lib.functions[f.name()]
        for _ in range(25):
            x = problem.model.lift(rng.uniform(-6, 6, 4) * [1, 1, 3, 3]) \
                if f.name_in(0) == "x" else None
            args = []
            for i in range(f.n_in()):
                name = f.name_in(i)
                args.append(x if name == "x" and x is not None and x.size == f.size1_in(i)
                            else rng.uniform(-10, 10, f.size_in(i)))
            for r, g in zip(f.call(args), ext.call(args), strict=True):
                r, g = np.asarray(r), np.asarray(g)
                fin = np.isfinite(r)
                np.testing.assert_array_equal(fin, np.isfinite(g))
                np.testing.assert_allclose(g[fin], r[fin], rtol=1e-12, atol=0)


def test_second_build_is_a_cache_hit_without_compiler(tmp_path, monkeypatch):
    fns = _simple_functions()
    first = cg.build_library("wbtest_hit", fns, root=tmp_path)
    assert first is not None and not first.cache_hit

    def no_compiler(*args, **kwargs):
        raise AssertionError("the compiler must not run on a cache hit")

    monkeypatch.setattr(cg, "_run_compiler", no_compiler)
    second = cg.build_library("wbtest_hit", fns, root=tmp_path)
    assert second.cache_hit and second.path == first.path


def test_key_depends_on_flags_and_source(tmp_path):
    fns = _simple_functions()
    tc = find_toolchain()
    a = cg.build_library("wbtest_key", fns, root=tmp_path, toolchain=tc)
    b = cg.build_library("wbtest_key", fns, root=tmp_path, toolchain=tc, extra_flags=("-DX=1",))
    c = cg.build_library("wbtest_key", fns, "/* other */", root=tmp_path, toolchain=tc)
    assert len({a.key, b.key, c.key}) == 3


def test_corrupted_library_is_detected_and_rebuilt(tmp_path, monkeypatch):
    # the first build runs in another process, as a cache left by an earlier run would be
    script = (
        "import sys; sys.path.insert(0, sys.argv[1]); from test_codegen import _simple_functions;"
        "from workbench.codegen import cache as cg; import pathlib;"
        "print(cg.build_library('wbtest_corrupt', _simple_functions(),"
        " root=pathlib.Path(sys.argv[2])).path)"
    )
    out = subprocess.run([sys.executable, "-c", script, str(Path(__file__).parent),
                          str(tmp_path)], capture_output=True, text=True, check=True)
    path = Path(out.stdout.strip().splitlines()[-1])
    fns = _simple_functions()
    data = bytearray(path.read_bytes())
    data[len(data) // 2 : len(data) // 2 + 64] = b"\xff" * 64
    path.write_bytes(bytes(data))
    calls = []
    real = cg._run_compiler
    monkeypatch.setattr(cg, "_run_compiler", lambda *a: (calls.append(a), real(*a))[1])
    again = cg.build_library("wbtest_corrupt", fns, root=tmp_path)
    assert len(calls) == 1 and not again.cache_hit
    x = np.array([0.3, -1.2, 2.0])
    np.testing.assert_array_equal(np.asarray(again.functions["wbt_f"](x)),
                                  np.asarray(fns[0](x)))


def test_failing_compile_shows_compiler_message(tmp_path):
    with pytest.raises(cg.CompileError, match=r"(?s)exit \d+.*wb_does_not_compile"):
        cg.build_library("wbtest_fail", _simple_functions(),
                         "int broken(void) { return wb_does_not_compile; }\n", root=tmp_path)
    assert not list(tmp_path.rglob("*.so"))  # nothing half-written is published


def test_missing_compiler_warns_once_and_falls_back(monkeypatch, bas_tracking, scene):
    from workbench.ilqg import ILQGOptions, compiled, ilqg

    monkeypatch.setenv("WORKBENCH_NO_CODEGEN", "1")
    monkeypatch.setattr(compiled, "_LIBS", {})
    problem, P = bas_tracking
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = ilqg(problem, scene.start, np.zeros((scene.horizon, 2)), P,
                   ILQGOptions(max_iter=2))
    msgs = [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]
    assert len(msgs) == 1 and "virtual machine" in msgs[0] and "\n" not in msgs[0]
    assert res.backend == "numpy"
    with pytest.raises(ValueError, match="backend"):
        ilqg(problem, scene.start, np.zeros((scene.horizon, 2)), P,
             ILQGOptions(max_iter=1, backend="compiled"))


def test_cache_dir_from_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("WORKBENCH_CACHE_DIR", str(tmp_path / "cc"))
    assert cg.cache_dir() == (tmp_path / "cc").resolve()


# ---------------------------------------------------------------------------------------------
# environment overrides that break or weaken the build


def _tiny_function():
    import casadi as ca

    x = ca.SX.sym("x", 2)
    return ca.Function("wbrel_tiny", [x], [ca.vertcat(x[0] * x[1], ca.exp(x[0]))], ["x"], ["y"])


def test_class6_extra_cflags_are_appended_to_the_required_ones(monkeypatch, tmp_path):
    from workbench.codegen import build_library, find_toolchain
    from workbench.codegen.toolchain import DEFAULT_FLAGS

    monkeypatch.setenv("WORKBENCH_CFLAGS", "-O2")
    tc = find_toolchain()
    assert tc.flags == (*DEFAULT_FLAGS, "-O2")
    assert {"-shared", "-fPIC"} <= set(tc.flags)
    lib = build_library("wbrel_cflags", [_tiny_function()], root=tmp_path)
    np.testing.assert_allclose(np.asarray(lib.functions["wbrel_tiny"]([0.5, 2.0])).ravel(),
                               [1.0, np.exp(0.5)])


@pytest.mark.parametrize("flag", ["-ffast-math", "-Ofast", "-funsafe-math-optimizations",
                                  "-ffinite-math-only", "-ffp-contract=fast", "-fno-honor-nans"])
def test_class6_flags_changing_floating_point_semantics_are_refused(monkeypatch, flag):
    from workbench.codegen import find_toolchain

    monkeypatch.setenv("WORKBENCH_CFLAGS", f"-O2 {flag}")
    with pytest.raises(ValueError, match=rf"^WORKBENCH_CFLAGS = .*{flag} changes floating-point"):
        find_toolchain()


@pytest.mark.parametrize("cc", ["/nonexistent/wbrel-cc", "false"])
def test_a_workbench_cc_that_is_not_a_working_compiler_is_refused_naming_it(monkeypatch, cc):
    from workbench.codegen import find_toolchain
    from workbench.codegen.toolchain import check_environment

    monkeypatch.delenv("WORKBENCH_CFLAGS", raising=False)
    monkeypatch.delenv("WORKBENCH_NO_CODEGEN", raising=False)
    monkeypatch.setenv("WORKBENCH_CC", cc)
    why = "not found on PATH" if cc.startswith("/") else "--version' failed"
    for call in (find_toolchain, check_environment):
        with pytest.raises(ValueError, match=rf"^WORKBENCH_CC = '{cc}' is invalid: must name a "
                                             rf"working C compiler \(.*{why}"):
            call()
    monkeypatch.setenv("WORKBENCH_CC", "cc")
    tc = find_toolchain()
    assert tc is not None and tc.cc == shutil.which("cc")


# ---------------------------------------------------------------------------------------------
# operations the C back ends cannot compile: a clear error or a correct fallback

_ERFINV_BUILD = """
import sys, pathlib
import casadi as ca
from workbench.codegen import cache as cg
x = ca.SX.sym("x", 2)
f = ca.Function("wbrel_erfinv", [x], [ca.erfinv(0.5 * ca.tanh(x[0])) + x[1]])
root = pathlib.Path(sys.argv[1])
if sys.argv[2] == "stale":  # a library published by a build without the link check
    import subprocess
    saved = {n: getattr(cg, n) for n in ("_run_compiler", "_verify", "_load_now")
             if hasattr(cg, n)}
    cg._run_compiler = lambda tc, src, out, extra: subprocess.run(
        [tc.cc, *tc.flags, *extra, str(src), "-o", str(out), "-lm"], check=True,
        capture_output=True)
    cg._verify = lambda lib, fns: {}
    cg._load_now = lambda lib: (None, lib)
    try:
        cg.build_library("wbrel_erfinv", [f], root=root)
    except Exception:
        pass
    for n, v in saved.items():
        setattr(cg, n, v)
    print("SO", sorted(p.name for p in root.rglob("*.so")))
try:
    lib = cg.build_library("wbrel_erfinv", [f], root=root)
    print("LOADED", lib.functions["wbrel_erfinv"]([0.1, 0.2]))
except cg.CompileError as exc:
    print("COMPILE_ERROR", str(exc).splitlines()[0])
print("CACHED", sorted(p.name for p in root.rglob("*.so")))
"""


@pytest.mark.parametrize("cache", ["empty", "stale"])
def test_class4_unlinkable_operation_is_a_clear_error_and_nothing_is_cached(tmp_path, cache):
    """erfinv compiles (implicit declaration) but libm has no erfinv: before the fix the
    library was published and the process died with 'undefined symbol' on first call (run in a
    subprocess so that the old behaviour cannot take the test run down)."""
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-c", _ERFINV_BUILD, str(tmp_path), cache],
                          capture_output=True, text=True, timeout=300,
                          cwd=os.path.dirname(os.path.dirname(os.path.dirname(__file__))))
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = proc.stdout.splitlines()
    if cache == "stale":
        assert lines[0] == "SO ['libwbrel_erfinv.so']"  # the broken library was in the cache
    error = [ln for ln in lines if ln.startswith("COMPILE_ERROR")]
    assert error and "erfinv" in error[0] and "nothing was cached" in error[0]
    assert lines[-1] == "CACHED []"


# ---------------------------------------------------------------------------------------------
# every loaded library is checked against CasADi's evaluation before first use




def test_class5_swapped_ilqg_library_is_detected_and_rebuilt(tmp_path):
    """The iLQG library's Functions are compared with CasADi on load; a swapped library must
    be rebuilt and the rebuilt one actually loaded (the dynamic loader would hand back the
    swapped one already open at that path)."""
    import casadi as ca

    from workbench.codegen import build_library

    x = ca.SX.sym("x", 2)

    def fns(k):
        return [ca.Function("wbrel_swap", [x], [ca.vertcat(k * x[0] + x[1], ca.sin(x[1]))],
                            ["x"], ["y"])]

    a = build_library("wbrel_swap", fns(2.0), root=tmp_path)
    b = build_library("wbrel_swap", fns(3.0), root=tmp_path)
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    # first loads of the victim happen below, in this process, after the swap
    import shutil

    for lib in (a, b):
        shutil.copytree(lib.path.parent, fresh / lib.path.parent.name)
    victim = type(a)(path=fresh / a.path.parent.name / a.path.name, key=a.key, cdll=a.cdll,
                     functions={}, cache_hit=True)
    donor = type(b)(path=fresh / b.path.parent.name / b.path.name, key=b.key, cdll=b.cdll,
                    functions={}, cache_hit=True)
    from conftest import swap_library  # here: a subprocess imports this module alone

    swap_library(victim, donor)
    again = build_library("wbrel_swap", fns(2.0), root=fresh)
    assert not again.cache_hit
    np.testing.assert_allclose(np.asarray(again.functions["wbrel_swap"]([1.0, 0.5])).ravel(),
                               [2.5, np.sin(0.5)], rtol=1e-15)

def test_class7_cache_directory_that_is_a_file_names_the_variable(tmp_path, monkeypatch):
    from workbench.codegen import build_library

    a_file = tmp_path / "cache_file"
    a_file.write_text("x")
    monkeypatch.setenv("WORKBENCH_CACHE_DIR", str(a_file))
    with pytest.raises(ValueError, match=r"^WORKBENCH_CACHE_DIR = .*not a directory"):
        build_library("wbrel_cachefile", [_tiny_function()])

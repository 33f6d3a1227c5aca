"""Generated C against the CasADi virtual machine; the content-addressed cache and its failures."""

from __future__ import annotations

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

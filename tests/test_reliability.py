"""Issue 9 (reliability): every bad input gets a clear error naming the field, no fault
corrupts a result, generated code is verified before it runs. One section per defect class."""

from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import pytest

from workbench.filters.ecbf import ECBFFilter, ECBFOptions
from workbench.problem.models import double_integrator
from workbench.problem.obstacles import Circle

ECBF_OBSTACLES = (Circle((0.0, 0.1), 1.5), Circle((0.5, 2.0), 0.7))
X_ACTIVE = np.array([-1.7, 0.1, 3.0, 0.0])  # near the first obstacle, moving towards it
U_TOWARDS = np.array([10.0, 0.0])


def _filter(**options) -> ECBFFilter:
    return ECBFFilter(double_integrator(obstacles=ECBF_OBSTACLES, u_limit=15.0),
                      ECBFOptions(**options))


# ---------------------------------------------------------------------------------------------
# class 1: an interrupt inside the QP solve must propagate, not become a fallback step


def _endless(filt: ECBFFilter) -> ECBFFilter:
    """Make every OSQP solve run until interrupted (no termination checks, huge max_iter)."""
    filt._solver.update_settings(max_iter=10**9, check_termination=0)
    return filt


def _sigint_after(seconds: float) -> threading.Timer:
    timer = threading.Timer(seconds, lambda: os.kill(os.getpid(), signal.SIGINT))
    timer.start()
    return timer


@pytest.mark.parametrize("call", ["single", "batch"])
def test_class1_sigint_inside_osqp_raises_keyboard_interrupt_promptly(call):
    filt = _endless(_filter())
    t0 = time.perf_counter()
    timer = _sigint_after(0.3)
    try:
        with pytest.raises(KeyboardInterrupt):
            if call == "single":
                filt(X_ACTIVE, U_TOWARDS)
            else:
                filt.filter_batch(np.array([X_ACTIVE, X_ACTIVE]), np.array([U_TOWARDS] * 2))
    finally:
        timer.cancel()
    assert time.perf_counter() - t0 < 5.0


def test_class1_filter_is_usable_after_an_interrupt():
    filt = _endless(_filter())
    timer = _sigint_after(0.3)
    try:
        with pytest.raises(KeyboardInterrupt):
            filt(X_ACTIVE, U_TOWARDS)
    finally:
        timer.cancel()
    res = filt(X_ACTIVE, U_TOWARDS)  # the workspace was set up afresh (normal settings)
    assert res.status == "solved" and not res.fallback_used
    np.testing.assert_allclose(res.u, _filter()(X_ACTIVE, U_TOWARDS).u, atol=1e-9)


def test_class1_interrupted_status_is_never_a_fallback(monkeypatch):
    """The status OSQP returns after catching SIGINT maps to KeyboardInterrupt (no signal)."""
    import osqp

    filt = _filter()
    real = filt._solver

    class Interrupted:
        def update(self, **kw):
            real.update(**kw)

        def solve(self, raise_error=False):
            res = real.solve(raise_error=False)
            res.info.status, res.info.status_val = "interrupted", osqp.SolverStatus.OSQP_SIGINT
            return res

    filt._solver = Interrupted()
    with pytest.raises(KeyboardInterrupt):
        filt(X_ACTIVE, U_TOWARDS)


# ---------------------------------------------------------------------------------------------
# class 2: a NaN state must not poison the OSQP workspace


@pytest.mark.parametrize("bad", [
    [np.nan, 0.1, 3.0, 0.0], [-1.7, np.inf, 3.0, 0.0], [-1.7, 0.1, 3.0, -np.inf]])
def test_class2_non_finite_state_is_rejected_before_the_solver(bad):
    filt = _filter()
    with pytest.raises(ValueError, match=r"^x = .* finite"):
        filt(np.array(bad), U_TOWARDS)
    res = filt(X_ACTIVE, U_TOWARDS)  # the next normal step is solved, not a fallback
    assert res.status == "solved" and not res.fallback_used


def test_class2_non_finite_batch_state_names_the_row():
    X = np.array([X_ACTIVE, [np.nan, 0.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match=r"(?s)^X = .*row 1"):
        _filter().filter_batch(X, np.array([U_TOWARDS] * 2))


@pytest.mark.parametrize("field", ["a", "b"])
def test_class2_non_finite_rows_are_rejected(field):
    filt = _filter()
    a, b = filt.rows(X_ACTIVE)
    (a if field == "a" else b)[0] = np.nan
    with pytest.raises(ValueError, match=rf"(?s)^{field} = .*finite"):
        filt.solve_rows(a, b, U_TOWARDS)
    assert filt(X_ACTIVE, U_TOWARDS).status == "solved"


def test_class2_broken_workspace_is_reset_and_the_step_solved(capfd):
    """A workspace left broken (non-quasidefinite KKT after NaN data reached OSQP) is set up
    afresh on the error status: the step is solved, and so are the later ones."""
    filt = _filter()
    expected = _filter()(X_ACTIVE, U_TOWARDS).u
    # what one step at a NaN state did before the input check: NaN rows through OSQP
    nh, pos = filt.nh, filt._a_pos
    filt._l[:nh], filt._Ax[pos] = np.nan, np.nan
    filt._solver.update(q=filt._q, l=filt._l, Ax=filt._Ax)
    filt._solver.solve(raise_error=False)
    for _ in range(3):
        res = filt(X_ACTIVE, U_TOWARDS)
        assert res.status == "solved" and not res.fallback_used
        np.testing.assert_allclose(res.u, expected, atol=1e-9)
    capfd.readouterr()


# class 7 (ECBF part): a state of the wrong length names the state, not numpy broadcasting


@pytest.mark.parametrize("x", [[1.0, 2.0], [1.0, 2.0, 3.0, 4.0, 5.0], [[-1.7, 0.1, 3.0, 0.0]]])
def test_class7_ecbf_state_of_wrong_shape_names_x(x):
    with pytest.raises(ValueError, match=r"^x = .*shape \(4,\)"):
        _filter()(x, U_TOWARDS)


def test_class7_ecbf_batch_of_wrong_width_names_X():
    with pytest.raises(ValueError, match=r"(?s)^X = .*shape \(N, 4\)"):
        _filter().filter_batch(np.zeros((3, 2)), np.zeros((3, 2)))


# ---------------------------------------------------------------------------------------------
# class 6: environment overrides that break or weaken the build


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


def test_class6_missing_workbench_cc_is_named_with_the_compiler_used(monkeypatch):
    from workbench.codegen import find_toolchain

    monkeypatch.delenv("WORKBENCH_CFLAGS", raising=False)
    monkeypatch.setenv("WORKBENCH_CC", "/nonexistent/wbrel-cc")
    with pytest.warns(RuntimeWarning, match=r"WORKBENCH_CC = '/nonexistent/wbrel-cc'.*using /"):
        tc = find_toolchain()
    assert tc is not None and tc.cc != "/nonexistent/wbrel-cc"


# ---------------------------------------------------------------------------------------------
# class 4: operations the C back ends cannot compile: a clear error or a correct fallback

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
                          cwd=os.path.dirname(os.path.dirname(__file__)))
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = proc.stdout.splitlines()
    if cache == "stale":
        assert lines[0] == "SO ['libwbrel_erfinv.so']"  # the broken library was in the cache
    error = [ln for ln in lines if ln.startswith("COMPILE_ERROR")]
    assert error and "erfinv" in error[0] and "nothing was cached" in error[0]
    assert lines[-1] == "CACHED []"


def _tiny_spec(expr_of):
    """A one-state kernel whose step applies ``expr_of(x)`` (SX) to the carry."""
    import casadi as ca

    from workbench.sampling.kernels.emit import KernelSpec

    c, z, w, s = (ca.SX.sym(n, 1) for n in ("carry", "z", "w", "s"))
    step = ca.Function("wbrel_k_step", [c, z, w, s],
                       [ca.vertcat(expr_of(0.3 * c + 0.1 * z + w)), s * c],
                       ["carry", "z", "w", "s"], ["carry_next", "y"])
    final = ca.Function("wbrel_k_final", [c, s], [c * s], ["carry", "s"], ["result"])
    return KernelSpec("wbrel_k", step, final,
                      {"carry": "carry", "z": "noise", "w": "time", "s": "const"})


_LIBM_OPS = {
    "asin": lambda v: __import__("casadi").asin(v), "acos": lambda v: __import__("casadi").acos(v),
    "sinh": lambda v: __import__("casadi").sinh(v), "cosh": lambda v: __import__("casadi").cosh(v),
    "erf": lambda v: __import__("casadi").erf(v), "asinh": lambda v: __import__("casadi").asinh(v),
    "acosh": lambda v: __import__("casadi").acosh(1.5 + v * v),
    "atanh": lambda v: __import__("casadi").atanh(0.5 * v),
    "remainder": lambda v: __import__("casadi").remainder(3.0 * v, 0.7),
}


@pytest.mark.parametrize("op", sorted(_LIBM_OPS))
def test_class4_emitter_writes_libm_operations_equal_to_casadi(op, tmp_path):
    from workbench.codegen import build_library
    from workbench.sampling.kernels.build import CompiledKernel
    from workbench.sampling.kernels.emit import emit_kernel, rng_source

    spec = _tiny_spec(_LIBM_OPS[op])
    lib = build_library("wbrel_ops", [], rng_source() + emit_kernel(spec), root=tmp_path,
                        extra_flags=("-fopenmp",))
    rng = np.random.default_rng(1)
    N, T = 6, 3
    carry0, w = rng.uniform(-0.5, 0.5, (N, 1)), rng.uniform(-0.5, 0.5, (T, 1))
    s, noise = np.array([0.7]), rng.standard_normal((T, 1, N))
    out = CompiledKernel(spec, lib.cdll)(carry0, consts={"s": s}, time_in={"w": w}, noise=noise)
    for n in range(N):  # CasADi's evaluation of the same step, sample by sample
        c = carry0[n]
        for t in range(T):
            c_next, y = (float(v) for v in spec.step(c, noise[t, 0, n], w[t], s))
            assert out.lane_out[0][t, 0, n] == pytest.approx(y, rel=1e-13, abs=1e-300)
            c = c_next
        assert out.result[n, 0] == pytest.approx(float(spec.final(c, s)), rel=1e-13)
    assert np.isfinite(out.result).all()


def test_class4_unsupported_operation_is_named_with_the_supported_list():
    import casadi as ca

    from workbench.sampling.kernels.emit import EmitError, emit_kernel

    with pytest.raises(EmitError, match=r"operation erfinv, which .* supported: acos, acosh"):
        emit_kernel(_tiny_spec(lambda v: ca.erfinv(0.5 * ca.tanh(v))))


def _erfinv_sampling_problem():
    import casadi as ca

    from workbench.problem.models import Model
    from workbench.sampling.problem import SamplingProblem

    x, u, g = ca.SX.sym("x", 2), ca.SX.sym("u", 2), ca.SX.sym("g", 2)
    x_next = x + 0.05 * (u + 0.1 * ca.erfinv(0.5 * ca.tanh(x)))
    model = Model.from_expressions("wbrel_erfinv_plane", x, u, x_next, dt=0.05,
                                   u_min=[-2, -2], u_max=[2, 2], h=ca.vertcat(4.0 - x[0]))
    e = x - g
    return SamplingProblem.from_costs(model, ca.dot(e, e), 10 * ca.dot(e, e), g)


def test_class4_sampler_falls_back_to_the_twin_with_one_warning(monkeypatch):
    import warnings

    from workbench.sampling.kernels import build as kernels
    from workbench.sampling.kernels.constants import SamplerConstants
    from workbench.sampling.reference import mppi_reference
    from workbench.sampling.sampler import Sampler

    monkeypatch.setattr(kernels, "_LIBS", {})
    sp = _erfinv_sampling_problem()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        first, second = Sampler(sp), Sampler(sp)
    msgs = [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]
    assert len(msgs) == 1 and "erfinv" in msgs[0] and "NumPy/CasADi" in msgs[0]
    assert first.backend == second.backend == "numpy"
    c = SamplerConstants(sigma=np.ones(2), lam=1.0, nu_mix=0.0, u_min=-2 * np.ones(2),
                         u_max=2 * np.ones(2), crash_cost=1e3, p=np.array([1.0, 1.0]))
    U = np.full((4, 2), 0.5)
    out = first.mppi(np.zeros(2), U, 6, c, seed=3)
    ref = mppi_reference(sp, np.zeros((6, 2)), U,
                         np.random.default_rng(3).standard_normal((6, 4, 2)), c)
    np.testing.assert_allclose(out.S, ref["S"], rtol=1e-12)
    assert np.all(np.isfinite(out.S))


# ---------------------------------------------------------------------------------------------
# class 5: every loaded library is checked against CasADi's evaluation before first use


def _small_navigation(center):
    from workbench.problem.barrier import embed_barrier
    from workbench.problem.obstacles import Circle
    from workbench.sampling.problem import navigation_costs

    return navigation_costs(embed_barrier(double_integrator(
        obstacles=(Circle(center, 0.5),), u_limit=5.0)))


def _swap(victim, donor) -> None:
    """Put donor's library bytes in victim's place and update victim's manifest hash."""
    import hashlib
    import json

    data = donor.path.read_bytes()
    tmp = victim.path.with_suffix(".swap")
    tmp.write_bytes(data)
    os.replace(tmp, victim.path)  # never rewrite a mapped library in place
    manifest = victim.path.parent / "manifest.json"
    meta = json.loads(manifest.read_text())
    meta["sha256"] = hashlib.sha256(data).hexdigest()
    manifest.write_text(json.dumps(meta))


def test_class5_swapped_sampler_library_is_detected_and_rebuilt(tmp_path, monkeypatch):
    """Issue 9 acceptance: a sampler library swapped with another problem's (hash updated in
    the manifest) is detected and rebuilt; the rebuilt kernels equal the twin."""
    import shutil

    from workbench.codegen import build_library
    from workbench.sampling.kernels import build as kernels
    from workbench.sampling.kernels.constants import SamplerConstants
    from workbench.sampling.reference import mppi_reference

    sp_a, sp_b = _small_navigation((2.0, 2.0)), _small_navigation((1.0, 3.0))
    built, cache = {}, tmp_path / "cache"
    for name, sp in (("a", sp_a), ("b", sp_b)):
        stem, _, source = kernels.library_sources(sp)
        lib = build_library(stem, [], source, extra_flags=kernels.KERNEL_FLAGS,
                            root=tmp_path / "build")
        # the cache under test holds copies this process has never loaded (as a cache left
        # by an earlier run would)
        shutil.copytree(lib.path.parent, cache / lib.path.parent.name)
        built[name] = type(lib)(cache / lib.path.parent.name / lib.path.name, lib.key,
                                lib.cdll, {}, True)
    assert built["a"].path != built["b"].path and built["a"].path.name == built["b"].path.name
    _swap(built["a"], built["b"])
    monkeypatch.setenv("WORKBENCH_CACHE_DIR", str(cache))
    monkeypatch.setattr(kernels, "_LIBS", {})
    with pytest.warns(RuntimeWarning, match=r"wb_mppi: .*differs.*rebuilding"):
        lib = kernels.sampler_library(sp_a)
    assert built["a"].path.read_bytes() != built["b"].path.read_bytes()
    m = sp_a.model
    c = SamplerConstants(sigma=np.array([2.0, 2.0]), lam=1.0, nu_mix=0.0, u_min=m.u_min,
                         u_max=m.u_max, crash_cost=1e6, p=m.lift([3.0, 3.0, 0.0, 0.0]))
    x0 = m.lift([0.5, 0.5, 1.0, 1.0])
    U = np.full((6, 2), 0.5)
    out = lib.mppi(np.tile(np.r_[x0, 0, 0], (9, 1)), consts=c.kernel_consts(),
                   time_in={"u": U}, seed=5, keep_noise=True)
    ref = mppi_reference(sp_a, np.tile(x0, (9, 1)), U, np.transpose(out.noise, (2, 0, 1)), c)
    np.testing.assert_allclose(out.result[:, 0], ref["S"], rtol=1e-9)


def test_class5_kernel_check_rejects_another_problems_kernel():
    from workbench.sampling.kernels import build as kernels
    from workbench.sampling.kernels.verify import KernelMismatch, verify_kernel

    lib_b = kernels.sampler_library(_small_navigation((1.0, 3.0)))
    spec_a = kernels.mppi_spec(_small_navigation((2.0, 2.0)))
    verify_kernel(lib_b.mppi)  # its own spec: fine
    with pytest.raises(KernelMismatch, match="wb_mppi"):
        verify_kernel(kernels.CompiledKernel(spec_a, lib_b.cdll))


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
    victim = type(a)(fresh / a.path.parent.name / a.path.name, a.key, a.cdll, {}, True)
    donor = type(b)(fresh / b.path.parent.name / b.path.name, b.key, b.cdll, {}, True)
    _swap(victim, donor)
    again = build_library("wbrel_swap", fns(2.0), root=fresh)
    assert not again.cache_hit
    np.testing.assert_allclose(np.asarray(again.functions["wbrel_swap"]([1.0, 0.5])).ravel(),
                               [2.5, np.sin(0.5)], rtol=1e-15)


# ---------------------------------------------------------------------------------------------
# class 7: errors that blame the wrong thing or nothing; the map generator

# NavigationScene().obstacles() at commit 59746ed (centre x, centre y, radius): studies depend
# on the default map, so it must never change
DEFAULT_MAP = (
    (3.6, 5.0, 1.0),
    (6.4, 5.0, 1.0),
    (8.177710407756603, 7.205485521961548, 0.6750572799628003),
    (3.4013302792898035, 7.988427563170095, 0.43512431399435514),
    (8.91168118145508, 2.7224695858847916, 0.6733075376646976),
    (5.900316834184246, 1.351536063691067, 0.3961272203147067),
    (2.9801193762186466, 1.0943522043400469, 0.5981240612361025),
    (6.5362569670547135, 2.6048537918959616, 0.4154412863911864),
    (1.0298739364166076, 7.640381838413965, 0.521721786361324),
    (1.474013138764029, 4.10105440888583, 0.6589104403243279),
    (8.829983075289773, 5.719933544084882, 0.5276677029301875),
    (4.5225077375055, 2.9165116946361866, 0.3904728115010212),
    (2.1636796300874153, 2.539707959746659, 0.6418314887155664),
    (5.1899208632838425, 7.982473668518195, 0.5569321478336888),
    (1.213618800690277, 6.206459547377829, 0.39690739616819953),
    (7.082986367921458, 8.94359086998885, 0.38268969260995866),
    (6.701405408491719, 7.602587202400322, 0.3887928892572388),
    (7.936528773886831, 1.045779434987292, 0.8191871725649438),
    (2.5964397486623687, 6.699657548641414, 0.5656286815253313),
    (5.069257882212596, 6.451923698702372, 0.4584678189714996),
    (4.614476367378825, 1.5054366854803254, 0.3191124230427081),
    (1.1105513785387817, 8.975837187616321, 0.37343908978547574),
    (8.134723419716398, 4.066531158500579, 0.3589994498588287),
    (5.636461951445057, 3.4313292021710984, 0.32708807636476),
    (1.0472490997152324, 1.5462408377893073, 0.4270262085296371),
    (8.383640375175865, 8.848284623513528, 0.35061809906955804),
    (3.4098466100518685, 3.277434307267626, 0.3064857233124098),
    (2.5628858912628063, 8.822100253988628, 0.33522505662487273),
    (4.290984776958586, 8.90845975440461, 0.3308706227975195),
    (3.8867801513347935, 6.8960733945788055, 0.3135203013138548),
)


def test_class7_default_map_is_unchanged():
    from workbench.scenarios.scenes import NavigationScene

    got = tuple((o.center[0], o.center[1], o.radius) for o in NavigationScene().obstacles())
    assert got == DEFAULT_MAP  # exact, bit for bit


@pytest.mark.parametrize("seed", [0, 3, 9])
def test_class7_map_generator_succeeds_where_rejection_sampling_jammed(seed):
    """These seeds raised 'NavigationScene.seed = ... could not place 30 obstacles' before."""
    from workbench.scenarios.scenes import NavigationScene

    sc = NavigationScene(seed=seed)
    obs = sc.obstacles()
    assert len(obs) == 30
    C = np.array([o.center for o in obs])
    R = np.array([o.radius for o in obs])
    assert np.all((R[2:] >= sc.radius_range[0] - 1e-12) & (R[2:] <= sc.radius_range[1]))
    assert np.all((C[2:] >= sc.center_range[0] - 1e-9) & (C[2:] <= sc.center_range[1] + 1e-9))
    gaps = np.hypot(*(C[:, None] - C[None]).transpose(2, 0, 1)) - R[:, None] - R[None]
    np.fill_diagonal(gaps, np.inf)
    assert gaps.min() >= sc.edge_gap - 1e-9
    for e in (sc.start, sc.goal):
        assert (np.hypot(*(C[2:] - np.array(e)).T) - R[2:]).min() >= sc.endpoint_clearance - 1e-9


def test_class7_infeasible_map_explains_density_not_seed():
    from workbench.scenarios.scenes import NavigationScene

    with pytest.raises(ValueError, match=r"too dense.*n_obstacles.*radius range.*gaps") as info:
        NavigationScene(n_obstacles=80, radius_range=(0.6, 0.9)).obstacles()
    assert "seed" not in str(info.value)


@pytest.mark.parametrize(("kwargs", "field"), [
    ({"radius_range": (0.9, 0.3)}, "NavigationScene.radius_range"),
    ({"center_range": (9.0, 1.0)}, "NavigationScene.center_range"),
    ({"start": (0.5, 0.5, 0.0)}, "NavigationScene.start"),
    ({"goal": (9.5,)}, "NavigationScene.goal"),
    ({"seed": -1}, "NavigationScene.seed"),
    ({"seed": 2.5}, "NavigationScene.seed"),
    ({"edge_gap": -0.1}, "NavigationScene.edge_gap"),
])
def test_class7_bad_navigation_scene_names_the_field(kwargs, field):
    from workbench.scenarios.scenes import NavigationScene

    with pytest.raises(ValueError, match=rf"^{field} = "):
        NavigationScene(**kwargs)


@pytest.mark.parametrize(("kwargs", "field"), [
    ({"start": (-5.0, 0.0)}, "TrackingScene.start"),
    ({"target": (5.0, 0.0, 0.0, 0.0, 1.0)}, "TrackingScene.target"),
    ({"horizon": 0}, "TrackingScene.horizon"),
])
def test_class7_bad_tracking_scene_names_the_field(kwargs, field):
    from workbench.scenarios.scenes import TrackingScene

    with pytest.raises(ValueError, match=rf"^{field} = "):
        TrackingScene(**kwargs)


@pytest.mark.parametrize("study", ["tracking_demo", "tracking_comparison"])
@pytest.mark.parametrize("where", ["file", "under_file", "unwritable"])
def test_class7_out_that_is_not_a_writable_directory_names_out(tmp_path, capsys, study, where):
    import importlib

    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    out = {"file": a_file, "under_file": a_file / "sub",
           "unwritable": "/proc/wbrel-no-such/out"}[where]
    main = importlib.import_module(f"studies.{study}.__main__").main
    with pytest.raises(SystemExit) as info:
        main(["--profile", "quick", "--out", str(out)])
    assert info.value.code == 2
    assert "error: --out = " in capsys.readouterr().err


def test_class7_cache_directory_that_is_a_file_names_the_variable(tmp_path, monkeypatch):
    from workbench.codegen import build_library

    a_file = tmp_path / "cache_file"
    a_file.write_text("x")
    monkeypatch.setenv("WORKBENCH_CACHE_DIR", str(a_file))
    with pytest.raises(ValueError, match=r"^WORKBENCH_CACHE_DIR = .*not a directory"):
        build_library("wbrel_cachefile", [_tiny_function()])


# ---------------------------------------------------------------------------------------------
# class 3 (scene part): accepted, then silently wrong


@pytest.mark.parametrize("n", [0, 1, -3, 2.5, True])
def test_class3_n_obstacles_below_two_or_not_an_integer_is_rejected(n):
    from workbench.scenarios.scenes import NavigationScene

    with pytest.raises(ValueError, match=r"^NavigationScene.n_obstacles = .*two gate circles"):
        NavigationScene(n_obstacles=n)


def test_class3_two_obstacles_gives_exactly_the_gates():
    from workbench.scenarios.scenes import NavigationScene

    obs = NavigationScene(n_obstacles=2).obstacles()
    assert len(obs) == 2 and {o.radius for o in obs} == {1.0}


@pytest.mark.parametrize(("field", "point"), [("start", (3.6, 5.0)), ("goal", (6.9, 5.2))])
def test_class3_start_or_goal_inside_an_obstacle_is_rejected(field, point):
    from workbench.scenarios.scenes import NavigationScene

    with pytest.raises(ValueError, match=rf"^NavigationScene.{field} = .*inside obstacle"):
        NavigationScene(**{field: point})


def test_class3_navigation_setup_rejects_a_start_inside_a_custom_map_obstacle():
    from workbench.problem.obstacles import Circle
    from workbench.scenarios.navigation import navigation_setup
    from workbench.scenarios.scenes import NavigationScene

    class OneCircle(NavigationScene):
        def obstacles(self):
            return (Circle((1.0, 1.0), 0.8),)

    with pytest.raises(ValueError, match=r"^scene.start = .*inside obstacle 0"):
        navigation_setup(OneCircle())


# ---------------------------------------------------------------------------------------------
# class 8: plants with other state sizes in closed_loop


class _Hold:
    def __init__(self, u):
        self.u = np.asarray(u, float)

    def initial_state(self, x0):
        return 0

    def step(self, state, x, rng):
        return state + 1, self.u, {}


def test_class8_single_integrator_closed_loop_disturbs_the_positions():
    from workbench.problem.models import single_integrator
    from workbench.sim import Disturbance, closed_loop

    plant = single_integrator(dt=0.02, u_limit=5.0)
    u = np.array([1.0, -0.5])
    ep = closed_loop(_Hold(u), plant, np.zeros(2), 4000, np.random.default_rng(0),
                     np.random.default_rng(1), Disturbance(10.0))
    W = np.diff(ep.X, axis=0) - 0.02 * u  # SPEC 2.4: w = dt xi on the position
    np.testing.assert_allclose(W.std(axis=0), 0.02 * np.sqrt(10.0), rtol=0.05)


def test_class8_one_state_plant_runs():
    import casadi as ca

    from workbench.problem.models import Model
    from workbench.sim import Disturbance, closed_loop

    x, u = ca.SX.sym("x", 1), ca.SX.sym("u", 1)
    plant = Model.from_expressions("scalar", x, u, 0.9 * x + 0.1 * u, dt=0.1, u_min=[-1],
                                   u_max=[1], h=1.0 - x**2)
    ep = closed_loop(_Hold([0.0]), plant, [0.0], 20, np.random.default_rng(0),
                     np.random.default_rng(1), Disturbance(0.01))
    assert ep.X.shape == (21, 1) and np.any(ep.X[1:] != 0.0)


@pytest.mark.parametrize("index", [(), (-1,), (2, 2), (1.5,)])
def test_class8_bad_disturbance_indices_are_rejected(index):
    from workbench.sim import Disturbance

    with pytest.raises(ValueError, match=r"^Disturbance.velocity_index = "):
        Disturbance(1.0, velocity_index=index)


def test_class8_disturbance_index_out_of_range_for_the_plant_is_named():
    from workbench.problem.models import single_integrator
    from workbench.sim import Disturbance, closed_loop

    with pytest.raises(ValueError, match=r"^Disturbance.velocity_index = .*out of range.*2 states"):
        closed_loop(_Hold([0.0, 0.0]), single_integrator(), np.zeros(2), 3,
                    np.random.default_rng(0), np.random.default_rng(1),
                    Disturbance(1.0, velocity_index=(2, 3)))


def test_class8_double_integrator_default_is_unchanged():
    """Guard (passes before the fix too): the plant-derived indices of the double integrator
    are (2, 3), so default episodes are bit-for-bit those of the explicit velocity indices."""
    from workbench.sim import Disturbance, closed_loop

    plant = double_integrator(u_limit=5.0)
    runs = [closed_loop(_Hold([1.0, 0.5]), plant, np.zeros(4), 50, np.random.default_rng(0),
                        np.random.default_rng(1), d).X
            for d in (Disturbance(10.0), Disturbance(10.0, velocity_index=(2, 3)))]
    np.testing.assert_array_equal(runs[0], runs[1])

"""IPOPT and FATROP on the library's multiple-shooting NLP with CasADi's just-in-time compiled
functions: the strongest NLP baselines of the BaS-iLQG benchmark.

The NLP is exactly :class:`workbench.ilqg.oracle.MultipleShootingNLP`'s (captured from its
construction, so the two can never drift apart); the jit solver is built from it with
``jit=True`` (CasADi's shell compiler, the library's C compiler, :data:`JIT_FLAGS`) and FATROP's
``structure_detection="auto"``. Building compiles the NLP's derivative functions, which takes
tens of seconds at T = 150, so the built solver is serialised with the binary embedded
(``jit_serialize="embed"``) into the code cache (``WORKBENCH_CACHE_DIR``), keyed by the NLP, the
options, the compiler and the CPU; later runs load it in a fraction of a second.
"""

from __future__ import annotations

import contextlib
import copy
import hashlib
import logging
import os
import platform
import tempfile
import time
from pathlib import Path

import casadi as ca

from workbench.codegen import cache_dir
from workbench.codegen.toolchain import find_toolchain
from workbench.ilqg.oracle import MultipleShootingNLP
from workbench.problem.problem import Problem

log = logging.getLogger("benchmarks.nlp_jit")

# -O1: CasADi's advice for large generated functions; measured as fast as -O3 -march=native at
# T = 150 here (29 vs 31-41 ms per FATROP solve) for a third of the compile time.
JIT_FLAGS = ("-O1",)


@contextlib.contextmanager
def _captured_nlpsol():
    """Record the (name, solver, nlp, opts) of every ``casadi.nlpsol`` call in the block."""
    seen: list[tuple] = []
    real = ca.nlpsol

    def spy(name, solver, nlp, opts=None):
        seen.append((name, solver, nlp, dict(opts or {})))
        return real(name, solver, nlp, opts or {})

    ca.nlpsol = spy
    try:
        yield seen
    finally:
        ca.nlpsol = real


@contextlib.contextmanager
def _scratch_cwd():
    """Run the block in a temporary working directory, removed afterwards: CasADi writes its
    jit sources and libraries (also when loading an embedded one) into the working directory.
    The loaded libraries stay usable (they are open)."""
    cwd = os.getcwd()
    with tempfile.TemporaryDirectory(prefix="wb-bench-jit-") as tmp:
        os.chdir(tmp)
        try:
            yield
        finally:
            os.chdir(cwd)


def _cpu_signature() -> str:
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        return platform.processor()
    keep = sorted({ln for ln in lines if ln.startswith(("model name", "flags", "Features"))})
    return hashlib.sha256("\n".join(keep).encode()).hexdigest()


def jit_nlp(problem: Problem, T: int, solver: str, *, tol: float,
            flags: tuple[str, ...] = JIT_FLAGS) -> tuple[MultipleShootingNLP, dict]:
    """The library's multiple-shooting NLP of ``problem`` for ``solver`` ("ipopt" or "fatrop")
    with jit-compiled functions, and facts about the build (cache hit, build or load seconds)."""
    with _captured_nlpsol() as seen:
        vm = MultipleShootingNLP(problem, T, solver, tol=tol)
    if len(seen) != 1:
        raise RuntimeError(f"expected one nlpsol call building the NLP, saw {len(seen)}")
    name, plugin, nlp, opts = seen[0]
    tc = find_toolchain()
    if tc is None:
        raise RuntimeError("no C compiler: the jit baselines need one")
    # the build runs in a temporary directory removed afterwards: no clean-up by CasADi
    jit_opts = {**opts, "jit": True, "compiler": "shell", "jit_serialize": "embed",
                "jit_cleanup": False,
                "jit_options": {"compiler": tc.cc, "flags": list(flags), "verbose": False,
                                "cleanup": False}}
    key_fn = ca.Function("nlp_key", [nlp["x"], nlp["p"]], [nlp["f"], nlp["g"]])
    ident = "\n".join([key_fn.serialize(), plugin, repr(sorted(jit_opts.items(), key=str)),
                       tc.key(), ca.__version__, platform.platform(), _cpu_signature()])
    key = hashlib.sha256(ident.encode()).hexdigest()[:20]
    folder = cache_dir() / f"bench_nlp_{plugin}_jit-{key}"
    path = folder / "solver.casadi"
    facts = {"flags": list(flags), "compiler": tc.cc, "compiler_version": tc.version,
             "cache": str(path)}
    t0 = time.perf_counter()
    solver_fn = None
    if path.is_file():
        try:
            with _scratch_cwd():
                solver_fn = ca.Function.load(str(path))
            facts.update(cache_hit=True, load_s=time.perf_counter() - t0)
        except RuntimeError as exc:  # stale or unreadable: rebuild
            log.warning("rebuilding %s: %s", path, exc)
    if solver_fn is None:
        log.info("jit-compiling the %s NLP (T = %d); cached for later runs", plugin, T)
        folder.mkdir(parents=True, exist_ok=True)
        fd, tmp_path = tempfile.mkstemp(dir=folder, suffix=".tmp")
        os.close(fd)
        try:
            # the embedding save reads the freshly built library back from the scratch folder
            with _scratch_cwd():
                solver_fn = ca.nlpsol(name + "_jit", plugin, nlp, jit_opts)
                facts.update(cache_hit=False, build_s=time.perf_counter() - t0)
                solver_fn.save(tmp_path)
            os.replace(tmp_path, path)
            with _scratch_cwd():
                solver_fn = ca.Function.load(str(path))  # what later runs load
        finally:
            if os.path.exists(tmp_path):
                os.unlink(tmp_path)
    out = copy.copy(vm)
    out._solver = solver_fn  # the same bounds and layout, the jit-compiled solver
    out.solver_name = f"{plugin}_jit"
    return out, facts

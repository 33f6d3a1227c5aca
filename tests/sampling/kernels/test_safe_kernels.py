"""The safe-MPPI kernel (per-sample CBF projection and DCBF cost) against its NumPy twin fed the
same noise, element by element, with the projection and the DCBF cost each on and off.

The scene (four circles around a start heading into them at 2 m/s, large sigma) is checked to
reach every branch: some samples are projected and some not, some projected steps stay
infeasible (box clip) and some become feasible, some samples crash, controls clip at both
bounds. A mutation check shows the comparison fails when the twin drops the projection, the
weight correction (raw instead of effective noise in the likelihood ratio) or the DCBF cost;
with both mechanisms off the kernel reproduces the plain MPPI kernel.
"""

from __future__ import annotations

import re
from dataclasses import replace

import numpy as np
import pytest

from workbench.problem.barrier import embed_barrier
from workbench.problem.models import double_integrator
from workbench.problem.obstacles import Circle
from workbench.sampling.kernels.constants import SamplerConstants
from workbench.sampling.kernels.safe import INFEASIBLE_TOL, safe_library
from workbench.sampling.methods.sampler import SafeOptions, SafeSampler
from workbench.sampling.methods.twin import _CBF, safe_twin
from workbench.sampling.problem import navigation_costs
from workbench.sampling.sampler import Sampler
from workbench.sampling.twin_model import model_twin

OBST = (Circle((2.0, 2.0), 0.8), Circle((3.5, 1.0), 0.5), Circle((1.0, 3.2), 0.6),
        Circle((2.2, 0.6), 0.4))
N, T = 125, 30  # N not a multiple of the lane count (4)
GOAL = (4.0, 4.0, 0.0, 0.0)
SEED = 123
# gamma = 0.3: the constraint binds on most samples but not all, and the box cannot always
# satisfy it (some projected samples still crash)
GAMMA, W_DCBF = 0.3, 1e3
# per element |a - b| <= RTOL max(|a|, |b|, 1), as in the sampler kernel tests; kernel and twin
# evaluate the same formulas in another order (measured <= 3e-16)
RTOL = 1e-10
COUNTS = ("crashed", "projected", "infeasible")
VALUES = ("S", "v", "dcbf")


def rel_err(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    assert a.shape == b.shape
    assert np.all(np.isfinite(a)) and np.all(np.isfinite(b))
    return float(np.max(np.abs(a - b) / np.maximum(np.maximum(np.abs(a), np.abs(b)), 1.0)))


def start() -> np.ndarray:
    """0.9 m off the line through the first obstacle's centre, heading along it at 2 m/s."""
    return np.array([1.0 - 0.9 / np.sqrt(2.0), 1.0 + 0.9 / np.sqrt(2.0), np.sqrt(2.0),
                     np.sqrt(2.0)])


@pytest.fixture(scope="module")
def setup():
    model = double_integrator(obstacles=OBST, u_limit=5.0)
    sp = navigation_costs(model, S=(10.0, 10.0, 1.0, 1.0))
    sampler = SafeSampler(sp, backend="compiled")
    c = SamplerConstants(sigma=np.array([3.0, 2.4]), lam=1.0, nu_mix=0.1, u_min=model.u_min,
                         u_max=model.u_max, crash_cost=1e6, p=np.array(GOAL))
    U = np.random.default_rng(11).normal(0.0, 2.0, (T, 2))
    Z = np.transpose(sampler.lib.normals(N, T, 2, SEED), (2, 0, 1))
    return sp, sampler, c, U, Z


def twin(sp, c, U, Z, project, w, x0=None, fn=safe_twin, **kw):
    x0 = start() if x0 is None else x0
    return fn(sp, np.tile(x0, (N, 1)), U, Z, c, project, w, GAMMA, **kw)


def mismatch(batch, ref) -> dict[str, float]:
    out = {"S": rel_err(batch.S, ref["S"]), "dcbf": rel_err(batch.dcbf, ref["dcbf"]),
           "v": rel_err(batch.v, np.transpose(ref["v"], (1, 2, 0)))}
    out |= {k: float(np.mean(getattr(batch, k) != ref[k])) for k in COUNTS}
    return out


def agrees(err) -> bool:
    return all(err[k] == 0.0 for k in COUNTS) and max(err[k] for k in VALUES) <= RTOL


@pytest.mark.parametrize(("project", "w"), [(True, W_DCBF), (True, 0.0), (False, W_DCBF),
                                            (False, 0.0)])
def test_safe_kernel_equals_twin_per_element(setup, project, w):
    sp, sampler, c, U, Z = setup
    batch = sampler.batch(start(), U, N, c, SafeOptions(project=project, w_dcbf=w,
                                                        gamma=GAMMA), SEED)
    ref = twin(sp, c, U, Z, project, w)
    err = mismatch(batch, ref)
    assert agrees(err), err
    v, cr = ref["v"], ref["crashed"]
    steps = ref["projected"].sum()
    assert 0 < cr.sum() < N // 2  # some samples crash, most do not
    assert min((v <= c.u_min).sum(), (v >= c.u_max).sum()) > 0.01 * v.size  # both bounds
    assert 0 < (ref["dcbf"] > 0).sum() < N  # the DCBF is violated on some samples only
    if project:
        # measured: 87 of 125 samples projected, 513 projected steps, 253 of them infeasible
        assert 0 < (ref["projected"] > 0).sum() < N
        assert 0 < ref["infeasible"].sum() < steps
        assert np.all(ref["infeasible"] <= ref["projected"])
    else:
        assert steps == 0 and ref["infeasible"].sum() == 0


def test_projected_steps_meet_the_chosen_constraint_unless_the_box_clips(setup):
    """c is convex in u here, so the linearised step meets the most restrictive constraint
    exactly, up to rounding, whenever the box does not clip the moved control; the
    infeasible steps are clipped ones or ones where another constraint is violated."""
    sp, _, c, U, Z = setup
    ref = twin(sp, c, U, Z, True, W_DCBF)
    cbf = _CBF(sp, N, GAMMA, sp.model.scene_value)
    n = {"unclipped": 0, "clipped": 0, "clipped_infeasible": 0}
    worst = np.inf
    for t in range(T):
        x, v = ref["X"][:, t], ref["v"][:, t]
        v0 = np.clip(U[t] + c.sigma * Z[:, t], c.u_min, c.u_max)
        c0 = cbf.c(x, v0)
        i_star = np.argmin(c0, axis=1)
        acted = c0[np.arange(N), i_star] < 0
        ch = cbf.c(x, v)
        clipped = np.any((v <= c.u_min) | (v >= c.u_max), axis=1)
        free = acted & ~clipped
        n["unclipped"] += free.sum()
        n["clipped"] += (acted & clipped).sum()
        n["clipped_infeasible"] += (acted & clipped & (ch.min(axis=1) < -INFEASIBLE_TOL)).sum()
        if free.any():
            worst = min(worst, float(np.min(ch[np.arange(N), i_star][free])))
    assert min(n.values()) > 0, n
    assert worst >= -1e-13, worst  # measured: >= 0 to rounding


def test_twin_on_the_casadi_model_and_a_moved_scene(setup):
    sp, sampler, c, U, Z = setup
    moved = replace(c, scene=sp.model.scene_vector([Circle((1.2, 2.4), 0.5),
                                                     Circle((2.5, 2.5), 0.7),
                                                     Circle((0.2, 1.0), 0.3)]))
    opts = SafeOptions(project=True, w_dcbf=W_DCBF, gamma=GAMMA)
    for cc in (c, moved):
        batch = sampler.batch(start(), U, N, cc, opts, SEED)
        ref = twin(sp, cc, U, Z, True, W_DCBF, model_backend="casadi")
        err = mismatch(batch, ref)
        assert agrees(err), err
        assert ref["projected"].sum() > 0


def test_barrier_embedded_problem_equals_twin():
    model = embed_barrier(double_integrator(obstacles=OBST, u_limit=5.0))
    sp = navigation_costs(model)
    sampler = SafeSampler(sp, backend="compiled")
    c = SamplerConstants(sigma=np.array([3.0, 2.4]), lam=1.0, nu_mix=0.0, u_min=model.u_min,
                         u_max=model.u_max, crash_cost=1e6, p=model.lift(GOAL))
    U = np.random.default_rng(2).normal(0.0, 2.0, (T, 2))
    Z = np.transpose(sampler.lib.normals(N, T, 2, 9), (2, 0, 1))
    x0 = model.lift(start())
    batch = sampler.batch(x0, U, N, c, SafeOptions(project=True, w_dcbf=W_DCBF, gamma=GAMMA), 9)
    ref = twin(sp, c, U, Z, True, W_DCBF, x0=x0)
    err = mismatch(batch, ref)
    assert agrees(err), err
    assert 0 < (ref["projected"] > 0).sum() < N


def test_mechanisms_off_reproduce_the_mppi_kernel(setup):
    sp, sampler, c, U, _ = setup
    plain = Sampler(sp, backend="compiled").mppi(start(), U, N, c, SEED)
    safe = sampler.batch(start(), U, N, c, SafeOptions(project=False, w_dcbf=0.0,
                                                        gamma=GAMMA), SEED)
    assert rel_err(safe.S, plain.S) <= 1e-12  # measured: bitwise
    assert rel_err(safe.v, plain.v) <= 1e-12
    np.testing.assert_array_equal(safe.crashed, plain.crashed)
    assert safe.projected.sum() == 0 and safe.dcbf.sum() > 0


# --- mutation check: a test copy of the twin with one piece of the algorithm left out ----------

MUTANTS = {
    "projection": "no projection: v_hat = clip(u + sigma z)",
    "weight_correction": "likelihood ratio on the raw noise sigma z instead of v_hat - u",
    "dcbf_cost": "no w_dcbf sum_i max(0, -c_i) in the step cost",
}


def twin_copy(sp, X0, U, Z, c, project, w_dcbf, gamma, model_backend="auto", drop=frozenset()):
    """:func:`safe_twin`, line for line, with the pieces named in ``drop`` left out.
    Without ``drop`` it equals the twin bit for bit (tested below)."""
    assert set(drop) <= set(MUTANTS)
    N_, T_ = Z.shape[0], Z.shape[1]
    scene = sp.model.scene_vector(c.scene if np.size(c.scene) else None)
    m = model_twin(sp, N_, scene, model_backend)
    cbf = _CBF(sp, N_, gamma, scene)
    inv = 1.0 / (c.sigma**2)
    half = 0.5 * c.lam * (1.0 - c.nu_mix)
    X = np.empty((N_, T_ + 1, sp.nx))
    X[:, 0] = X0
    S, dcbf = np.zeros(N_), np.zeros(N_)
    projected, infeasible = np.zeros(N_, int), np.zeros(N_, int)
    crashed = np.zeros(N_, bool)
    V = np.empty((N_, T_, sp.nu))
    rows = np.arange(N_)
    for t in range(T_):
        x, u = X[:, t], U[t]
        v = np.clip(u + c.sigma * Z[:, t], c.u_min, c.u_max)
        acted = np.zeros(N_, bool)
        if project and "projection" not in drop:
            cv = cbf.c(x, v)
            i_star = np.argmin(cv, axis=1)
            c_star = cv[rows, i_star]
            g = cbf.jacobian(x, v)[rows, i_star]
            acted = c_star < 0
            gg = np.sum(g * g, axis=1)
            step = np.where(gg > 0, -c_star / np.where(gg > 0, gg, 1.0), 0.0)
            moved = np.clip(v + step[:, None] * g, c.u_min, c.u_max)
            v = np.where(acted[:, None], moved, v)
        c_hat = cbf.c(x, v)
        projected += acted
        infeasible += acted & (np.min(c_hat, axis=1) < -INFEASIBLE_TOL)
        viol = np.sum(np.maximum(0.0, -c_hat), axis=1)
        dcbf += viol
        eps = c.sigma * Z[:, t] if "weight_correction" in drop else v - u
        X[:, t + 1] = m.step(x, v)
        crashed |= m.crashed(X[:, t + 1], sp.eps_h)
        S += m.cost(m.q, X[:, t + 1], c.p) + c.crash_cost * crashed
        S += half * (u @ (inv * u) + 2.0 * (eps @ (inv * u)))
        S += (0.0 if "dcbf_cost" in drop else w_dcbf) * viol
        V[:, t] = v
    S += m.cost(m.phi, X[:, T_], c.p)
    return {"S": S, "crashed": crashed, "v": V, "projected": projected,
            "infeasible": infeasible, "dcbf": dcbf, "X": X}


def test_unmutated_twin_copy_is_the_twin(setup):
    sp, _, c, U, Z = setup
    a, b = twin(sp, c, U, Z, True, W_DCBF, fn=twin_copy), twin(sp, c, U, Z, True, W_DCBF)
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


@pytest.mark.parametrize("mutant", list(MUTANTS))
def test_kernel_comparison_detects_a_mutated_twin(setup, mutant):
    sp, sampler, c, U, Z = setup
    batch = sampler.batch(start(), U, N, c, SafeOptions(project=True, w_dcbf=W_DCBF,
                                                        gamma=GAMMA), SEED)

    def mutated(*args, **kw):
        return twin_copy(*args, **kw, drop={mutant})

    err = mismatch(batch, twin(sp, c, U, Z, True, W_DCBF, fn=mutated))
    assert not agrees(err), MUTANTS[mutant]
    # by orders of magnitude (measured: >= 1e-2 relative on S), RTOL is 1e-10
    assert max(err[k] for k in VALUES) > 1e4 * RTOL, (MUTANTS[mutant], err)


# --- the sampler's other paths and options -----------------------------------------------------


def test_numpy_backend_draws_its_own_noise_and_runs_the_twin(setup):
    sp, _, c, U, _ = setup
    s = SafeSampler(sp, backend="numpy")
    assert s.lib is None and s.backend == "numpy"
    opts = SafeOptions(project=True, w_dcbf=W_DCBF, gamma=GAMMA)
    b = s.batch(start(), U, 9, c, opts, 4)
    Z = np.random.default_rng(4).standard_normal((9, T, 2))
    ref = safe_twin(sp, np.tile(start(), (9, 1)), U, Z, c, True, W_DCBF, GAMMA)
    np.testing.assert_array_equal(b.S, ref["S"])
    np.testing.assert_array_equal(b.v, np.transpose(ref["v"], (1, 2, 0)))
    assert b.projected.dtype.kind == "i" and b.v.shape == (T, 2, 9)


def test_library_is_built_once_per_problem(setup):
    sp, sampler, _, _, _ = setup
    assert safe_library(sp) is sampler.lib
    assert sampler.lib.normals(5, 3, 2, 1).shape == (3, 2, 5)
    sampler.lib.set_threads(1)
    sampler.lib.set_threads(2)


@pytest.mark.parametrize(("kw", "field"), [
    ({"project": 1}, "SafeOptions.project"), ({"w_dcbf": -1.0}, "SafeOptions.w_dcbf"),
    ({"w_dcbf": float("inf")}, "SafeOptions.w_dcbf"), ({"gamma": 0.0}, "SafeOptions.gamma"),
    ({"gamma": 1.5}, "SafeOptions.gamma"), ({"gamma": float("nan")}, "SafeOptions.gamma"),
])
def test_bad_options_name_the_field(kw, field):
    with pytest.raises(ValueError, match=re.escape(field + " =")):
        SafeOptions(**kw)


def test_bad_batch_input_names_the_field(setup):
    sp, sampler, c, U, _ = setup
    opts = SafeOptions()
    with pytest.raises(ValueError, match=r"^options = "):
        sampler.batch(start(), U, N, c, {"project": True}, 1)
    with pytest.raises(ValueError, match=r"^U = "):
        sampler.batch(start(), U[:, :1], N, c, opts, 1)
    with pytest.raises(ValueError, match=r"^N = "):
        sampler.batch(start(), U, 0, c, opts, 1)
    with pytest.raises(ValueError, match=r"^x0 = "):
        sampler.batch(start()[:3], U, N, c, opts, 1)
    with pytest.raises(ValueError, match=re.escape("SamplerConstants.scene =")):
        sampler.batch(start(), U, N, replace(c, scene=np.zeros(5)), opts, 1)
    with pytest.raises(ValueError, match=r"^backend = "):
        SafeSampler(sp, backend="gpu")

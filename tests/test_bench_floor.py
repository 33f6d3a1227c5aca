"""The hand-written C floor of the sampler kernels (benchmarks/floor) against the NumPy twin.

The floor is the speed record of ``make bench``; it counts only if it computes the same thing as
the kernels. It is fed the twin's noise and compared element by element (relative, as the
kernel tests do) on a case where some samples crash (real only, nominal only), controls clip at
both bounds, the feedback (barrier-state column included) acts and the alpha clamp binds on some
samples only. The comparison is shown to be sharp: the twin given a changed input the floor must
read (feedback gains, alpha, crash cost, mixing, one circle) disagrees by orders of magnitude.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from benchmarks.floor import FloorProblem, load_floor
from benchmarks.timing import prepared_kernel
from workbench.problem.barrier import BarrierOptions, embed_barrier
from workbench.problem.models import double_integrator
from workbench.problem.obstacles import Circle
from workbench.sampling.kernels.constants import SamplerConstants
from workbench.sampling.problem import navigation_costs
from workbench.sampling.sampler import Sampler, check_batch
from workbench.sampling.twin import mppi_twin, sais_twin

# five circles: the pairwise sum has two pairs and an odd tail, the four-circle form one group
OBST = (Circle((2.0, 2.0), 0.8), Circle((3.5, 1.0), 0.5), Circle((1.0, 3.2), 0.6),
        Circle((4.6, 0.4), 0.3), Circle((0.4, 4.6), 0.3))
N, T = 125, 30  # N not a multiple of the floor's 8 lanes: padding is exercised
GOAL = (4.0, 4.0, 0.0, 0.0)
ZSEED = 0
RTOL, FLOOR = 1e-10, 1.0  # |a - b| <= RTOL * max(|a|, |b|, FLOOR), as the kernel tests
COSTS = ("S_nom", "S_real", "S_state_nom", "S_hat", "LR")


def rel_err(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    assert a.shape == b.shape
    assert np.all(np.isfinite(a)) and np.all(np.isfinite(b))
    return float(np.max(np.abs(a - b) / np.maximum(np.maximum(np.abs(a), np.abs(b)), FLOOR)))


def lane_major(v) -> np.ndarray:
    return np.transpose(v, (1, 2, 0))


@pytest.fixture(scope="module")
def case():
    model = embed_barrier(double_integrator(obstacles=OBST, u_limit=5.0))
    sp = navigation_costs(model)
    rng = np.random.default_rng(2026)
    side = np.array([-1.0, 1.0]) / np.sqrt(2.0)
    heading = np.array([1.0, 1.0]) * np.sqrt(2.0)
    x0 = model.lift([*(np.array([1.0, 1.0]) + 0.9 * side), *heading])
    xs0 = model.lift([*(np.array([0.95, 0.95]) + 0.9 * side), *np.add(heading, (0.1, -0.1))])
    U = rng.normal(0.0, 2.0, (T, 2))
    K = np.zeros((T, 2, 5))
    K[:, 0, 0] = K[:, 1, 1] = -2.0
    K[:, 0, 2] = K[:, 1, 3] = -1.5
    K += rng.normal(0.0, 0.5, K.shape)
    K[:, :, 4] = rng.normal(0.0, 0.3, (T, 2))  # feedback on the barrier state
    Z = np.random.default_rng(ZSEED).standard_normal((N, T, 2))  # sample-major for the twin
    c = SamplerConstants(sigma=np.array([3.0, 2.4]), lam=1.3, nu_mix=0.1, u_min=model.u_min,
                         u_max=model.u_max, crash_cost=1e6, p=model.lift(GOAL))
    free = sais_twin(sp, np.tile(x0, (N, 1)), np.tile(xs0, (N, 1)), U, K, Z, c)
    Sh = np.sort(free["S_hat"][~free["crashed_real"] & ~free["crashed_nom"]])
    c = replace(c, alpha=float(0.5 * (Sh[Sh.size // 2 - 1] + Sh[Sh.size // 2])))
    return sp, x0, xs0, U, K, Z, c


def twin(case, **changes):
    sp, x0, xs0, U, K, Z, c = case
    K = changes.pop("K", K)
    c = replace(c, **changes)
    return sais_twin(sp, np.tile(x0, (N, 1)), np.tile(xs0, (N, 1)), U, K, Z, c)


def floor_sais(case, group: int = 2):
    sp, x0, xs0, U, K, Z, c = case
    floor = load_floor(group=group)
    assert floor is not None, "the floor needs a C compiler"
    return floor.sais(FloorProblem.of(sp, c), x0, xs0, U, K, lane_major(Z))


def mismatch(fl, ref) -> float:
    """Largest cost/control mismatch; inf when a crash flag differs."""
    if any(not np.array_equal(fl[n], ref[n]) for n in ("crashed_real", "crashed_nom")):
        return np.inf
    return max([rel_err(fl[n], ref[n]) for n in COSTS]
               + [rel_err(fl[n], lane_major(ref[n])) for n in ("v_nom", "v_real")])


def test_case_reaches_every_branch(case):
    ref = twin(case)
    cr, cn, c = ref["crashed_real"], ref["crashed_nom"], case[-1]
    assert (cr & ~cn).sum() > 0 and (cn & ~cr).sum() > 0 and (~cr & ~cn).sum() > 0.5 * N
    Sh = ref["S_hat"]
    assert 0 < (Sh > c.alpha).sum() < N  # the alpha clamp binds on some samples only
    for name in ("v_nom", "v_real"):
        v = ref[name]
        assert (v <= c.u_min).sum() > 0.02 * v.size and (v >= c.u_max).sum() > 0.02 * v.size
    assert np.abs(ref["v_real"] - ref["v_nom"]).max() > 0.1  # the feedback acts


@pytest.mark.parametrize("group", [2, 4])
def test_floor_sais_equals_twin(case, group):
    err = mismatch(floor_sais(case, group), twin(case))
    assert err <= RTOL, err


@pytest.mark.parametrize("change", [
    {"K": "zero"}, {"alpha": np.inf}, {"crash_cost": 1e8}, {"nu_mix": 0.0}, {"scene": "moved"}])
def test_floor_comparison_is_sharp(case, change):
    """The twin with one input changed no longer matches the floor: the floor reads each."""
    sp = case[0]
    key, val = next(iter(change.items()))
    if val == "zero":
        val = np.zeros_like(case[4])
    elif val == "moved":
        s = sp.model.scene_value.copy()
        s[0] += 0.05  # circle 0 moved 5 cm
        val = s
    fl = floor_sais(case)
    assert mismatch(fl, twin(case)) <= RTOL
    assert mismatch(fl, twin(case, **{key: val})) > 1e4 * RTOL


def test_floor_mppi_equals_twin(case):
    sp, x0, _, U, _, Z, c = case
    ref = mppi_twin(sp, np.tile(x0, (N, 1)), U, Z, c)
    fl = load_floor().mppi(FloorProblem.of(sp, c), x0, U, lane_major(Z))
    assert ref["crashed"].any() and not ref["crashed"].all()
    assert np.array_equal(fl["crashed"], ref["crashed"])
    assert max(rel_err(fl["S"], ref["S"]), rel_err(fl["v"], lane_major(ref["v"]))) <= RTOL
    other = mppi_twin(sp, np.tile(x0, (N, 1)), U, Z, replace(c, lam=2.0))
    assert rel_err(fl["S"], other["S"]) > 1e4 * RTOL


def test_floor_draws_the_kernels_noise(case):
    """floor_normals and the seeded floor draw exactly the kernels' normals for a seed."""
    sp, x0, xs0, U, K, _, c = case
    floor = load_floor()
    kernel_noise = Sampler(sp, "compiled").lib.normals(N, T, 2, 11)
    assert np.array_equal(floor.normals(N, T, 2, 11), kernel_noise)
    prob = FloorProblem.of(sp, c)
    seeded = floor.sais(prob, x0, xs0, U, K, N=N, seed=11)
    given = floor.sais(prob, x0, xs0, U, K, kernel_noise)
    for n, v in given.items():
        assert np.array_equal(v, seeded[n]), n
    other = floor.sais(prob, x0, xs0, U, K, N=N, seed=12)
    assert not np.array_equal(other["S_real"], seeded["S_real"])


def test_prepared_kernel_call_equals_the_library_call(case):
    """The split times the kernels through prepared calls; they compute what Sampler does."""
    sp, x0, xs0, U, K, _, c = case
    sampler = Sampler(sp, "compiled")
    _, cc = check_batch(sp, N, U, c)
    k = sampler.lib.sais
    carry = k.carry.pack(N, x=x0, x_nom=xs0)
    time_in = {"u": U, "K": K.reshape(T, -1)}
    for kw in ({"seed": 5}, {"noise": sampler.lib.normals(N, T, 2, 5)}):
        call, outs, res = prepared_kernel(k, carry, cc.kernel_consts(), time_in, **kw)
        call()
        ref = k(carry, consts=cc.kernel_consts(), time_in=time_in, seed=5)
        assert np.array_equal(res[:N], ref.result)
        for a, b in zip(outs, ref.lane_out, strict=True):
            assert np.array_equal(a[..., :N], b)


def test_floor_threads_give_the_same_result(case):
    floor = load_floor()
    before = floor.threads()
    try:
        floor.set_threads(1)
        one = floor_sais(case)
        floor.set_threads(2)
        two = floor_sais(case)
    finally:
        floor.set_threads(before)
    for n, v in one.items():
        assert np.array_equal(v, two[n]), n


def test_floor_problem_refuses_other_problems(case):
    sp, *_, c = case
    with pytest.raises(ValueError, match="clip_in_cost"):
        FloorProblem.of(sp, replace(c, clip_in_cost=False))
    plain = navigation_costs(double_integrator(obstacles=OBST, u_limit=5.0),
                             S=(10.0, 10.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="sp"):
        FloorProblem.of(plain, c)
    per = navigation_costs(embed_barrier(double_integrator(obstacles=OBST, u_limit=5.0),
                                         BarrierOptions(gamma=0.5)))
    with pytest.raises(ValueError, match="gamma"):
        FloorProblem.of(per, c)

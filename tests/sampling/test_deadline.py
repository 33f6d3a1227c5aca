"""The step deadline (``MPPIConfig.deadline_s``): bad values are refused naming the field;
with a deadline that never binds a step draws every sample (in chunks, each from its own seed,
weighted as one batch); with one that always binds it draws one chunk and says so; the
controllers with their own sampling loops refuse it; without a deadline nothing changes."""

from __future__ import annotations

import copy
import math
import time

import numpy as np
import pytest

from workbench.problem.barrier import embed_barrier
from workbench.problem.models import double_integrator
from workbench.problem.obstacles import Circle
from workbench.sampling import deadline
from workbench.sampling.deadline import (
    DeadlineHistory,
    JoinBuffers,
    StepClock,
    chunk_sizes,
    least_chunk,
    sample_within,
)
from workbench.sampling.methods.cbf_projection import CBFProjectionConfig, CBFProjectionMPPI
from workbench.sampling.methods.shield import ShieldConfig, ShieldMPPI
from workbench.sampling.methods.tube import TubeMPPI
from workbench.sampling.mppi import MPPI, MPPIConfig, join_mppi
from workbench.sampling.problem import navigation_costs
from workbench.sampling.robust import RMPPIConfig, RobustMPPI
from workbench.sampling.threshold import ConstantThreshold
from workbench.sampling.weights import importance_weights, weighted_controls

OBST = (Circle((2.0, 2.0), 0.8), Circle((3.5, 1.0), 0.5))
N, T, CHUNKS = 203, 25, 4
GOAL = (4.0, 4.0, 0.0, 0.0)
X0 = np.array([0.3, 0.5, 0.5, 0.4])
RTOL = 1e-12


@pytest.fixture(scope="module")
def problems():
    plain = double_integrator(obstacles=OBST, u_limit=5.0)
    return (navigation_costs(embed_barrier(plain)),
            navigation_costs(plain, S=(10.0, 10.0, 1.0, 1.0)))


def cfg(**kw) -> MPPIConfig:
    return MPPIConfig(n_samples=N, horizon=T, lam=1.3, sigma=(3.0, 2.4), backend="compiled",
                      **kw)


@pytest.mark.parametrize("kw, match", [
    ({"deadline_s": 0.0}, r"^MPPIConfig\.deadline_s = 0"),
    ({"deadline_s": -0.02}, r"^MPPIConfig\.deadline_s = -0\.02"),
    ({"deadline_s": math.nan}, r"^MPPIConfig\.deadline_s"),
    ({"deadline_s": math.inf}, r"^MPPIConfig\.deadline_s"),
    ({"deadline_s": True}, r"^MPPIConfig\.deadline_s"),
    ({"deadline_s": 0.05, "deadline_chunks": 0}, r"^MPPIConfig\.deadline_chunks = 0"),
    ({"deadline_s": 0.05, "deadline_chunks": N + 1},
     rf"^MPPIConfig\.deadline_chunks = {N + 1}"),
    ({"deadline_chunks": 4}, r"^MPPIConfig\.deadline_chunks = 4 .*set deadline_s"),
])
def test_bad_deadline_is_refused_naming_the_field(kw, match):
    with pytest.raises(ValueError, match=match):
        cfg(**kw)


def test_a_small_batch_without_a_deadline_is_accepted_and_chunks_default_to_the_samples():
    assert MPPIConfig(n_samples=8, horizon=5).deadline_chunks is None
    assert MPPIConfig(n_samples=8, horizon=5, deadline_s=0.05).chunks == 8
    assert MPPIConfig(n_samples=64, horizon=5, deadline_s=0.05).chunks == 16


def test_chunks_cover_the_samples():
    assert chunk_sizes(203, 4) == [51, 51, 51, 50]
    assert chunk_sizes(3, 8) == [1, 1, 1]
    assert sum(chunk_sizes(8192, 8)) == 8192


def test_loose_deadline_draws_every_sample_in_chunks(problems):
    """A deadline of an hour never binds: all N samples, weighted as one batch of the chunks
    drawn from the step's own seeds (the plan equals that batch's update to 1e-12)."""
    bas, _ = problems
    ctrl = MPPI(bas, GOAL, cfg(deadline_s=3600.0, deadline_chunks=CHUNKS))
    rng = np.random.default_rng(5)
    twin = copy.deepcopy(rng)
    st0 = ctrl.initial_state(X0)
    _, u, info = ctrl.step(st0, X0, rng)
    d = info.deadline
    assert d is not None and not d.truncated and not d.missed
    assert (d.samples, d.planned, d.iterations) == (N, N, 1)
    assert info.stats.n_samples == N
    xb = ctrl.sp.model.lift(X0, ctrl.consts.scene)
    parts = [ctrl.sampler.mppi(xb, st0.U, n, ctrl.consts, int(twin.integers(0, 2**63)))
             for n in chunk_sizes(N, CHUNKS)]
    b = join_mppi(parts)
    U = weighted_controls(b.v, importance_weights(b.S, ctrl.cfg.lam).w)
    np.testing.assert_allclose(u, U[0], rtol=RTOL, atol=0)


def test_tight_deadline_draws_the_least_chunk_and_says_so(problems):
    """A deadline no step can meet: one iteration of the least chunk (an eighth of the
    first), from the second step on too (its history says no more fits)."""
    bas, _ = problems
    ctrl = MPPI(bas, GOAL, cfg(deadline_s=1e-9, deadline_chunks=CHUNKS, iterations=3))
    st = ctrl.initial_state(X0)
    for _ in range(2):
        st, u, info = ctrl.step(st, X0, np.random.default_rng(5))
        d = info.deadline
        assert d.truncated and d.missed and d.iterations == 1
        assert d.samples == info.stats.n_samples == least_chunk(chunk_sizes(N, CHUNKS)[0]) == 7
        assert np.all(np.isfinite(u))


class FakeClock:
    """time.perf_counter for the deadline module: advanced by the draws (1 ms per sample)."""

    def __init__(self) -> None:
        self.now = 100.0

    def perf_counter(self) -> float:
        return self.now

    def process_time(self) -> float:  # the process computes all the time it waits
        return self.now


def test_a_deadline_that_fits_part_of_the_samples_shortens_the_last_chunk(monkeypatch):
    """Each sample costs 1 ms and each step's tail 5 ms; a 100 ms deadline keeps 90 ms after
    the guard, and each part needs at most half the time left. Step 1: 51 (no history yet),
    then 19 (of 39 ms left), 10 (of 20), and 5 would fit, below the least chunk (7): stop at
    80. Step 2 charges each sample the first step's tail per sample (5 ms / 80, the only one
    known): int(90 / 1.0625 / 2) = 42, then 9, 16 and 8: 75. Step 3 charges step 2's tail
    per sample instead (5 ms / 75; the first step's is never in the median): the same 75."""
    fake = FakeClock()
    monkeypatch.setattr(deadline, "time", fake)
    hist, steps = DeadlineHistory(), []
    for _ in range(3):
        clock = StepClock(0.1, fake.now, hist)
        sizes: list[int] = []

        def draw(n: int, seed: int, sizes: list[int] = sizes) -> int:
            sizes.append(n)
            fake.now += n * 1e-3
            return n

        got = sample_within(clock, N, CHUNKS, draw, np.random.default_rng(0), sum)
        assert got == sum(sizes) and clock.truncated
        fake.now += 5e-3  # the step's tail
        rep = clock.report(N)
        assert not rep.missed
        assert rep.chunks == tuple((n, pytest.approx(n * 1e-3, rel=1e-9),
                                    pytest.approx(n * 1e-3, rel=1e-9), 1) for n in sizes)
        assert rep.tail_s == pytest.approx(5e-3, rel=1e-9)
        steps.append(sizes)
    assert steps == [[51, 19, 10], [42, 9, 16, 8], [42, 9, 16, 8]]
    assert hist.tail_rate() == pytest.approx(5e-3 / 75, rel=1e-9)  # median of steps 2, 3


def test_a_stall_is_kept_free_in_later_steps(monkeypatch):
    """Samples cost 1 ms and one chunk waited 4 ms for a core: that excess over the rate is
    kept free from then on, so 4 ms less fits (at the rate, before the slowdown allowance)."""
    fake = FakeClock()
    monkeypatch.setattr(deadline, "time", fake)
    calm, stalled = DeadlineHistory(), DeadlineHistory()
    for h, wait in ((calm, 0.0), (stalled, 4e-3)):
        h.add(51, 51e-3)
        h.add(39, 39e-3 + wait)
    assert stalled.stall() == pytest.approx(4e-3, rel=1e-9) and calm.stall() == 0.0
    rate = stalled.rate()
    assert rate == pytest.approx(94e-3 / 90, rel=1e-12)
    free = StepClock(0.1, fake.now, calm).room()
    held = StepClock(0.1, fake.now, stalled).room()
    assert free == pytest.approx(90, rel=1e-9)  # 90 ms after the guard at 1 ms per sample
    assert held == pytest.approx((90e-3 - 4e-3) / rate, rel=1e-9)


def test_history_rate_and_stall():
    h = DeadlineHistory()
    assert h.rate() == 0.0 and h.stall() == 0.0
    h.add(10, 0.010)  # the first chunk sets the rate; no excess yet
    h.add(10, 0.015)  # 5 ms over the 1 ms per sample expected
    h.add(20, 0.010)  # faster than expected: no negative excess
    assert h.stall() == pytest.approx(0.005, rel=1e-12)
    assert h.rate() == pytest.approx(0.035 / 40, rel=1e-12)
    for _ in range(deadline.WINDOW):  # WINDOW fast chunks: the long rate still holds the
        h.add(10, 0.002)                 # slow ones (the slower of the two rates counts)
    assert h.rate() == pytest.approx((0.035 + deadline.WINDOW * 0.002)
                                     / (40 + deadline.WINDOW * 10), rel=1e-12)
    assert h.stall() == pytest.approx(0.005, rel=1e-12)  # the stall is remembered as long
    for _ in range(deadline.STALL_WINDOW):
        h.add(10, 0.002)
    assert h.stall() == 0.0
    assert h.rate() == pytest.approx(0.0002, rel=1e-12)
    h.add(10, 0.02)  # a slow chunk: the short rate reacts first
    assert h.rate() == pytest.approx((0.02 + (deadline.WINDOW - 1) * 0.002)
                                     / (deadline.WINDOW * 10), rel=1e-12)


def test_rates_are_kept_per_thread_count():
    """A chunk is judged by the rate of the thread count it runs on, never faster than on
    fewer threads; with no chunk on that count yet, by the others' rate, with no gain from
    more threads and a full loss from fewer."""
    h = DeadlineHistory()
    h.add(100, 0.1, threads=2)  # 1 ms per sample on 2 threads
    assert h.rate(2) == pytest.approx(1e-3, rel=1e-12)
    assert h.rate(1) == pytest.approx(2e-3, rel=1e-12)  # none on 1 thread yet: twice as slow
    assert h.rate(4) == pytest.approx(1e-3, rel=1e-12)  # no gain assumed from more
    h.add(100, 0.15, threads=1)  # 1.5 ms on 1 thread: faster than the 2 ms assumed
    assert h.stall() == 0.0
    assert h.rate(1) == pytest.approx(1.5e-3, rel=1e-12)
    assert h.rate(2) == pytest.approx(1.5e-3, rel=1e-12)  # not faster than on 1 thread
    h.add(100, 0.05, threads=1)  # 1 thread now 1 ms per sample on average
    h.add(100, 0.3, threads=2)  # 2 threads slower under load: 2 ms over their 2 chunks
    assert h.rate(2) == pytest.approx(0.4 / 200, rel=1e-12)


def test_a_part_that_runs_on_fewer_threads_is_judged_at_their_rate(monkeypatch):
    """Chunks of 100 run on 2 threads, smaller ones on 1 (the kernels' small-batch rule): the
    part of a chunk that fits is sized at the 1-thread rate."""
    fake = FakeClock()
    monkeypatch.setattr(deadline, "time", fake)
    hist = DeadlineHistory()
    hist.add(100, 0.05, threads=2)  # 0.5 ms per sample on 2 threads
    clock = StepClock(0.1, fake.now, hist, threads_of=lambda n: 2 if n >= 100 else 1)
    fake.now += 0.05  # 40 ms left after the 10 ms guard
    # 80 fit on 2 threads; that part runs on 1 thread, which has no chunk yet: twice as slow
    assert clock.fits(100) == pytest.approx(40, rel=1e-9)
    assert StepClock(0.1, fake.now - 0.05, hist, threads_of=lambda n: 2).fits(100) == \
        pytest.approx(80, rel=1e-9)


def test_no_room_for_a_later_iteration_returns_none():
    hist = DeadlineHistory()
    hist.add(1, 1.0)  # one second per sample: nothing fits a 10 ms deadline
    clock = StepClock(0.01, time.perf_counter(), hist)
    clock.iterations = 1
    assert sample_within(clock, 64, 4, lambda n, s: n, np.random.default_rng(0), sum) is None
    clock.iterations = 0  # the first chunk of a step always runs, shortened
    assert sample_within(clock, 64, 4, lambda n, s: n, np.random.default_rng(0), sum) == 2


def test_robust_controller_applies_the_deadline(problems):
    bas, _ = problems
    loose = RobustMPPI(bas, GOAL, cfg(deadline_s=3600.0, deadline_chunks=CHUNKS),
                       RMPPIConfig(), threshold=ConstantThreshold(-1e9))
    tight = RobustMPPI(bas, GOAL, cfg(deadline_s=1e-9, deadline_chunks=CHUNKS),
                       RMPPIConfig(), threshold=ConstantThreshold(-1e9))
    for ctrl, n, cut in ((loose, N, False),
                         (tight, least_chunk(chunk_sizes(N, CHUNKS)[0]), True)):
        _, u, info = ctrl.step(ctrl.initial_state(X0), X0, np.random.default_rng(2))
        assert info.deadline.truncated is cut and info.deadline.samples == n
        assert info.stats.n_samples == n and np.all(np.isfinite(u))


def test_no_deadline_reports_nothing_and_stays_reproducible(problems):
    bas, _ = problems
    ctrl = MPPI(bas, GOAL, cfg())
    a = ctrl.step(ctrl.initial_state(X0), X0, np.random.default_rng(9))
    b = ctrl.step(ctrl.initial_state(X0), X0, np.random.default_rng(9))
    assert a[2].deadline is None
    np.testing.assert_array_equal(a[1], b[1])
    np.testing.assert_array_equal(a[0].U, b[0].U)


def test_controllers_without_a_deadline_refuse_it(problems):
    bas, phys = problems
    c = cfg(deadline_s=0.05)
    for build in (lambda: TubeMPPI(phys, GOAL, c),
                  lambda: ShieldMPPI(phys, GOAL, c, ShieldConfig(gamma=0.1)),
                  lambda: CBFProjectionMPPI(phys, GOAL, c, CBFProjectionConfig(gamma=0.1)),
                  lambda: RobustMPPI(bas, GOAL, c, RMPPIConfig(diagnostics=True),
                                     threshold=ConstantThreshold(-1e9))):
        with pytest.raises(ValueError, match=r"^MPPIConfig\.deadline_s = 0\.05"):
            build()


def test_join_buffers_join_into_one_buffer_per_field_and_reuse_it():
    """A join equals np.concatenate and is contiguous (BLAS reads it without a copy); a
    later join that fits reuses the field's buffer (the same memory), one that does not, or
    of another dtype, gets a new one."""
    rng = np.random.default_rng(3)
    jb = JoinBuffers(10)
    parts = [rng.normal(size=(4, 2, n)) for n in (3, 5)]
    a = jb.cat("v", parts, -1)
    np.testing.assert_array_equal(a, np.concatenate(parts, axis=-1))
    assert a.flags.c_contiguous and jb.arrays["v"].size == 4 * 2 * 10
    buf = jb.arrays["v"]
    b = jb.cat("v", [parts[1], parts[0], parts[0]], -1)  # 11 samples: more than 10
    np.testing.assert_array_equal(b, np.concatenate([parts[1], parts[0], parts[0]], axis=-1))
    assert jb.arrays["v"].size == 4 * 2 * 11 and not np.shares_memory(b, buf)
    c = jb.cat("v", [parts[0], parts[0]], -1)  # 6 fit: the same buffer
    np.testing.assert_array_equal(c, np.concatenate([parts[0], parts[0]], axis=-1))
    assert np.shares_memory(b, c) and c.flags.c_contiguous
    flags = [rng.random(n) < 0.5 for n in (3, 4)]
    f = jb.cat("crashed", flags)
    assert f.dtype == bool
    np.testing.assert_array_equal(f, np.concatenate(flags))
    wide = [rng.normal(size=(4, 3, 9))]  # 108 entries: more than the 88 there is room for
    np.testing.assert_array_equal(jb.cat("v", wide, -1), wide[0])
    assert jb.arrays["v"].size == 4 * 3 * 10
    rows = [rng.normal(size=(n, 3)) for n in (2, 3)]  # along the first axis
    np.testing.assert_array_equal(jb.cat("rows", rows), np.concatenate(rows))
    as32 = [p.astype(np.float32) for p in parts]  # another dtype: a new buffer
    assert jb.cat("v", as32, -1).dtype == np.float32


def test_a_deadline_step_runs_blas_on_one_thread_and_pauses_the_collector(problems):
    """MPPI and the robust controllers: inside a step with a deadline numpy's BLAS has one
    thread and Python's cyclic garbage collector is off; without a deadline, and after the
    step, both are as set before (2 threads; the collector on, or off when it was off)."""
    import gc

    from threadpoolctl import ThreadpoolController, threadpool_limits

    blas = ThreadpoolController().select(user_api="blas")
    if not blas.lib_controllers:
        pytest.skip("numpy's BLAS is not one threadpoolctl can limit")
    bas, _ = problems
    seen: dict[tuple[str, float | None, bool], set[tuple[int, bool]]] = {}
    for deadline_s in (None, 1.0):
        ctrls = {"mppi": MPPI(bas, GOAL, cfg(deadline_s=deadline_s)),
                 "robust": RobustMPPI(bas, GOAL, cfg(deadline_s=deadline_s),
                                      threshold=ConstantThreshold(1e4))}
        for name, ctrl in ctrls.items():
            into: list[set[tuple[int, bool]]] = []  # where the spies record, per run
            for kernel in ("mppi", "sais"):
                orig = getattr(ctrl.sampler, kernel)

                def spy(*a, orig=orig, into=into, **k):
                    into[-1].add((blas.info()[0]["num_threads"], gc.isenabled()))
                    return orig(*a, **k)

                setattr(ctrl.sampler, kernel, spy)
            for collecting in (True, False):
                into.append(seen.setdefault((name, deadline_s, collecting), set()))
                was = gc.isenabled()
                (gc.enable if collecting else gc.disable)()
                try:
                    with threadpool_limits(2, user_api="blas"):
                        ctrl.step(ctrl.initial_state(X0), X0, np.random.default_rng(0))
                        assert blas.info()[0]["num_threads"] == 2
                    assert gc.isenabled() == collecting
                finally:
                    (gc.enable if was else gc.disable)()
    for (_, deadline_s, collecting), state in seen.items():
        assert state == ({(2, collecting)} if deadline_s is None else {(1, False)})

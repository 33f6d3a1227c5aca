"""Recorded sample trajectories (``ctrl.record_samples``) of every sampling controller against
the batch they come from.

For each controller the step's last batch is drawn again from the same seed (the kernels are
deterministic in it), and the NumPy twin is fed the kernel's noise: the recorded trajectories
equal the twin's (Robust MPPI: the diagnostics batch's own X, X_nom) per element to 1e-10
relative, the controls, crash flags and weights equal the batch's bitwise, and the crash flags
agree with the margins along the recorded trajectories. Recording is off by default, does no
work then, and never changes what the controller does.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

from workbench.codegen.fastcall import FastFunction
from workbench.problem.barrier import embed_barrier
from workbench.problem.models import double_integrator
from workbench.problem.obstacles import Circle
from workbench.sampling import samples as samples_module
from workbench.sampling.feedback import Gains
from workbench.sampling.methods.cbf_projection import CBFProjectionConfig, CBFProjectionMPPI
from workbench.sampling.methods.gatekeeper import Gatekeeper, braking_backup
from workbench.sampling.methods.sampler import SafeOptions
from workbench.sampling.methods.shield import ShieldConfig, ShieldMPPI
from workbench.sampling.methods.tube import TubeMPPI
from workbench.sampling.methods.twin import safe_twin
from workbench.sampling.mppi import MPPI, MPPIConfig
from workbench.sampling.problem import navigation_costs
from workbench.sampling.robust import RMPPIConfig, RobustMPPI
from workbench.sampling.samples import (
    Rollout,
    SampleTrajectories,
    kept_lanes,
)
from workbench.sampling.threshold import ConstantThreshold
from workbench.sampling.twin import mppi_twin
from workbench.sampling.weights import importance_weights

OBST = (Circle((2.0, 2.0), 0.8), Circle((3.5, 1.0), 0.5), Circle((1.0, 3.2), 0.6))
N, T, K = 125, 30, 40
GOAL = (4.0, 4.0, 0.0, 0.0)
KICK = np.array([0.0, 0.0, 0.3, -0.2])  # velocity kick before the second step, m/s
# per element |a - b| <= RTOL max(|a|, |b|, 1), as in the sampler kernel tests
RTOL = 1e-10
KINDS = ("mppi", "rmppi", "tube", "cbf_projection", "shield", "gatekeeper")


def rel_err(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    assert a.shape == b.shape
    return float(np.max(np.abs(a - b) / np.maximum(np.maximum(np.abs(a), np.abs(b)), 1.0)))


class FixedGains:
    """A feedback law with fixed nonzero gains (no iLQG): u += K (x - x_nom)."""

    name = "fixed"

    def __init__(self, nx: int):
        k = np.zeros((2, nx))
        k[0, 0], k[1, 1], k[0, 2], k[1, 3] = -3.0, -3.0, -1.5, -1.5
        self.K = np.repeat(k[None], T, axis=0)

    def gains(self, x_nom, U, previous, stride) -> Gains:
        return Gains(K=self.K.copy())

    def set_scene(self, scene) -> None:
        pass


@pytest.fixture(scope="module")
def problems():
    plain = double_integrator(obstacles=OBST, u_limit=5.0)
    bas = navigation_costs(embed_barrier(plain))
    phys = navigation_costs(plain, S=(10.0, 10.0, 1.0, 1.0))
    cfg = MPPIConfig(n_samples=N, horizon=T, lam=1.3, sigma=(3.0, 2.4), nu_mix=0.1,
                     backend="compiled")
    return plain, bas, phys, cfg


def start() -> np.ndarray:
    """0.9 m off the line through the first obstacle's centre, heading along it at 2 m/s:
    some samples crash, most do not."""
    return np.array([1.0 - 0.9 / np.sqrt(2.0), 1.0 + 0.9 / np.sqrt(2.0), np.sqrt(2.0),
                     np.sqrt(2.0)])


def make(kind: str, problems):
    plain, bas, phys, cfg = problems
    if kind == "mppi":
        return MPPI(bas, GOAL, cfg)
    if kind == "rmppi":  # alpha below every free energy: the propagated nominal is taken
        return RobustMPPI(bas, GOAL, cfg, RMPPIConfig(diagnostics=True), FixedGains(bas.nx),
                          ConstantThreshold(-1e9))
    if kind == "tube":
        return TubeMPPI(phys, GOAL, cfg, feedback=FixedGains(phys.nx))
    if kind == "cbf_projection":
        return CBFProjectionMPPI(phys, GOAL, cfg, CBFProjectionConfig(gamma=0.1))
    if kind == "shield":
        return ShieldMPPI(phys, GOAL, cfg, ShieldConfig(gamma=0.1))
    return Gatekeeper(MPPI(phys, GOAL, cfg), plain, braking_backup(plain))


def two_steps(ctrl, rng):
    """Step from start(), then from the model's next state plus a velocity kick (so that the
    nominal systems differ from the measured one); (rng copy before step 2, state before
    step 2, x of step 2, info of step 2)."""
    x, dt = start(), 0.02  # double_integrator's default step
    st, u, _ = ctrl.step(ctrl.initial_state(x), x, rng)
    x2 = np.concatenate([x[:2] + dt * x[2:], x[2:] + dt * u]) + KICK
    before, st_before = copy.deepcopy(rng), st
    _, _, info = ctrl.step(st, x2, rng)
    return before, st_before, x2, info


def margins_crashed(sp, X, scene) -> np.ndarray:
    """Crash flags of trajectories (K, T+1, nx) by the crash rule: some min_i h_i(x_k) <=
    eps_h, k = 1..T."""
    m = FastFunction(sp.functions()["margins"])
    h = np.array([[np.min(m(x, scene)[0]) for x in traj[1:]] for traj in X])
    return np.any(h <= sp.eps_h, axis=1)


def noise(sampler, seed: int) -> np.ndarray:
    return np.transpose(sampler.lib.normals(N, T, 2, seed), (2, 0, 1))


def lanes(v, idx) -> np.ndarray:
    return np.transpose(v[:, :, idx], (2, 0, 1))


@pytest.fixture(scope="module")
def recorded(problems):
    """Each controller's second step with recording on (K samples, spread)."""
    out = {}
    for kind in KINDS:
        ctrl = make(kind, problems)
        ctrl.record_samples(K)
        out[kind] = (ctrl, *two_steps(ctrl, np.random.default_rng(14)))
    return out


def check(rec: SampleTrajectories, *, X, crashed, v, w, X_nom=None, crashed_nom=None,
          v_nom=None, w_real=None) -> dict[str, float]:
    """The record against the batch (bitwise: lanes, flags, controls, weights) and reference
    trajectories (per element); returns the trajectory errors."""
    idx = kept_lanes(N, K, "spread")
    np.testing.assert_array_equal(rec.index, idx)
    assert rec.real.shape == X[idx].shape == (K, T + 1, X.shape[-1])
    np.testing.assert_array_equal(rec.crashed, crashed[idx])
    np.testing.assert_array_equal(rec.controls, lanes(v, idx))
    np.testing.assert_array_equal(rec.weights, w[idx])
    errs = {"real": rel_err(rec.real, X[idx])}
    if X_nom is None:
        assert rec.nominal is None and rec.crashed_nominal is None
    else:
        errs["nominal"] = rel_err(rec.nominal, X_nom[idx])
        np.testing.assert_array_equal(rec.crashed_nominal, crashed_nom[idx])
        np.testing.assert_array_equal(rec.controls_nominal, lanes(v_nom, idx))
    if w_real is None:
        assert rec.weights_real is None
    else:
        np.testing.assert_array_equal(rec.weights_real, w_real[idx])
    return errs


def test_mppi_samples_are_the_batch_rolled_out(recorded, problems):
    ctrl, rng, st, x, info = recorded["mppi"]
    rec = info.samples
    seed = int(rng.integers(0, 2**63))
    xb = ctrl.sp.model.lift(x, ctrl.scene)
    b = ctrl.sampler.mppi(xb, st.U, N, ctrl.consts, seed)
    ref = mppi_twin(ctrl.sp, np.tile(xb, (N, 1)), st.U, noise(ctrl.sampler, seed),
                    ctrl.consts)
    errs = check(rec, X=ref["X"], crashed=b.crashed, v=b.v,
                 w=importance_weights(b.S, ctrl.cfg.lam).w)
    assert max(errs.values()) <= RTOL, errs
    np.testing.assert_array_equal(ref["crashed"], b.crashed)
    # the kept lanes cover both outcomes, and the flags follow from the recorded states
    assert 0 < rec.n_crashed < K
    np.testing.assert_array_equal(margins_crashed(ctrl.sp, rec.real, ctrl.scene), rec.crashed)
    assert rec.position == (0, 1) and rec.n_samples == N and rec.keep == "spread"
    np.testing.assert_array_equal(rec.scene, ctrl.scene)
    assert 0 < rec.mass < 1 and rec.mass == pytest.approx(rec.weights.sum())


def test_robust_mppi_samples_equal_the_diagnostics_batch(recorded):
    ctrl, _, _, x, info = recorded["rmppi"]
    rec, b = info.samples, info.batch
    assert info.nominal_differs  # the propagated nominal, not the kicked measured state
    lam = ctrl.cfg.lam
    errs = check(rec, X=np.transpose(b.X, (2, 0, 1)), crashed=b.crashed_real, v=b.v_real,
                 w=importance_weights(b.S_nom, lam).w, X_nom=np.transpose(b.X_nom, (2, 0, 1)),
                 crashed_nom=b.crashed_nom, v_nom=b.v_nom,
                 w_real=importance_weights(b.S_real, lam).w)
    assert max(errs.values()) <= RTOL, errs  # measured: 0 (the same generated dynamics)
    np.testing.assert_array_equal(rec.real[:, 0], np.tile(ctrl.sp.model.lift(x, ctrl.scene),
                                                          (K, 1)))
    np.testing.assert_array_equal(rec.nominal[:, 0], np.tile(info.x_nom, (K, 1)))
    # real and nominal samples differ (feedback on x - x_nom); flags follow from the states
    assert rel_err(rec.real, rec.nominal) > 1e-3
    np.testing.assert_array_equal(margins_crashed(ctrl.sp, rec.real, ctrl.scene), rec.crashed)
    np.testing.assert_array_equal(margins_crashed(ctrl.sp, rec.nominal, ctrl.scene),
                                  rec.crashed_nominal)
    assert rec.n_crashed > 0


def test_a_wrong_lane_or_start_state_is_caught(recorded):
    """The comparison is sensitive: the recorded controls rolled out one lane off, or from the
    nominal start instead of the measured one, miss the diagnostics batch by far more than
    the tolerance."""
    ctrl, _, _, _, info = recorded["rmppi"]
    rec, b = info.samples, info.batch
    X = np.transpose(b.X, (2, 0, 1))[rec.index]
    roll = Rollout(ctrl.sp)
    shifted = roll(rec.real[:, 0], np.roll(rec.controls, 1, axis=0), ctrl.scene)
    from_nominal = roll(info.x_nom, rec.controls, ctrl.scene)
    assert rel_err(roll(rec.real[:, 0], rec.controls, ctrl.scene), X) <= RTOL
    assert rel_err(shifted, X) > 1e3 * RTOL
    assert rel_err(from_nominal, X) > 1e3 * RTOL
    vm = Rollout(ctrl.sp, backend="casadi")  # the virtual machine gives the same states
    assert rel_err(vm(rec.real[:, 0], rec.controls, ctrl.scene), X) <= RTOL


def test_tube_samples_are_both_batches(recorded):
    ctrl, rng, st, x, info = recorded["tube"]
    rec = info.samples
    # the nominal reset after its batch: the batch started from the propagated nominal
    assert info.nominal_reset and not np.array_equal(st.x_nom, x)
    seed = int(rng.integers(0, 2**63))
    c, lam = ctrl.consts, ctrl.cfg.lam
    ba = ctrl.sampler.mppi(x, st.U_a, N, c, seed)
    bn = ctrl.sampler.mppi(st.x_nom, st.U_n, N, c, seed)
    Z = noise(ctrl.sampler, seed)
    ra = mppi_twin(ctrl.sp, np.tile(x, (N, 1)), st.U_a, Z, c)
    rn = mppi_twin(ctrl.sp, np.tile(st.x_nom, (N, 1)), st.U_n, Z, c)
    errs = check(rec, X=ra["X"], crashed=ba.crashed, v=ba.v,
                 w=importance_weights(bn.S, lam).w, X_nom=rn["X"], crashed_nom=bn.crashed,
                 v_nom=bn.v, w_real=importance_weights(ba.S, lam).w)
    assert max(errs.values()) <= RTOL, errs
    np.testing.assert_array_equal(rec.nominal[:, 0], np.tile(st.x_nom, (K, 1)))
    np.testing.assert_array_equal(margins_crashed(ctrl.sp, rec.real, c.scene), rec.crashed)
    np.testing.assert_array_equal(margins_crashed(ctrl.sp, rec.nominal, c.scene),
                                  rec.crashed_nominal)


@pytest.mark.parametrize("kind", ["cbf_projection", "shield"])
def test_safe_method_samples_are_the_batch_rolled_out(recorded, kind):
    ctrl, rng, st, x, info = recorded[kind]
    rec = info.samples
    seed = int(rng.integers(0, 2**63))
    o: SafeOptions = ctrl.planner.options
    b = ctrl.sampler.batch(x, st.U, N, ctrl.consts, o, seed)
    ref = safe_twin(ctrl.sp, np.tile(x, (N, 1)), st.U, noise(ctrl.sampler, seed),
                    ctrl.consts, o.project, o.w_dcbf, o.gamma)
    errs = check(rec, X=ref["X"], crashed=b.crashed, v=b.v,
                 w=importance_weights(b.S, ctrl.cfg.lam).w)
    assert max(errs.values()) <= RTOL, errs
    np.testing.assert_array_equal(margins_crashed(ctrl.sp, rec.real, ctrl.scene), rec.crashed)
    if kind == "cbf_projection":  # the recorded controls are the projected ones
        assert info.projected > 0


def test_gatekeeper_hands_out_the_inner_samples(recorded):
    ctrl, rng, st, x, info = recorded["gatekeeper"]
    inner = ctrl.inner
    assert info.samples is info.inner.samples is not None
    assert inner.sample_recorder is not None and inner.sample_recorder.k == K
    seed = int(rng.integers(0, 2**63))
    b = inner.sampler.mppi(x, st.inner.U, N, inner.consts, seed)
    ref = mppi_twin(inner.sp, np.tile(x, (N, 1)), st.inner.U, noise(inner.sampler, seed),
                    inner.consts)
    errs = check(info.samples, X=ref["X"], crashed=b.crashed, v=b.v,
                 w=importance_weights(b.S, inner.cfg.lam).w)
    assert max(errs.values()) <= RTOL, errs


@pytest.mark.parametrize("kind", KINDS)
def test_off_by_default_no_work_and_the_same_controls(problems, kind, monkeypatch):
    """Off: info.samples is None and nothing of the recording runs. On: the controls, the
    plan and the generator's state are exactly those of a run without it."""
    off = make(kind, problems)
    assert getattr(off, "sample_recorder", None) is None

    def boom(*a, **k):
        raise AssertionError("recording ran while off")

    with monkeypatch.context() as mp:
        mp.setattr(samples_module.SampleRecorder, "record", boom)
        mp.setattr(samples_module.Rollout, "__call__", boom)
        r_off = np.random.default_rng(3)
        _, st_off, x_off, info_off = two_steps(off, r_off)
    assert info_off.samples is None
    on = make(kind, problems)
    on.record_samples(16, keep="top")
    r_on = np.random.default_rng(3)
    _, st_on, x_on, info_on = two_steps(on, r_on)
    assert info_on.samples is not None and info_on.samples.k == 16
    np.testing.assert_array_equal(x_on, x_off)  # the first step's control was the same
    for a, b in zip(vars(st_on).values(), vars(st_off).values(), strict=True):
        if isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b)
    assert r_on.bit_generator.state == r_off.bit_generator.state
    on.record_samples(0)  # and off again
    _, _, _, info = two_steps(on, np.random.default_rng(3))
    assert info.samples is None


def test_top_keeps_the_heaviest_and_all_lanes_hold_all_the_mass(problems):
    ctrl = make("mppi", problems)
    ctrl.record_samples(10, keep="top")
    rng = np.random.default_rng(4)
    before = copy.deepcopy(rng)
    _, _, info = ctrl.step(ctrl.initial_state(), start(), rng)
    rec = info.samples
    seed = int(before.integers(0, 2**63))
    b = ctrl.sampler.mppi(ctrl.sp.model.lift(start(), ctrl.scene), np.zeros((T, 2)), N,
                          ctrl.consts, seed)
    w = importance_weights(b.S, ctrl.cfg.lam).w
    np.testing.assert_array_equal(rec.index, np.sort(np.argsort(-w, kind="stable")[:10]))
    assert rec.weights.min() >= np.sort(w)[-10]
    assert rec.mass == pytest.approx(np.sort(w)[-10:].sum(), rel=1e-12)
    ctrl.record_samples(10 * N)  # more than N: every lane, all the weight
    _, _, info = ctrl.step(ctrl.initial_state(), start(), np.random.default_rng(4))
    assert info.samples.k == N and info.samples.mass == pytest.approx(1.0, rel=1e-12)
    np.testing.assert_array_equal(info.samples.index, np.arange(N))


def test_recording_settings_are_checked(problems):
    ctrl = make("mppi", problems)
    for k in (True, -1, 2.5, 2**40):
        with pytest.raises(ValueError, match=r"record_samples\.k"):
            ctrl.record_samples(k)
    with pytest.raises(ValueError, match=r"record_samples\.keep"):
        ctrl.record_samples(8, keep="best")
    assert ctrl.sample_recorder is None
    gk = make("gatekeeper", problems)
    with pytest.raises(ValueError, match=r"record_samples\.keep"):
        gk.record_samples(8, keep="best")

    class Plain:
        def initial_state(self, x0=None):
            return None

        def step(self, state, x, rng):
            return None, np.zeros(2), None

    plain = problems[0]
    with pytest.raises(ValueError, match="record_samples"):
        Gatekeeper(Plain(), plain, braking_backup(plain)).record_samples(4)
    with pytest.raises(ValueError, match=r"SampleTrajectories\.controls"):
        SampleTrajectories(real=np.zeros((3, 5, 4)), controls=np.zeros((3, 5, 2)),
                           crashed=np.zeros(3, bool), weights=np.zeros(3), index=np.arange(3),
                           n_samples=3)

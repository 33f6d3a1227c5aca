"""Demo (not a study): SA-RMPPI on the navigation map with the Lemma-1 checks at every step.

    python -m workbench.bound.demo [--steps 50] [--variance 10] [--seed 0] [--kappa 0.1]
                                   [--space physical|augmented]

``--kappa`` is the progress-indexed alpha rule's margin. The default here is 0.1, not the
rule's default 1.0: at variance 10 the default never rejects the real state (measured: 0 of
300 steps), so the nominal equals the real state, R = 0 and every check is trivial.

Prints, per test and set of Lipschitz constants, the fraction of steps where it holds and the
median slack; the strata of assumptions §11.3; the steps where T1 fails and why; and the cost of the
diagnostics per step (each step also runs without them on a copy of the generator: same
control, timed alternately).
"""

from __future__ import annotations

import argparse
import copy
import time

import numpy as np

from workbench.bound.checks import episode_checks
from workbench.bound.episode import BoundRecorder
from workbench.bound.step import BoundConfig, BoundEstimator
from workbench.bound.summary import summarize
from workbench.sampling.threshold import AlphaRule
from workbench.scenarios.navigation import navigation_setup
from workbench.sim import Disturbance, closed_loop


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--variance", type=float, default=10.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--kappa", type=float, default=0.1)
    ap.add_argument("--space", choices=("physical", "augmented"), default="physical",
                    help="norm of R and L: physical state with beta = B(h(p)), or [x; beta]")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    nav = navigation_setup()
    # progress-indexed alpha (one undisturbed calibration run)
    ctrl = nav.controller("sa_rmppi", rule=AlphaRule(kappa=a.kappa))
    t1 = time.perf_counter()
    dist = Disturbance(level=a.variance)
    est = BoundEstimator(ctrl, dist, BoundConfig(space=a.space))
    t2 = time.perf_counter()
    print(f"set-up: controller + alpha calibration {t1 - t0:.1f} s, global Lipschitz constant "
          f"{t2 - t1:.1f} s ({est.grid.describe(ctrl.sp.eps_h)})")
    g = est.global_
    print(f"norm: {a.space} state; global L_q = {g.L_q:.3g}, L_phi = {g.L_phi:.3g} over "
          f"{g.points_q} points ({g.excluded_q} inside obstacles); D = {est.D:.4g}")

    rec = BoundRecorder(est)
    timed = _Interleaved(ctrl, rec)
    ep = closed_loop(timed, nav.plant, nav.x0, a.steps, np.random.default_rng(a.seed),
                     np.random.default_rng(a.seed + 1), dist, keep_infos=False)
    same = timed.same
    steps = rec.records
    print(f"\n{len(steps)} steps at variance {a.variance:g} (alpha: progress, kappa {a.kappa:g}), "
          f"crashed: {ep.crashed}; same controls "
          f"with and without diagnostics: {same}")
    n_safe = sum(s.all_real_safe for s in steps)
    print(f"strata: all real samples safe {n_safe}/{len(steps)}, fallback used "
          f"{sum(s.fallback_used for s in steps)}, nominal differed from real "
          f"{sum(s.nominal_differs for s in steps)}, F_nom <= alpha "
          f"{sum(s.nominal_admissible for s in steps)}")
    print("medians: R {:.3g} (R99 {:.3g}, position {:.3g}, about mean nominal {:.3g}), "
          "local L_q {:.3g}, L_phi {:.3g}, E {:.3g}, ESS real {:.3g}, D_F {:.3g}".format(
              *(float(np.median(v)) for v in (
                  [s.tube.R for s in steps], [s.tube.R99 for s in steps],
                  [s.tube.R_position for s in steps], [s.tube.R_mean_nominal for s in steps],
                  [s.local.L_q for s in steps], [s.local.L_phi for s in steps],
                  [s.E for s in steps], [s.F_real.ess for s in steps],
                  [s.D_F for s in steps]))))
    print(f"secant check (local) passed on {sum(s.local.secant_ok for s in steps)}/{len(steps)} "
          "steps")

    checks = episode_checks(steps)
    rows = summarize(steps, checks)
    get = {(r.test, r.constants, r.stratum): r for r in rows}
    print(f"\n{'test':5} {'const':6} {'n':>3} {'holds':>5} {'95% interval':>13} {'med slack':>10} "
          f"{'5% slack':>10} {'glob/loc term':>13} | holds: all real safe, nominal differs")
    for r in (r for r in rows if r.stratum == "all"):
        ratio = "" if r.constants != "global" else f"{r.term_ratio:.3g}"
        extra = [get.get((r.test, r.constants, k)) for k in ("all_real_safe", "nominal_differs")]
        extra_s = ", ".join(f"{e.fraction_holding:.2f} of {e.n_steps}" if e else "-"
                            for e in extra)
        print(f"{r.test:5} {r.constants:6} {r.n_steps:3d} {r.fraction_holding:5.2f} "
              f"[{r.interval[0]:.2f}, {r.interval[1]:.2f}] {r.slack_q50:10.4g} "
              f"{r.slack_q05:10.4g} {ratio:>13} | {extra_s}")
    for i, cs in enumerate(checks):
        for c in cs:
            if c.constants == "local" and not c.holds:
                print(f"{c.test} (local) fails at step {i}: {_why(c, steps, i)}")

    ts = np.median(rec.step_time_s) * 1e3
    tb = np.median(rec.bound_time_s) * 1e3
    tp = np.median(timed.plain_s) * 1e3
    print(f"\nper step (median): plain SA-RMPPI step {tp:.1f} ms; with diagnostic batch "
          f"{ts:.1f} ms ({ts - tp:+.1f}); estimators {tb:.1f} ms; total {ts + tb:.1f} ms = "
          f"{(ts + tb) / tp:.1f}x a plain step")


class _Interleaved:
    """Each step: the plain controller on a copy of the generator (timed, control compared),
    then the recorder (diagnostic step + estimators) — interleaved, so that load from other
    processes hits both timings alike."""

    def __init__(self, ctrl, rec: BoundRecorder):
        self.ctrl, self.rec = ctrl, rec
        self.plain_s: list[float] = []
        self.same = True

    def initial_state(self, x0=None):
        return self.rec.initial_state(x0)

    def step(self, state, x, rng):
        t0 = time.perf_counter()
        _, u0, _ = self.ctrl.step(state, x, copy.deepcopy(rng))
        self.plain_s.append(time.perf_counter() - t0)
        state, u, info = self.rec.step(state, x, rng)
        self.same &= bool(np.array_equal(u0, u))
        return state, u, info

    def set_scene(self, scene) -> None:
        """Both controllers see the same obstacles."""
        self.ctrl.set_scene(scene)
        self.rec.ctrl.set_scene(scene)

    def record_samples(self, k: int = 64, keep="spread") -> None:
        self.ctrl.record_samples(k, keep)
        self.rec.ctrl.record_samples(k, keep)


def _why(c, steps, i) -> str:
    s = steps[i]
    if c.test.startswith("T1") or c.test.startswith("T2"):
        return (f"slack {c.slack:.3g}; {s.n_crashed_real} real samples crashed (beta_max in "
                f"their state cost), T1 over samples that stayed safe holds: "
                f"{s.delta() + s.t1_gap_safe >= 0}")
    n = steps[i + 1]
    return (f"slack {c.slack:.3g}; F_real(t+1) = {n.F_real.value:.1f} vs alpha_t = {s.alpha:.1f}"
            f", alpha_t+1 = {n.alpha:.1f}, 2E = {2 * max(s.E, n.E):.1f}; R_t = {s.tube.R:.3g} "
            f"(nominal differs: {s.nominal_differs}); fallback at t+1: {n.fallback_used}")


if __name__ == "__main__":
    main()

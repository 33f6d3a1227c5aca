"""How hard the arena's disturbance is on each system: the reference controller's crash rate
on the training maps, the level scale that puts it in a stated band, and a label for settings
that cannot tell controllers apart.

A system's disturbance is ``DisturbanceSpec(model, level)`` with ``level`` in the double
integrator's units, scaled by ``System.level_scale`` on ``System.disturbed``
(:mod:`workbench.scenarios.systems`). Calibrated here: under ``velocity_variance`` at the
levels 50 and 100 (the quick profile's), the hand-tuned BaS-MPPI (the arena's hand settings)
should crash in :data:`BAND` of the training maps (the tuning seed range, never the test
maps), and reach the goal undisturbed on at least :data:`MIN_GOAL_RATE` of them.

Random streams: every episode draws from ``numpy`` Generators seeded with
``SeedSequence(SEED, (system, map seed, realisation))``: not the level, the level scale or the
disturbed states, so every probe of a calibration meets the same draws (common random numbers:
the crash rate changes with the level scale only through the disturbance's size).

Rerun (one process; prints what it measured)::

    python -m studies.arena.difficulty --system unicycle                  # the system's values
    python -m studies.arena.difficulty --system unicycle --states theta --calibrate 0.01 1
    python -m studies.arena.difficulty --system examples/user_models.py:point_mass_system

A system of your own (an entry, as in the arena's ``systems``) runs on its own scene: the map
seeds then only select the random streams.

The chosen values and their figures are recorded beside each system's definition
(:mod:`workbench.scenarios.systems`) and in assumptions §2.6.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from studies.arena import STUDY
from studies.arena.config import ArenaConfig, DisturbanceSpec
from studies.arena.episodes import Controls, Where, arena_system, capacity, run_episode
from studies.arena.tasks import hand_settings, system_key
from workbench.scenarios.systems import SYSTEMS
from workbench.sim import Disturbance
from workbench.study import Rate, fmt_rate, seed_sequence
from workbench.study.runner import profile_config
from workbench.validation import fail, integer, real

BAND = (0.2, 0.6)  # the reference controller's crash rate at each calibrated level
TARGET = 0.4  # the bisection's aim: the band's centre, pooled over the levels
TOLERANCE = 0.1  # a probe within this of TARGET ends the bisection
LEVELS = (50.0, 100.0)  # DI-unit levels of the quick profile's disturbances
MODEL = "velocity_variance"
MIN_GOAL_RATE = 0.9  # undisturbed, the reference reaches the goal on at least this share
REFERENCE = "bas_mppi"
SEED = 20260  # the calibration's own streams (not the arena's seed)


@dataclass(frozen=True)
class Measured:
    """The reference controller on one system with given disturbed states and level scale:
    crash rate per level and the undisturbed goal rate (None: not measured)."""

    system: str
    disturbed: tuple[str, ...]
    level_scale: float
    crashes: Mapping[float, Rate]
    goal: Rate | None

    @property
    def pooled(self) -> Rate:
        """The crash rate over every level's episodes."""
        return Rate(sum(r.k for r in self.crashes.values()),
                    sum(r.n for r in self.crashes.values()))

    def lines(self) -> list[str]:
        out = [f"{self.system}: disturbed {self.disturbed}, level_scale {self.level_scale:.4g}"]
        out += [f"  crash at level {lv:g}: {fmt_rate(r)} ({r.k}/{r.n})"
                for lv, r in self.crashes.items()]
        if self.goal is not None:
            out.append(f"  undisturbed goal: {fmt_rate(self.goal)} ({self.goal.k}/{self.goal.n})")
        return out


def streams(system_name: str, map_seed: int,
            realisation: int) -> tuple[np.random.Generator, np.random.Generator]:
    """The (controller, plant) Generators of one calibration episode."""
    ss = seed_sequence(SEED, (system_key(system_name), map_seed, realisation))
    rc, rp = (np.random.default_rng(s) for s in ss.spawn(2))
    return rc, rp


@dataclass(frozen=True)
class Bench:
    """The reference controller of ``config`` (hand settings) on ``system_name`` over the maps
    ``seeds`` of the config's first map family, ``realisations`` episodes each (realisations
    ``first`` .. ``first + realisations - 1``)."""

    config: ArenaConfig
    system_name: str
    seeds: tuple[int, ...]
    realisations: int = 1
    first: int = 0
    controller: str = REFERENCE

    def __post_init__(self) -> None:
        try:
            arena_system(self.system_name)
        except ValueError as exc:
            raise fail("system", self.system_name, str(exc).split(" is invalid: ", 1)[-1]
                       if ":" in self.system_name else "unknown system; allowed values are "
                       f"{tuple(SYSTEMS)} or an entry 'path/file.py:function'") from None
        if not self.seeds:
            raise fail("seeds", self.seeds, "must name at least one map seed")
        integer("realisations", self.realisations, 1)
        integer("first", self.first, 0)

    def _where(self, seed: int) -> Where:
        fam = self.config.families[0]  # circle slots for these maps (padding: same results)
        if arena_system(self.system_name).scene is not None:  # its own scene: no slots
            return Where(self.system_name, fam, seed, None)
        return Where(self.system_name, fam, seed, capacity(fam, tuple(self.seeds)))

    def _controls(self) -> Controls:
        c = self.config
        return Controls(self.controller, hand_settings(c, self.system_name), c.robust,
                        c.feedback, c.calibration_seed)

    def episodes(self, disturbance: Disturbance):
        """One outcome per (map, realisation)."""
        c = self.config
        for seed in self.seeds:
            for j in range(self.first, self.first + self.realisations):
                rc, rp = streams(self.system_name, seed, j)
                yield run_episode(self._where(seed), self._controls(), disturbance, c.steps,
                                  c.goal_radius, rc, rp)

    def crash_rate(self, level: float, level_scale: float,
                   disturbed: tuple[str, ...]) -> Rate:
        dist = DisturbanceSpec(MODEL, level).disturbance(level_scale, disturbed)
        return Rate.of([o.crashed for o in self.episodes(dist)])

    def goal_rate(self) -> Rate:
        """Undisturbed: the share of episodes that reach the goal without a crash."""
        return Rate.of([o.success for o in self.episodes(Disturbance(0.0))])

    def measure(self, level_scale: float, disturbed: tuple[str, ...],
                levels: Sequence[float] = LEVELS, goal: bool = True) -> Measured:
        crashes = {float(lv): self.crash_rate(lv, level_scale, disturbed) for lv in levels}
        return Measured(self.system_name, tuple(disturbed), float(level_scale), crashes,
                        self.goal_rate() if goal else None)


@dataclass(frozen=True)
class Probe:
    level_scale: float
    rate: float


@dataclass(frozen=True)
class Bisection:
    """The probes in the order evaluated and the chosen one. ``in_band``: the chosen probe's
    rate lies in the band."""

    probes: tuple[Probe, ...]
    chosen: Probe
    in_band: bool


def bisect_scale(rate_of: Callable[[float], float], low: float, high: float, *,
                 target: float = TARGET, band: tuple[float, float] = BAND,
                 tolerance: float = TOLERANCE, evaluations: int = 6) -> Bisection:
    """A level scale in [``low``, ``high``] whose rate ``rate_of(scale)`` (assumed
    non-decreasing in the scale) is within ``tolerance`` of ``target``: bisection on the log
    scale, probing the bracket's geometric midpoint (never its ends) at most ``evaluations``
    times; below the target the bracket moves up, otherwise down. The chosen probe is the
    first within tolerance, else the probe closest to the target (the earliest of equals)."""
    low = real("low", low, 0.0, strict=True)
    high = real("high", high, 0.0, strict=True)
    if not low < high:
        raise fail("high", high, f"must be above low = {low}")
    lo_b, hi_b = (real(f"band[{i}]", b, 0.0, maximum=1.0) for i, b in enumerate(band))
    if not lo_b <= target <= hi_b:
        raise fail("target", target, f"must lie in the band [{lo_b}, {hi_b}]")
    real("tolerance", tolerance, 0.0)
    integer("evaluations", evaluations, 1)
    probes: list[Probe] = []
    for _ in range(evaluations):
        mid = math.sqrt(low * high)
        p = Probe(mid, float(rate_of(mid)))
        probes.append(p)
        if abs(p.rate - target) <= tolerance:
            break
        if p.rate < target:
            low = mid
        else:
            high = mid
    chosen = min(probes, key=lambda q: abs(q.rate - target))  # min keeps the earliest of equals
    return Bisection(tuple(probes), chosen, lo_b <= chosen.rate <= hi_b)


def calibrate(bench: Bench, disturbed: tuple[str, ...], low: float, high: float,
              levels: Sequence[float] = LEVELS, evaluations: int = 6,
              report: Callable[[str], None] = print) -> Bisection:
    """:func:`bisect_scale` on the bench's crash rate pooled over ``levels``."""
    def rate_of(scale: float) -> float:
        m = bench.measure(scale, disturbed, levels, goal=False)
        for line in m.lines():
            report(line)
        return m.pooled.value

    return bisect_scale(rate_of, low, high, evaluations=evaluations)


def uninformative(rates: Mapping[str, float], n: int) -> str | None:
    """Why a setting cannot discriminate between controllers, or None.

    ``rates``: each controller's rate (a share in [0, 1], e.g. safety) over ``n`` episodes.
    A reason when every rate is 0 %, when every rate is 100 %, or (two controllers or more)
    when every rate is within one episode of every other (``max - min <= 1 / n``: a
    difference a single episode makes)."""
    n = integer("n", n, 1)
    if not rates:
        raise fail("rates", rates, "must give at least one controller's rate")
    for name, r in rates.items():
        real(f"rates[{name!r}]", r, 0.0, maximum=1.0)
    values = [float(r) for r in rates.values()]
    each = "every controller's" if len(values) > 1 else "the only controller's"
    if all(v == 0.0 for v in values):
        return f"{each} rate is 0 % (of {n} episodes)"
    if all(v == 1.0 for v in values):
        return f"{each} rate is 100 % (of {n} episodes)"
    counts = [round(v * n) for v in values]
    if len(values) > 1 and max(counts) - min(counts) <= 1:
        return (f"every controller's rate is within one episode of the others' "
                f"({100 * min(values):.0f}-{100 * max(values):.0f} % of {n} episodes)")
    return None


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m studies.arena.difficulty",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--system", required=True,
                    help=f"one of {', '.join(SYSTEMS)}, or an entry 'path/file.py:function'")
    ap.add_argument("--states", nargs="+", help="disturbed states (default: the system's)")
    ap.add_argument("--scale", type=float, help="level scale (default: the system's)")
    ap.add_argument("--calibrate", nargs=2, type=float, metavar=("LOW", "HIGH"),
                    help="bisect the level scale in [LOW, HIGH] (realisation 0), then measure")
    ap.add_argument("--evaluations", type=int, default=6)
    ap.add_argument("--profile", default="quick", help="the arena profile of the hand settings")
    ap.add_argument("--maps", type=int, default=12,
                    help="training maps from the profile's tuning seed on")
    ap.add_argument("--realisations", type=int, default=2,
                    help="episodes per map of the measurement")
    ap.add_argument("--first", type=int, default=1,
                    help="the measurement's first realisation (0 is the calibration's)")
    ap.add_argument("--no-goal", action="store_true", help="skip the undisturbed goal rate")
    args = ap.parse_args(argv)
    config = profile_config(STUDY, args.profile)
    seeds = tuple(range(config.tuning_seed, config.tuning_seed + args.maps))
    overlap = set(seeds) & set(config.map_seeds())
    if overlap:
        raise SystemExit(f"the training maps {seeds} overlap the test maps "
                         f"{config.map_seeds()}")
    try:
        sysm = arena_system(args.system)
    except ValueError as exc:
        ap.error(str(exc))
    states = tuple(args.states) if args.states else sysm.disturbed
    scale = sysm.level_scale if args.scale is None else args.scale
    fam = config.families[0].family
    print(f"{REFERENCE} (hand settings, profile {args.profile}) on {args.system}, {MODEL} at "
          f"levels {LEVELS}, maps {fam} {seeds[0]}..{seeds[-1]}")
    if args.calibrate:
        print("calibration (realisation 0):")
        b = calibrate(Bench(config, args.system, seeds), states, *args.calibrate,
                      evaluations=args.evaluations)
        scale = b.chosen.level_scale
        print(f"chosen level_scale {scale:.4g} (pooled crash {100 * b.chosen.rate:.0f} %, "
              f"{'in' if b.in_band else 'NOT in'} the band {BAND})")
    first = args.first
    print(f"measurement (realisations {first}..{first + args.realisations - 1}):")
    m = Bench(config, args.system, seeds, args.realisations, first).measure(
        scale, states, goal=not args.no_goal)
    for line in m.lines():
        print(line)
    ok = all(BAND[0] <= r.value <= BAND[1] for r in m.crashes.values())
    verdict = f"crash rates {'in' if ok else 'NOT in'} the band {BAND}"
    if m.goal is not None:
        verdict += f"; undisturbed goal {'>=' if m.goal.value >= MIN_GOAL_RATE else '<'} "
        verdict += f"{MIN_GOAL_RATE:.0%}"
    print(verdict)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

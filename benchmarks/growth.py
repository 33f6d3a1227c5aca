"""Growth curves: time per control step against the number of samples N, the horizon T and the
number of circles, on one thread (robust to other load), with linear fits.

Per point, timed in turn (medians of ``repeats``): the SAIS batch (``Sampler.sais`` with its
noise, the two importance weightings and the two weighted control sums: the bulk of an SA-RMPPI
step), the BaS-MPPI control step (``MPPI.step``), the hand-written C floor of the SAIS rollout
(noise given, :mod:`benchmarks.floor`) and, along N and T, the SA-RMPPI control step (closed
loop, a fixed selection threshold so no calibration episode runs; K_safe, selection and SAIS
included). Along N and T the map is the paper's 30-circle map; along the circle count it is a
generated map of that many circles (the kernels are compiled for that many scene slots; compile
or load time is recorded per count).

Along the circle count, the SAIS batch and the BaS-MPPI step are also timed with the slot-loop
kernels (:mod:`workbench.sampling.kernels.slots`: the circle slots in a loop instead of unrolled
into the step, bitwise-equal results), in turn with the straight-line ones, with their compile
times and library sizes; the report gives both curves, their slopes per circle and the ratio.

``python -m benchmarks --growth`` runs only these curves; ``growth(cfg, out_dir)`` writes
``growth.json`` and ``growth.png`` into ``out_dir``.
"""

from __future__ import annotations

import json
import logging
import statistics
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from benchmarks.floor import FloorProblem, load_floor
from benchmarks.split import machine
from benchmarks.timing import pinned_threads, round_robin
from workbench.codegen import build_counts
from workbench.sampling.kernels import slots
from workbench.sampling.kernels.constants import SamplerConstants
from workbench.sampling.kernels.library import load_sampler_library
from workbench.sampling.mppi import MPPI, MPPIConfig
from workbench.sampling.sampler import Sampler, check_batch
from workbench.sampling.threshold import AlphaRule
from workbench.sampling.weights import importance_weights, weighted_controls
from workbench.scenarios.navigation import navigation_setup
from workbench.scenarios.scenes import CircleScene
from workbench.sim import closed_loop
from workbench.study.io import atomic_write_json
from workbench.validation import fail, integer

log = logging.getLogger("benchmarks.growth")

SERIES = ("sais_batch", "bas_mppi_step", "floor_sais", "sa_rmppi_step", "sais_batch_loop",
          "bas_mppi_step_loop")
LABELS = {"sais_batch": "SAIS batch (noise + rollout + weights + update)",
          "bas_mppi_step": "BaS-MPPI control step",
          "floor_sais": "C floor: SAIS rollout, noise given",
          "sa_rmppi_step": "SA-RMPPI control step",
          "sais_batch_loop": "SAIS batch, slot-loop kernels",
          "bas_mppi_step_loop": "BaS-MPPI control step, slot-loop kernels"}
LOOP_PAIRS = (("sais_batch", "sais_batch_loop"), ("bas_mppi_step", "bas_mppi_step_loop"))


def _ints(name: str, values, minimum: int, maximum: int) -> tuple[int, ...]:
    vals = tuple(values)
    if not vals:
        raise fail(name, values, "must list at least one value")
    for v in vals:
        integer(name, v, minimum, maximum)
    if list(vals) != sorted(set(vals)):
        raise fail(name, values, "must be strictly increasing")
    return tuple(int(v) for v in vals)


@dataclass(frozen=True)
class GrowthConfig:
    """The three axes and the fixed values of the other two; ``step_steps`` SA-RMPPI steps per
    point along N and T (0: no SA-RMPPI curve); ``threads`` OpenMP threads for every kernel."""

    samples: tuple[int, ...] = (256, 512, 1024, 2048, 4096, 8192, 16384)
    horizons: tuple[int, ...] = (25, 50, 100, 200)
    circles: tuple[int, ...] = (1, 3, 10, 30, 100, 300, 1000)
    base_samples: int = 1024
    base_horizon: int = 100
    base_circles: int = 30
    repeats: int = 5
    step_steps: int = 20
    threads: int = 1
    seed: int = 0
    fit_from_circles: int = 10  # the per-circle slope fits counts >= this (all if fewer than 2)
    loop_kernels: bool = True  # also time the slot-loop kernels along the circle count

    def __post_init__(self) -> None:
        object.__setattr__(self, "samples", _ints("GrowthConfig.samples", self.samples, 4,
                                                  2**20))
        object.__setattr__(self, "horizons", _ints("GrowthConfig.horizons", self.horizons, 1,
                                                   10_000))
        object.__setattr__(self, "circles", _ints("GrowthConfig.circles", self.circles, 1,
                                                  10_000))
        integer("GrowthConfig.base_samples", self.base_samples, 4, 2**20)
        integer("GrowthConfig.base_horizon", self.base_horizon, 1, 10_000)
        integer("GrowthConfig.base_circles", self.base_circles, 2, 10_000)
        integer("GrowthConfig.repeats", self.repeats, 1, 1000)
        integer("GrowthConfig.step_steps", self.step_steps, 0, 10_000)
        integer("GrowthConfig.threads", self.threads, 1, 1024)
        integer("GrowthConfig.seed", self.seed, 0)
        integer("GrowthConfig.fit_from_circles", self.fit_from_circles, 1)
        if not isinstance(self.loop_kernels, bool):
            raise fail("GrowthConfig.loop_kernels", self.loop_kernels, "must be True or False")


def circle_map(n: int, seed: int = 0) -> CircleScene:
    """n circles with centres uniform in [1, 9]^2, clear of the start (0.5, 0.5) and goal
    (9.5, 9.5); radius 0.6 sqrt(30 / n) (at most 0.9), so the covered area stays about that of
    the paper's 30-circle map."""
    integer("circles", n, 1)
    rng = np.random.default_rng(seed + 7919 * n)
    r = min(0.9, 0.6 * float(np.sqrt(30.0 / n)))
    ends = np.array([[0.5, 0.5], [9.5, 9.5]])
    out = []
    while len(out) < n:
        c = rng.uniform(1.0, 9.0, 2)
        if np.min(np.linalg.norm(ends - c, axis=1)) > r + 0.3:
            out.append((float(c[0]), float(c[1]), r))
    return CircleScene(tuple(out))


@dataclass
class _Point:
    """One set-up (map, N, T): the timed calls."""

    fns: dict = field(default_factory=dict)
    step: object = None


def _plan(sp, T: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.normal(0, 1.0, (T, sp.nu)), rng.normal(0, 1.0, (T, sp.nu, sp.nx))


def _point(nav, N: int, T: int, cfg: GrowthConfig, floor, with_step: bool,
           loop_lib=None, straight_lib=None) -> _Point:
    """The timed calls of one set-up; ``loop_lib`` (a slot-loop kernel library of the same
    problem) adds the SAIS batch and the BaS-MPPI step on it; ``straight_lib`` (the
    straight-line library) replaces the library's default choice in the main series."""
    sp = nav.problem
    sampler = Sampler(sp, "compiled")
    if straight_lib is not None:
        sampler.lib = straight_lib
    U, K = _plan(sp, T, cfg.seed)
    c = SamplerConstants(sigma=np.array(nav.mppi.sigma), lam=nav.mppi.lam, nu_mix=0.0,
                         u_min=sp.model.u_min, u_max=sp.model.u_max, crash_cost=1e6,
                         p=sp.model.lift(nav.goal), alpha=2e4)
    _, c = check_batch(sp, N, U, c)
    x0 = sp.model.lift(nav.x0)

    def sais_on(smp):
        def sais(i):
            b = smp.sais(x0, x0, U, K, N, c, i)
            wn, wr = importance_weights(b.S_nom, c.lam), importance_weights(b.S_real, c.lam)
            return weighted_controls(b.v_nom, wn.w), weighted_controls(b.v_real, wr.w)
        return sais

    sais = sais_on(sampler)
    mcfg = MPPIConfig(n_samples=N, horizon=T, sigma=nav.mppi.sigma, lam=nav.mppi.lam)
    mppi = MPPI(sp, nav.goal, mcfg)
    if straight_lib is not None:
        mppi.sampler.lib = straight_lib
    state = mppi.initial_state()
    rng = np.random.default_rng(cfg.seed)
    fcall, _ = floor.prepare_sais(FloorProblem.of(sp, c), x0, x0, U, K,
                                  sampler.lib.normals(N, T, sp.nu, 1))
    pt = _Point(fns={"sais_batch": sais,
                     "bas_mppi_step": lambda i: mppi.step(state, nav.x0, rng),
                     "floor_sais": lambda i: fcall()})
    if loop_lib is not None:
        loop_sampler = Sampler(sp, "compiled")
        loop_sampler.lib = loop_lib  # the same kernels' interface; the slot-loop code
        loop_mppi = MPPI(sp, nav.goal, mcfg)
        loop_mppi.sampler.lib = loop_lib
        loop_state = loop_mppi.initial_state()
        rng_loop = np.random.default_rng(cfg.seed)
        pt.fns["sais_batch_loop"] = sais_on(loop_sampler)
        pt.fns["bas_mppi_step_loop"] = lambda i: loop_mppi.step(loop_state, nav.x0, rng_loop)
    if with_step and cfg.step_steps:
        pt.step = (nav, mcfg)
    return pt


def _step_time(nav, mcfg: MPPIConfig, cfg: GrowthConfig) -> float:
    """Median SA-RMPPI step (ms) over a short closed-loop run from the start."""
    setup = navigation_setup(nav.scene, mppi=mcfg)
    ctrl = setup.controller("sa_rmppi", rule=AlphaRule(kind="fixed", value=2e4))
    closed_loop(ctrl, setup.plant, setup.x0, 2, np.random.default_rng(0),
                np.random.default_rng(1))  # warm
    ep = closed_loop(ctrl, setup.plant, setup.x0, cfg.step_steps, np.random.default_rng(2),
                     np.random.default_rng(3))
    return 1e3 * statistics.median(ep.step_time_s)


def _measure(pt: _Point, cfg: GrowthConfig) -> tuple[dict[str, float], dict[str, float]]:
    """(medians, minima) in ms; the SA-RMPPI step's median is also its 'minimum' entry."""
    med, low = round_robin(pt.fns, cfg.repeats, block=1, warm=2, with_min=True)
    out, out_min = {k: 1e3 * v for k, v in med.items()}, {k: 1e3 * v for k, v in low.items()}
    if pt.step is not None:
        out["sa_rmppi_step"] = out_min["sa_rmppi_step"] = _step_time(*pt.step, cfg)
    return out, out_min


def linear_fit(x, y) -> dict:
    """Least-squares line y = slope x + intercept, its R^2, and the log-log exponent of the
    upper half of the points (1 = linear growth)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    if x.size < 2:
        return {"slope": None, "intercept": None, "r2": None, "loglog_exponent": None}
    slope, icpt = np.polyfit(x, y, 1)
    pred = slope * x + icpt
    ss = float(np.sum((y - y.mean()) ** 2))
    r2 = 1.0 - float(np.sum((y - pred) ** 2)) / ss if ss > 0 else None
    h = max(2, x.size // 2)
    expo = float(np.polyfit(np.log(x[-h:]), np.log(np.maximum(y[-h:], 1e-12)), 1)[0])
    return {"slope": float(slope), "intercept": float(icpt), "r2": r2, "loglog_exponent": expo}


def _fits(x, series: dict, start: int | None = None) -> dict:
    """Per series: the least-squares line over x >= start and the marginal slopes between
    consecutive points (``marginal``: [x_a, x_b, slope])."""
    x = np.asarray(x, float)
    keep = x >= start if start is not None and np.sum(x >= start) >= 2 else np.ones_like(x, bool)
    out = {}
    for k, v in series.items():
        if len(v) != len(x):
            continue
        y = np.asarray(v, float)
        marginal = [[int(x[i]), int(x[i + 1]), float((y[i + 1] - y[i]) / (x[i + 1] - x[i]))]
                    for i in range(len(x) - 1)]
        out[k] = {**linear_fit(x[keep], y[keep]), "fitted_points": [int(a) for a in x[keep]],
                  "marginal": marginal}
    return out


def _previous_compile(out_dir: Path) -> dict:
    try:
        old = json.loads((out_dir / "growth.json").read_text())
        return {int(k): v for k, v in old.get("compile", {}).items()}
    except (OSError, ValueError, AttributeError):
        return {}


def growth(cfg: GrowthConfig, out_dir: Path) -> dict:
    """Measure the three curves, write ``growth.json`` and ``growth.png`` into ``out_dir``,
    return the JSON content."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    floor = load_floor()
    base = navigation_setup()
    with pinned_threads(cfg.threads, floor.set_threads):
        data = _growth(cfg, out_dir, floor, base)
    atomic_write_json(out_dir / "growth.json", data)
    plot(data, out_dir / "growth.png")
    return data


def _growth(cfg: GrowthConfig, out_dir: Path, floor, base) -> dict:
    axes: dict[str, dict] = {}

    def run(axis: str, xs, make) -> None:
        series: dict[str, list] = {}
        minima: dict[str, list] = {}
        for x in xs:
            t0 = time.perf_counter()
            pt = make(x)
            med, low = _measure(pt, cfg)
            for k, v in med.items():
                series.setdefault(k, []).append(v)
                minima.setdefault(k, []).append(low[k])
            log.info("growth %s = %d: %s (%.1f s)", axis, x,
                     ", ".join(f"{k} {v[-1]:.3g} ms" for k, v in series.items()),
                     time.perf_counter() - t0)
        axes[axis] = {"x": list(xs), "series": series, "series_min": minima}

    def setup_for(mcfg: MPPIConfig):
        return navigation_setup(base.scene, mppi=mcfg)

    run("samples", cfg.samples, lambda n: _point(
        base, n, cfg.base_horizon, cfg, floor, True))
    run("horizon", cfg.horizons, lambda t: _point(
        setup_for(MPPIConfig(horizon=t, sigma=base.mppi.sigma, lam=base.mppi.lam)),
        cfg.base_samples, t, cfg, floor, True))
    previous = _previous_compile(out_dir)
    compile_facts: dict[int, dict] = {}

    def timed_build(make, old: dict) -> tuple[object, dict]:
        """(library, facts): compile or load time, cache hit, file size and folder."""
        before = build_counts()["compiled"]
        t0 = time.perf_counter()
        lib = make()
        dt = time.perf_counter() - t0
        compiled = build_counts()["compiled"] > before
        lib_path = Path(lib.cdll._name)
        facts = {"cache_hit": not compiled, "library_bytes": lib_path.stat().st_size,
                 "library": lib_path.parent.name}
        if compiled:
            facts["compile_s"] = dt
        else:
            facts["load_s"] = dt
            if old.get("library") == facts["library"] and "compile_s" in old:
                facts["compile_s"] = old["compile_s"]  # measured when it was built
        return lib, facts

    def circles_point(n: int) -> _Point:
        nav = navigation_setup(circle_map(n, cfg.seed))
        old = previous.get(n, {})
        straight_lib, facts = timed_build(
            lambda: load_sampler_library(nav.problem, slot_loop=False), old)
        loop_lib = None
        if cfg.loop_kernels and slots.unsupported_reason(nav.problem) is None:
            loop_lib, facts["loop"] = timed_build(
                lambda: load_sampler_library(nav.problem, slot_loop=True), old.get("loop", {}))
        compile_facts[n] = facts
        return _point(nav, cfg.base_samples, cfg.base_horizon, cfg, floor, False, loop_lib,
                      straight_lib)

    run("circles", cfg.circles, circles_point)
    fits = {"samples": _fits(cfg.samples, axes["samples"]["series"]),
            "horizon": _fits(cfg.horizons, axes["horizon"]["series"]),
            "circles": _fits(cfg.circles, axes["circles"]["series"], cfg.fit_from_circles)}
    for axis in fits:
        axes[axis]["fits"] = fits[axis]
    axes["circles"]["fits_min"] = _fits(cfg.circles, axes["circles"]["series_min"],
                                        cfg.fit_from_circles)
    axes["samples"]["fits_min"] = _fits(cfg.samples, axes["samples"]["series_min"])
    summary = summarise(axes, cfg)
    data = {"config": asdict(cfg), "threads": cfg.threads, "machine": machine(),
            "measured": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
            "units": {"time": "ms per call (median)", "samples": "samples N",
                      "horizon": "time steps T", "circles": "circles (scene slots)"},
            "axes": axes, "compile": {str(k): v for k, v in compile_facts.items()},
            "summary": summary, "labels": LABELS}
    data["loop_vs_straight"] = loop_comparison(data)
    return data


def summarise(axes: dict, cfg: GrowthConfig) -> dict:
    """The headline slopes: ms per circle, microseconds per sample, ms per time step."""
    out = {}
    for k in SERIES:
        c = axes.get("circles", {}).get("fits", {}).get(k)
        n = axes.get("samples", {}).get("fits", {}).get(k)
        t = axes.get("horizon", {}).get("fits", {}).get(k)
        out[k] = {
            "ms_per_circle": None if not c or c["slope"] is None else c["slope"],
            "circles_loglog_exponent": None if not c else c["loglog_exponent"],
            "us_per_sample": None if not n or n["slope"] is None else 1e3 * n["slope"],
            "samples_loglog_exponent": None if not n else n["loglog_exponent"],
            "ms_per_time_step": None if not t or t["slope"] is None else t["slope"],
        }
        cm = axes.get("circles", {}).get("fits_min", {}).get(k)
        nm = axes.get("samples", {}).get("fits_min", {}).get(k)
        out[k]["ms_per_circle_minima"] = None if not cm else cm["slope"]
        out[k]["us_per_sample_minima"] = None if not nm or nm["slope"] is None \
            else 1e3 * nm["slope"]
    return out


def plot(data: dict, path: Path) -> None:
    """Three panels (N, T, circles), log axes, fitted slopes in the legends."""
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    titles = {"samples": ("samples N", f"T = {data['config']['base_horizon']}, 30 circles"),
              "horizon": ("horizon T [steps]", f"N = {data['config']['base_samples']}, "
                          "30 circles"),
              "circles": ("circles (scene slots)", f"N = {data['config']['base_samples']}, "
                          f"T = {data['config']['base_horizon']}")}
    fig, axs = plt.subplots(1, 3, figsize=(15, 4.6))
    for ax, (axis, (xlabel, sub)) in zip(axs, titles.items(), strict=True):
        a = data["axes"].get(axis)
        if not a:
            continue
        x = np.asarray(a["x"], float)
        for k in SERIES:
            y = a["series"].get(k)
            if not y:
                continue
            f = a["fits"].get(k, {})
            unit = {"samples": ("us/sample", 1e3), "horizon": ("ms/step", 1.0),
                    "circles": ("ms/circle", 1.0)}[axis]
            slope = f.get("slope")
            lab = LABELS[k] + ("" if slope is None else f" ({unit[1] * slope:.3g} {unit[0]})")
            ax.plot(x, y, "o-", label=lab)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xticks(x, [str(int(v)) for v in x])
        ax.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
        ax.set_xlabel(xlabel)
        ax.set_ylabel("time per call [ms]")
        ax.set_title(f"vs {xlabel.split(' [')[0]} ({sub})", fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(f"Growth curves, {data['threads']} thread(s), float64; medians", fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def markdown(data: dict) -> str:
    """The growth section of ``report.md``."""
    s = data["summary"]
    cfg = data["config"]
    lines = ["## Growth curves", "",
             "![growth curves](growth.png)", "",
             f"Measured {data.get('measured', '?')} (`python -m benchmarks --growth`). "
             f"One thread, float64, medians of {cfg['repeats']} (SA-RMPPI: of "
             f"{cfg['step_steps']} closed-loop steps). Fixed values: N = {cfg['base_samples']}, "
             f"T = {cfg['base_horizon']}, the paper's 30-circle map (circle axis: generated maps "
             "of that many circles). Slopes are least-squares lines (circle slope over counts "
             f">= {cfg['fit_from_circles']}); the log-log exponent of the upper half of the points "
             "is 1 for linear growth.", "",
             "Columns marked (min) fit the fastest of the repeats instead of the median: "
             "a check that load on the machine did not make the slopes.", "",
             "| series | ms per circle | (min) | exponent (circles) | us per sample | (min) | "
             "exponent (N) | ms per time step |", "|---|---:|---:|---:|---:|---:|---:|---:|"]

    def f(v, spec=".3g"):
        return "—" if v is None else format(v, spec)

    for k in SERIES:
        r = s.get(k, {})
        if all(v is None for v in r.values()):
            continue
        lines.append(f"| {LABELS[k]} | {f(r['ms_per_circle'], '.4f')} | "
                     f"{f(r.get('ms_per_circle_minima'), '.4f')} | "
                     f"{f(r['circles_loglog_exponent'], '.2f')} | {f(r['us_per_sample'])} | "
                     f"{f(r.get('us_per_sample_minima'))} | "
                     f"{f(r['samples_loglog_exponent'], '.2f')} | "
                     f"{f(r['ms_per_time_step'], '.4f')} |")
    marg = data["axes"].get("circles", {}).get("fits", {})
    if marg:
        lines += ["", "Marginal cost per circle between consecutive counts (ms per circle; "
                  "constant for linear growth):", "",
                  "| series | " + " | ".join(f"{a}-{b}" for a, b, _ in
                                           next(iter(marg.values()))["marginal"]) + " |",
                  "|---|" + "---:|" * len(next(iter(marg.values()))["marginal"])]
        for k in SERIES:
            if k in marg:
                lines.append(f"| {LABELS[k]} | " + " | ".join(
                    f"{m:.3g}" for _, _, m in marg[k]["marginal"]) + " |")
    comp = data.get("compile", {})
    if comp:
        loops = any("loop" in v for v in comp.values())
        lines += ["", "Kernel library per circle count (compiled for that many scene slots; "
                  "compile time when this or an earlier growth run built it, load time when it "
                  "came from the code cache)" + ("; straight-line and slot-loop kernels" if loops
                                                 else "") + ":", ""]
        if loops:
            lines += ["| circles | compile [s] | load [s] | library [kB] | loop: compile [s] | "
                      "load [s] | library [kB] |", "|---:|---:|---:|---:|---:|---:|---:|"]
        else:
            lines += ["| circles | compile [s] | load [s] | library [kB] |",
                      "|---:|---:|---:|---:|"]
        for n, v in comp.items():
            row = (f"| {n} | {f(v.get('compile_s'), '.1f')} | {f(v.get('load_s'), '.2f')} "
                   f"| {v['library_bytes'] / 1024:.0f} |")
            if loops:
                lp = v.get("loop", {})
                size = lp.get("library_bytes")
                row += (f" {f(lp.get('compile_s'), '.1f')} | {f(lp.get('load_s'), '.2f')} | "
                        f"{f(None if size is None else size / 1024, '.0f')} |")
            lines.append(row)
    lines += loop_markdown(data)
    return "\n".join(lines) + "\n"


def loop_comparison(data: dict) -> list[dict]:
    """Per circle count: straight-line and slot-loop times (ms) and their ratio (loop /
    straight-line) for the SAIS batch and the BaS-MPPI step."""
    a = data["axes"].get("circles", {})
    ser = a.get("series", {})
    out = []
    for i, n in enumerate(a.get("x", [])):
        row = {"circles": int(n)}
        for base, loop in LOOP_PAIRS:
            if len(ser.get(loop, [])) > i and len(ser.get(base, [])) > i:
                row[base], row[loop] = ser[base][i], ser[loop][i]
                row[f"{loop}_ratio"] = ser[loop][i] / ser[base][i]
        out.append(row)
    return out


def loop_markdown(data: dict) -> list[str]:
    """The slot-loop section of the report: both curves side by side and their slopes."""
    rows = [r for r in loop_comparison(data) if "sais_batch_loop" in r]
    if not rows:
        return []
    s = data["summary"]
    cfg = data["config"]

    def f(v, spec=".3g"):
        return "—" if v is None else format(v, spec)

    lines = ["", "### Slot-loop kernels", "",
             "The slot-loop kernels (`workbench/sampling/kernels/slots.py`) evaluate the circle "
             "slots in a loop (code size independent of the number of circles) with results "
             "bitwise equal to the straight-line kernels'. Timed in turn with them, one thread:",
             "", "| circles | SAIS batch [ms] | loop [ms] | loop / straight | BaS-MPPI step [ms] | "
             "loop [ms] | loop / straight |", "|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['circles']} | {f(r.get('sais_batch'))} | "
                     f"{f(r.get('sais_batch_loop'))} | {f(r.get('sais_batch_loop_ratio'), '.2f')} "
                     f"| {f(r.get('bas_mppi_step'))} | {f(r.get('bas_mppi_step_loop'))} | "
                     f"{f(r.get('bas_mppi_step_loop_ratio'), '.2f')} |")
    lines += ["", f"Slope per circle (least squares over counts >= {cfg['fit_from_circles']}; "
              "(min): fitted to the fastest repeat):", ""]
    for base, loop in LOOP_PAIRS:
        b, lp = s.get(base, {}), s.get(loop, {})
        lines.append(f"- {LABELS[base]}: straight-line {f(b.get('ms_per_circle'), '.4f')} ms "
                     f"per circle ((min) {f(b.get('ms_per_circle_minima'), '.4f')}, log-log "
                     f"exponent {f(b.get('circles_loglog_exponent'), '.2f')}); slot loop "
                     f"{f(lp.get('ms_per_circle'), '.4f')} ms per circle ((min) "
                     f"{f(lp.get('ms_per_circle_minima'), '.4f')}, exponent "
                     f"{f(lp.get('circles_loglog_exponent'), '.2f')})")
    return lines

"""What the run-time scene kinds cost in the compiled SAIS kernel (one thread, float64).

Every figure is the bare SAIS kernel (its noise drawn inside, no Python wrapping: the C
function on prepared buffers) on N = 1024 samples and T = 100 steps of a double integrator with
a goal cost and no barrier state, so the difference between two models is their margins and
crash tests alone. A SAIS sample-step advances two systems (real and nominal), so it evaluates
every margin twice. The calls of one figure are timed in turn; figures on three bases: the
median thread CPU time (the records' values: the time the kernel ran, robust when other
processes share the cores), the median wall time and the fastest call.

* ``grid_vs_circle``: the cost per sample-step of one signed-distance grid margin (100 x 100
  nodes) and of one circle margin, each minus the same model without obstacles; their ratio.
* ``grid_sizes``: the SAIS kernel on 10 m x 10 m grids of 50^2 ... 400^2 nodes (the finer the
  grid, the larger the table the lookups read: 20 kB to 1.3 MB), with every sample starting
  at one place (their lookups stay in a band of the map) and with the samples' starts spread
  uniformly over the map (the lookups reach the whole table); and, at 200 x 200 nodes, on a
  map with a few large obstacles and one with many small ones (the same kernel: only the values
  change; the lookup reads four nodes whatever they hold).
* ``spheres_vs_circles``: a 3-D double integrator (``Model.from_expressions`` with
  ``SceneLayout(dim=3, slots=(("spheres", n),))``) against the planar one with n circles, n = 1
  and 33: the cost per obstacle per sample-step (the slope between the two counts) and the
  kernels' totals (the 3-D model also has more states and controls).

Circles are the models' default squared margins |p - c|^2 - r^2, spheres likewise in 3-D.
``records(repeats)`` is called by ``python -m benchmarks`` (``make bench``, the records in
``bench.json``); ``python -m benchmarks.scene_margins [--out FILE]`` runs only these and
writes their JSON.
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np

from benchmarks.split import machine
from benchmarks.timing import pinned_threads, prepared_kernel, record, samples_in_turn
from workbench.codegen import build_library
from workbench.problem.models import Model, double_integrator
from workbench.problem.obstacles import Circle
from workbench.problem.scene_kinds import Sphere
from workbench.problem.scene_layout import SceneLayout
from workbench.problem.sdf_grid import SignedDistanceGrid
from workbench.sampling.kernels.compiled import CompiledKernel
from workbench.sampling.kernels.constants import SamplerConstants
from workbench.sampling.kernels.flags import kernel_flags
from workbench.sampling.kernels.library import kernel_source
from workbench.sampling.kernels.specs import layouts, sais_spec
from workbench.sampling.kernels.verify import verify_kernel
from workbench.sampling.problem import SamplingProblem
from workbench.sampling.sampler import check_batch
from workbench.study.io import atomic_write_json
from workbench.validation import fail, integer

EXTENT = 10.0  # m, the grids' side
DT = 0.02
U_LIMIT = 6.0
FEW = ((3.0, 2.6, 0.8), (5.5, 6.0, 1.0), (7.5, 3.5, 0.7))  # the few-obstacle map (x, y, r)


@dataclass(frozen=True)
class SceneBenchConfig:
    """Sizes of the measurements; ``repeats`` timed calls per kernel."""

    samples: int = 1024
    horizon: int = 100
    repeats: int = 7
    grid_sizes: tuple[int, ...] = (50, 100, 200, 400)
    grid_vs_circle_size: int = 100
    occupancy_size: int = 200
    many_obstacles: int = 400
    obstacles: tuple[int, int] = (1, 33)
    seed: int = 0

    def __post_init__(self) -> None:
        integer("SceneBenchConfig.samples", self.samples, 4, 2**20)
        integer("SceneBenchConfig.horizon", self.horizon, 1, 10_000)
        integer("SceneBenchConfig.repeats", self.repeats, 1, 1000)
        for n in self.grid_sizes:
            integer("SceneBenchConfig.grid_sizes", n, 2, 2000)
        integer("SceneBenchConfig.grid_vs_circle_size", self.grid_vs_circle_size, 2, 2000)
        integer("SceneBenchConfig.occupancy_size", self.occupancy_size, 2, 2000)
        integer("SceneBenchConfig.many_obstacles", self.many_obstacles, len(FEW) + 1, 10_000)
        if len(self.obstacles) != 2 or not 1 <= self.obstacles[0] < self.obstacles[1]:
            raise fail("SceneBenchConfig.obstacles", self.obstacles,
                       "two increasing counts >= 1 (the per-obstacle slope's ends)")
        integer("SceneBenchConfig.seed", self.seed, 0)


def goal_problem(model: Model) -> SamplingProblem:
    """Squared distance to the goal position, per step and (x10) at the end."""
    g = ca.SX.sym("goal", model.nx)
    d = len(model.position or ())
    e = model.x[:d] - g[:d]
    return SamplingProblem.from_costs(model, q=ca.dot(e, e), phi=10.0 * ca.dot(e, e), p=g)


def double_integrator_3d(layout: SceneLayout, obstacles: list) -> Model:
    """x = [p (3), v (3)], u = a (3), explicit Euler with step DT, margins of ``layout``."""
    x, u = ca.SX.sym("x", 6), ca.SX.sym("u", 3)
    s = layout.symbol()
    x_next = ca.vertcat(x[:3] + DT * x[3:], x[3:] + DT * u)
    return Model.from_expressions(
        "double_integrator_3d", x, u, x_next, dt=DT, u_min=[-U_LIMIT] * 3,
        u_max=[U_LIMIT] * 3, h=layout.margins(x[:3], s), position=(0, 1, 2), scene=s,
        scene_value=obstacles, scene_layout=layout)


def circles_grid(n: int, circles) -> SignedDistanceGrid:
    """n x n nodes over [0, EXTENT]^2: the signed distance of a union of circles."""
    xs = np.linspace(0.0, EXTENT, n)
    c = np.asarray(circles, dtype=float)
    d = np.full((n, n), np.inf)
    for x, y, r in c:
        d = np.minimum(d, np.hypot(xs[:, None] - x, xs[None, :] - y) - r)
    return SignedDistanceGrid(d, (0.0, 0.0), EXTENT / (n - 1))


def many_circles(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(0.5, EXTENT - 0.5, (n, 2)), rng.uniform(0.1, 0.25, n)]


@dataclass
class Kernel:
    """A compiled, verified SAIS kernel of one model and its prepared calls per scene."""

    sp: SamplingProblem
    k: CompiledKernel
    build_s: float

    def call(self, cfg: SceneBenchConfig, scene=None, spread: bool = False):
        """The bare kernel call on the model's scene (or ``scene``, a flat vector); ``spread``:
        every sample starts at its own place, uniform over the map (else all at one)."""
        sp, k = self.sp, self.k
        N, T = cfg.samples, cfg.horizon
        m = sp.model
        d = len(m.position or ())
        x0 = np.zeros(m.nx)
        x0[:d], x0[d:2 * d] = 1.0, 2.0  # from (1, 1[, 1]) at 2 m/s per axis
        goal = np.zeros(m.nx)
        goal[:d] = 8.0
        rng = np.random.default_rng(cfg.seed)
        U = rng.normal(0.0, 1.0, (T, m.nu))
        K = rng.normal(0.0, 0.1, (T, m.nu, m.nx))
        c = SamplerConstants(sigma=np.full(m.nu, 2.0), lam=1.0, nu_mix=0.1, u_min=m.u_min,
                             u_max=m.u_max, crash_cost=1e6, p=goal, alpha=2e4,
                             scene=m.scene_value if scene is None else scene)
        _, c = check_batch(sp, N, U, c)
        X0 = np.tile(x0, (N, 1))
        if spread:
            X0[:, :d] = rng.uniform(0.0, EXTENT, (N, d))
        fn, _, _ = prepared_kernel(k, k.carry.pack(N, x=X0, x_nom=X0), c.kernel_consts(),
                                   {"u": U, "K": K.reshape(T, -1)}, seed=1)
        return lambda i: fn()


def sais_kernel(model: Model, tag: str) -> Kernel:
    """The SAIS kernel alone (not the sampler library's three), built and checked."""
    sp = goal_problem(model)
    t0 = time.perf_counter()
    spec = sais_spec(sp)
    lib = build_library(f"bench_scene_{tag}", [], kernel_source([spec]),
                        extra_flags=kernel_flags("float64"))
    if lib is None:
        raise RuntimeError("no C compiler")
    k = CompiledKernel(spec, lib.cdll, *layouts(sp, "sais"))
    verify_kernel(k)
    return Kernel(sp, k, time.perf_counter() - t0)


BASES = ("cpu", "wall", "wall_min")


def _timed(fns: dict, cfg: SceneBenchConfig) -> dict[str, dict[str, float]]:
    """ms per call of each function, by basis: ``cpu`` the median thread CPU time (the time
    the kernel ran: robust when other processes share the cores), ``wall`` the median wall
    time, ``wall_min`` the fastest call. The functions are timed in turn: ``cfg.repeats``
    rounds of 5 timed calls of each after 1 untimed (a controller calls one kernel over and
    over)."""
    t = samples_in_turn(fns, cfg.repeats, block=5, warmup=1, warm=1)
    return {"cpu": {k: 1e3 * statistics.median(c) for k, (_, c) in t.items()},
            "wall": {k: 1e3 * statistics.median(w) for k, (w, _) in t.items()},
            "wall_min": {k: 1e3 * min(w) for k, (w, _) in t.items()}}


def measure(cfg: SceneBenchConfig) -> dict:
    """Every figure of the module docstring, per timing basis (:func:`_timed`): ms per
    kernel call, ns per sample-step, ratios."""
    steps = cfg.samples * cfg.horizon
    builds: dict[str, float] = {}

    def kernel(model: Model, tag: str) -> Kernel:
        k = sais_kernel(model, tag)
        builds[tag] = k.build_s
        return k

    def planar(layout: SceneLayout | None, objs: list) -> Model:
        return (double_integrator(obstacles=(), u_limit=U_LIMIT) if layout is None else
                double_integrator(scene_layout=layout, obstacles=objs, u_limit=U_LIMIT))

    def ns(ms: float) -> float:
        return 1e6 * ms / steps

    out: dict = {"build_s": builds}
    # (a) one grid margin against one circle margin, above the obstacle-free model
    n = cfg.grid_vs_circle_size
    none = kernel(planar(None, []), "none")
    circle = kernel(planar(SceneLayout.of(circles=1), [Circle(FEW[0][:2], FEW[0][2])]),
                    "circles_1")
    grid = kernel(planar(SceneLayout.of(grid=(n, n)), [circles_grid(n, FEW)]), f"grid_{n}")
    t = _timed({"none": none.call(cfg), "circle": circle.call(cfg), "grid": grid.call(cfg)},
               cfg)
    a: dict = {"grid_nodes": [n, n]}
    for b, ms in t.items():
        per = {k: ns(ms[k] - ms["none"]) for k in ("circle", "grid")}
        a[b] = {"ms": ms, "ns_per_sample_step": per, "grid_over_circle": per["grid"]
                / per["circle"]}
    out["grid_vs_circle"] = a
    # (b) grid size (samples starting together or spread over the map), occupancy at one size
    kernels = {s: grid if s == n else kernel(planar(SceneLayout.of(grid=(s, s)),
                                                    [circles_grid(s, FEW)]), f"grid_{s}")
               for s in cfg.grid_sizes}
    t = _timed({f"{s}{tag}": k.call(cfg, spread=bool(tag)) for s, k in kernels.items()
                for tag in ("", "_spread")}, cfg)
    out["grid_sizes"] = {str(s): {"table_kB": 8 * s * s / 1024,
                                  "resolution_m": EXTENT / (s - 1),
                                  **{b: {"ms": ms[str(s)], "spread_ms": ms[f"{s}_spread"]}
                                     for b, ms in t.items()}}
                         for s in cfg.grid_sizes}
    s = cfg.occupancy_size
    k = kernels.get(s) or kernel(planar(SceneLayout.of(grid=(s, s)), [circles_grid(s, FEW)]),
                                 f"grid_{s}")
    maps = {"few": circles_grid(s, FEW),
            "many": circles_grid(s, many_circles(cfg.many_obstacles, cfg.seed))}
    lay = k.sp.model.scene_layout
    assert lay is not None
    t = _timed({name: k.call(cfg, lay.vector([g])) for name, g in maps.items()}, cfg)
    out["occupancy"] = {
        "grid_nodes": [s, s],
        "maps": {name: {"occupied_share": float(np.mean(g.values < 0)),
                        "obstacles": len(FEW) if name == "few" else cfg.many_obstacles}
                 for name, g in maps.items()},
        **{b: {"ms": ms, "many_over_few": ms["many"] / ms["few"]} for b, ms in t.items()}}
    # (c) 3-D spheres against planar circles
    rng = np.random.default_rng(cfg.seed + 1)
    calls, cnt = {}, cfg.obstacles
    for m in cnt:
        cs = np.c_[rng.uniform(2.0, 9.0, (m, 3)), rng.uniform(0.2, 0.5, m)]
        circ = kernel(planar(SceneLayout.of(circles=m), [Circle(tuple(r[:2]), r[3]) for r in cs]),
                      f"circles_{m}")
        sph = kernel(double_integrator_3d(SceneLayout(3, (("spheres", m),)),
                                          [Sphere(tuple(r[:3]), r[3]) for r in cs]),
                     f"spheres_{m}")
        calls[f"circles_{m}"], calls[f"spheres_{m}"] = circ.call(cfg), sph.call(cfg)
    t = _timed(calls, cfg)
    c: dict = {"counts": list(cnt)}
    for b, ms in t.items():
        sl = {kind: ns(ms[f"{kind}_{cnt[1]}"] - ms[f"{kind}_{cnt[0]}"]) / (cnt[1] - cnt[0])
              for kind in ("circles", "spheres")}
        c[b] = {"ms": ms, "ns_per_obstacle_sample_step": sl,
                "sphere_over_circle_per_obstacle": sl["spheres"] / sl["circles"],
                "sphere_over_circle_total": {str(m): ms[f"spheres_{m}"] / ms[f"circles_{m}"]
                                             for m in cnt}}
    out["spheres_vs_circles"] = c
    return out


def records(repeats: int = 7, cfg: SceneBenchConfig | None = None) -> list[dict]:
    """The records of ``make bench`` (1 thread): values and baselines on the CPU-time basis,
    every basis in the params."""
    cfg = cfg or SceneBenchConfig(repeats=repeats)
    with pinned_threads(1):
        m = measure(cfg)
    common = {"N": cfg.samples, "T": cfg.horizon, "threads": 1, "kernel": "SAIS, bare C call",
              "basis": "median thread CPU time (wall medians and minima in the params)"}
    g, sizes, occ, sph = (m["grid_vs_circle"], m["grid_sizes"], m["occupancy"],
                          m["spheres_vs_circles"])
    first = str(cfg.grid_sizes[0])
    per, sl = g["cpu"]["ns_per_sample_step"], sph["cpu"]["ns_per_obstacle_sample_step"]
    out = [record("scene_grid_margin_ns_per_sample_step", per["grid"], "ns/sample-step",
                  "circle_margin_ns_per_sample_step", per["circle"],
                  {**common, **g, "kernel_build_s": m["build_s"]}),
           record("scene_grid_occupancy_many_vs_few", occ["cpu"]["ms"]["many"], "ms",
                  "few_obstacles_ms", occ["cpu"]["ms"]["few"], {**common, **occ}),
           record(f"scene_spheres_vs_circles_per_obstacle_n{cfg.obstacles[1]}",
                  sl["spheres"], "ns/obstacle/sample-step", "circle_ns_per_obstacle_sample_step",
                  sl["circles"], {**common, **sph})]
    for s, v in sizes.items():
        for tag, key in (("", "ms"), ("_spread", "spread_ms")):
            out.append(record(f"scene_grid_sais_{s}x{s}{tag}", v["cpu"][key], "ms",
                              f"grid_{first}{tag}_ms", sizes[first]["cpu"][key],
                              {**common, **v, "starts": "uniform over the map" if tag else
                               "one place"}))
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.scene_margins",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("reports/bench/scene_margins.json"))
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args(argv)
    if args.repeats < 1:
        ap.error(f"--repeats {args.repeats}: must be at least 1")
    t0 = time.perf_counter()
    recs = records(args.repeats)
    for r in recs:
        print(f"{r['name']:48s} {r['value']:10.4g} {r['unit']:24s} baseline "
              f"{r['baseline']} = {r['baseline_value']:.4g}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(args.out, {"records": recs, "machine": machine(),
                                 "measured": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
                                 "run_s": time.perf_counter() - t0})
    print(f"wrote {args.out} ({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()

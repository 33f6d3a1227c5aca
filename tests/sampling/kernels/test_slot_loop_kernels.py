"""Slot-loop sampler kernels (workbench/sampling/kernels/slots.py) against the straight-line ones.

Same problem, same seed: the MPPI, SAIS and candidate kernels of both libraries must agree per
element (|a - b| <= 1e-12 max(|a|, |b|, 1); in practice bitwise) on the paper's 30-circle map, on
an odd number of slots with empty ones (radius 0 nearby, inert far away), with gamma != 0, on a
unicycle, and on a plain model (crash test only, one slot); with crashes in every batch. Broken
copies of the loop kernel (a loop bound off by one, a dropped last slot) must fail the comparison.
"""

from __future__ import annotations

import numpy as np
import pytest

from workbench.problem.barrier import BarrierOptions, embed_barrier
from workbench.problem.models import double_integrator
from workbench.problem.obstacles import INERT_CENTER, Circle
from workbench.problem.vehicles import unicycle
from workbench.sampling.kernels import library, slots
from workbench.sampling.kernels.constants import SamplerConstants
from workbench.sampling.kernels.flags import kernel_flags
from workbench.sampling.kernels.specs import layouts
from workbench.sampling.kernels.verify import KernelMismatch
from workbench.sampling.problem import goal_costs, navigation_costs
from workbench.scenarios.navigation import navigation_setup

RTOL = 1e-12
N, T = 37, 40  # N not a multiple of the block width: a padded block


def _scene(entries) -> np.ndarray:
    return np.array([v for e in entries for v in e], dtype=float)


def _problems() -> dict:
    """name -> (sampling problem, scene vector, physical start, physical goal)."""
    out = {}
    nav = navigation_setup()
    sp = nav.problem
    sc = sp.model.scene_value.reshape(-1, 3)
    # start just outside the circle nearest the map's centre, heading into it at 0.5 m/s
    k = int(np.argmin(np.linalg.norm(sc[:, :2] - 5.0, axis=1)))
    c, r = sc[k, :2], sc[k, 2]
    d = np.array([-1.0, -0.4]) / np.hypot(1.0, 0.4)
    out["nav30"] = (sp, sp.model.scene_value, np.r_[c + (r + 0.3) * d, -0.5 * d], nav.goal)
    # 9 slots (odd): 4 pairs in the loop and a last slot; a small circle near the path and an
    # unused (inert) slot between real circles; gamma != 0 (the sums at x_k as well)
    di = double_integrator(obstacles=(Circle((2.0, 2.0), 0.8),), u_limit=5.0, scene_capacity=9)
    sp9 = navigation_costs(embed_barrier(di, BarrierOptions(gamma=0.4)))
    scene9 = _scene([(2.0, 2.0, 0.8), (3.2, 1.0, 0.5), (1.5, 1.5, 0.05),
                     (1.0, 3.0, 0.6), (INERT_CENTER, INERT_CENTER, 0.0), (3.0, 3.0, 0.7),
                     (2.4, 0.5, 0.4), (0.4, 2.3, 0.3), (2.0, 3.6, 0.5)])
    out["odd9_gamma"] = (sp9, scene9, np.array([0.9, 0.9, 0.8, 0.8]),
                         np.array([4.0, 4.0, 0.0, 0.0]))
    # unicycle, 3 slots: the first pair and a last slot, no loop iterations
    uni = unicycle(obstacles=(Circle((1.5, 1.2), 0.5),), scene_capacity=3)
    spu = goal_costs(embed_barrier(uni), Q=[1.0, 1.0, 0.1], S=[10.0, 10.0, 1.0])
    sceneu = _scene([(1.5, 1.2, 0.5), (0.8, 1.9, 0.4), (2.0, 0.2, 0.3)])
    out["unicycle3"] = (spu, sceneu, np.array([0.8, 0.8, 0.6]), np.array([3.0, 3.0, 0.0]))
    # plain double integrator (crash test only), one slot
    d1 = double_integrator(obstacles=(Circle((2.0, 2.0), 0.8),), u_limit=5.0)
    sp1 = navigation_costs(d1, S=(10.0, 10.0, 1.0, 1.0))
    out["plain1"] = (sp1, d1.scene_value, np.array([0.9, 0.9, 0.8, 0.8]),
                     np.array([4.0, 4.0, 0.0, 0.0]))
    return out


PROBLEMS = _problems()


def _consts(sp, scene, goal) -> SamplerConstants:
    m = sp.model
    return SamplerConstants(sigma=np.full(sp.nu, 3.0), lam=1.3, nu_mix=0.1, u_min=m.u_min,
                            u_max=m.u_max, crash_cost=1e3, p=m.lift(goal, scene), alpha=50.0,
                            scene=scene)


def run_all(lib, sp, scene, x_phys, goal, seed: int = 11) -> dict[str, np.ndarray]:
    """Results and lane outputs of the three kernels of ``lib`` on one seeded batch."""
    rng = np.random.default_rng(5)
    m = sp.model
    c = _consts(sp, scene, goal)
    consts = c.kernel_consts()
    x0 = m.lift(x_phys, scene)
    xs0 = m.lift(x_phys + rng.normal(0.0, 0.05, x_phys.size), scene)
    U = rng.normal(0.0, 1.0, (T, sp.nu))
    K = rng.normal(0.0, 0.3, (T, sp.nu * sp.nx))
    out = {}
    k = lib.mppi
    o = k(k.carry.pack(N, x=x0), consts=consts, time_in={"u": U}, seed=seed)
    out |= {"mppi.result": o.result, "mppi.v": o.lane_out[0]}
    k = lib.sais
    o = k(k.carry.pack(N, x=x0, x_nom=xs0), consts=consts, time_in={"u": U, "K": K}, seed=seed)
    out |= {"sais.result": o.result, "sais.v_nom": o.lane_out[0], "sais.v_real": o.lane_out[1]}
    k = lib.candidates
    carry = k.carry.pack(N, x=x0, delay=rng.integers(0, 4, N), stride=rng.integers(0, 2, N))
    o = k(carry, consts=consts, time_in={"u": U, "u_next": np.roll(U, -1, axis=0)}, seed=seed)
    out |= {"candidates.result": o.result, "candidates.v": o.lane_out[0]}
    return out


def max_rel(a: dict, b: dict) -> float:
    """Largest per-element relative difference |a - b| / max(|a|, |b|, 1) (inf when the
    non-finite entries differ)."""
    worst = 0.0
    for key in a:
        x, y = np.asarray(a[key]), np.asarray(b[key])
        if x.shape != y.shape or not np.array_equal(np.isfinite(x), np.isfinite(y)):
            return np.inf
        f = np.isfinite(x)
        d = np.abs(x[f] - y[f]) / np.maximum(np.maximum(np.abs(x[f]), np.abs(y[f])), 1.0)
        worst = max(worst, float(d.max(initial=0.0)))
    return worst


_LIBS: dict = {}


def libraries(name: str):
    if name not in _LIBS:
        sp = PROBLEMS[name][0]
        ref = library.load_sampler_library(sp, slot_loop=False)
        loop = library.load_sampler_library(sp, slot_loop=True)
        if ref is None or loop is None:
            pytest.skip("no C compiler")
        _LIBS[name] = (ref, loop)
    return _LIBS[name]


@pytest.mark.parametrize("name", list(PROBLEMS))
def test_loop_kernels_equal_straight_line(name):
    sp, scene, x_phys, goal = PROBLEMS[name]
    ref, loop = libraries(name)
    a = run_all(ref, sp, scene, x_phys, goal)
    b = run_all(loop, sp, scene, x_phys, goal)
    assert max_rel(a, b) <= RTOL
    # the batches are informative: some samples crash, some do not (real and nominal systems)
    lay = layouts(sp, "sais")[1]
    r = lay.unpack(a["sais.result"])
    for key in ("crashed_real", "crashed_nom"):
        assert 0 < np.mean(r[key]) < 1, (key, np.mean(r[key]))
    assert 0 < np.mean(layouts(sp, "mppi")[1].unpack(a["mppi.result"])["crashed"]) < 1


def _broken(source: str, n_pairs: int, what: str) -> str:
    """A broken copy of a loop library's source: the pair loop stops one pair early
    (``bound``) or the odd last slot is left out (``tail``)."""
    if what == "bound":
        old = f"j < {n_pairs};"
        assert old in source
        return source.replace(old, f"j < {n_pairs - 1};")
    lines, out, depth = source.splitlines(), [], 0
    for i, s in enumerate(lines):
        if not depth and i + 1 < len(lines) and s.strip() == "{" and \
                lines[i + 1].rstrip().endswith(f"+ {6 * n_pairs};"):
            depth = 1
            continue
        if depth:
            depth += s.count("{") - s.count("}")
            continue
        out.append(s)
    assert len(out) < len(lines)
    return "\n".join(out)


@pytest.mark.parametrize("what", ["bound", "tail"])
def test_broken_loop_fails(what):
    name = "odd9_gamma"
    sp, scene, x_phys, goal = PROBLEMS[name]
    ref, loop = libraries(name)
    a = run_all(ref, sp, scene, x_phys, goal)
    stem, specs, source = library.library_sources(sp, slot_loop=True)
    bad = _broken(source, 4, what)
    lib = library._load(f"{stem}_broken_{what}", bad, kernel_flags())
    lays = [layouts(sp, k) for k in ("mppi", "sais", "candidates")]
    broken = library._sampler_library(lib.cdll, specs, lays)
    b = run_all(broken, sp, scene, x_phys, goal)
    for kern in ("mppi", "sais", "candidates"):
        part = {k: v for k, v in a.items() if k.startswith(kern + ".")}
        assert max_rel(part, {k: b[k] for k in part}) > 1e3 * RTOL, kern
    # the unbroken copy passes the same comparison
    assert max_rel(a, run_all(loop, sp, scene, x_phys, goal)) <= RTOL


def test_code_size_does_not_grow_with_slots():
    sizes = []
    for cap in (10, 200):
        di = double_integrator(obstacles=(Circle((2.0, 2.0), 0.8),), u_limit=5.0,
                               scene_capacity=cap)
        sp = navigation_costs(embed_barrier(di))
        sizes.append(len(slots.emit_slot_kernel(slots.sais_slot_spec(sp)).splitlines()))
    assert sizes[0] == sizes[1]


def test_refuses_what_it_does_not_support():
    di = double_integrator(obstacles=(Circle((2.0, 2.0), 0.8), Circle((3.0, 1.0), 0.5)),
                           u_limit=5.0)
    cases = {
        "kind 'log'": embed_barrier(di, BarrierOptions(kind="log")),
        "grouping 'per_obstacle'": embed_barrier(di, BarrierOptions(grouping="per_obstacle")),
        "no circle slots": embed_barrier(double_integrator(
            obstacles=(Circle((2.0, 2.0), 0.8),), u_limit=5.0, runtime_obstacles=False)),
    }
    for words, model in cases.items():
        sp = goal_costs(model, Q=[1.0, 1.0, 0.1, 0.1], S=[10.0, 10.0, 1.0, 1.0])
        with pytest.raises(slots.SlotLoopUnsupported, match=words):
            slots.sais_slot_spec(sp)
        assert words in slots.unsupported_reason(sp)
        assert not slots.use_slot_loop(sp, min_slots=1)
    sp = navigation_costs(embed_barrier(di))
    with pytest.raises(slots.SlotLoopUnsupported, match="float32"):
        slots.mppi_slot_spec(sp, precision="float32")
    assert slots.unsupported_reason(sp) is None
    assert slots.use_slot_loop(sp, min_slots=2) and not slots.use_slot_loop(sp, min_slots=3)


def test_refuses_non_circle_margins():
    import casadi as ca

    from workbench.problem.models import Model
    from workbench.problem.obstacles import scene_symbol, slot_margins

    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 2)
    s = scene_symbol(2)
    h = slot_margins(x, s)
    h = ca.vertcat(h[0], h[1] + 0.1 * x[0])  # slot 1 is not the same expression as slot 0
    m = Model.from_expressions("odd", x, u, x + 0.02 * u, dt=0.02, u_min=[-1, -1],
                               u_max=[1, 1], h=h, scene=s, scene_capacity=2,
                               position=(0, 1))
    sp = goal_costs(embed_barrier(m), Q=[1.0, 1.0], S=[1.0, 1.0])
    with pytest.raises(slots.SlotLoopUnsupported, match="margin 1"):
        slots.mppi_slot_spec(sp)


def test_growth_report_states_loop_slopes_and_ratios():
    from benchmarks.growth import GrowthConfig, _fits, loop_comparison, markdown, summarise

    cfg = GrowthConfig(circles=(10, 100, 1000), fit_from_circles=10)
    x = list(cfg.circles)
    series = {"sais_batch": [2.0, 10.0, 466.0], "sais_batch_loop": [2.1, 6.0, 48.0],
              "bas_mppi_step": [1.0, 3.0, 146.0], "bas_mppi_step_loop": [1.0, 3.0, 23.0]}
    axes = {"circles": {"x": x, "series": series, "series_min": series,
                        "fits": _fits(x, series, 10), "fits_min": _fits(x, series, 10)}}
    data = {"config": {**cfg.__dict__}, "axes": axes, "summary": summarise(axes, cfg),
            "threads": 1, "compile": {}}
    rows = loop_comparison(data)
    assert [r["circles"] for r in rows] == x
    assert rows[-1]["sais_batch_loop_ratio"] == pytest.approx(48.0 / 466.0)
    slope = data["summary"]["sais_batch_loop"]["ms_per_circle"]
    assert slope == pytest.approx(np.polyfit(x, series["sais_batch_loop"], 1)[0])
    md = markdown(data)
    assert "### Slot-loop kernels" in md and f"slot loop {slope:.4f} ms per circle" in md


def test_the_library_chooses_the_loop_from_the_slot_threshold():
    """30 circle slots (the navigation map): loop kernels by default; 9 slots: straight-line;
    float32 (unsupported by the loop): straight-line; ``slot_loop`` forces either."""
    nav30, nine = PROBLEMS["nav30"][0], PROBLEMS["odd9_gamma"][0]
    assert library.library_sources(nav30)[0].endswith("_loop")
    assert not library.library_sources(nine)[0].endswith("_loop")
    assert library.library_sources(nine, slot_loop=True)[0].endswith("_loop")
    assert not library.library_sources(nav30, slot_loop=False)[0].endswith("_loop")
    assert not library.library_sources(nav30, precision="float32")[0].endswith("_loop")


def test_an_automatic_loop_library_that_fails_its_check_falls_back(monkeypatch):
    """A loop library that fails the load-time check is replaced by the straight-line one,
    with one warning; asked for explicitly (slot_loop=True) the failure is raised."""
    sp = PROBLEMS["nav30"][0]
    real = library.load_verified
    stems = []

    def failing(stem, source, *a, **kw):
        stems.append(stem)
        if stem.endswith("_loop"):
            raise KernelMismatch(f"compiled kernel in {stem}: planted mismatch")
        return real(stem, source, *a, **kw)

    monkeypatch.setattr(library, "load_verified", failing)
    with pytest.warns(RuntimeWarning, match="loop-over-circles kernels"):
        lib = library.load_sampler_library(sp)
    if lib is None:
        pytest.skip("no C compiler")
    assert stems[0].endswith("_loop") and not stems[-1].endswith("_loop")
    with pytest.raises(KernelMismatch, match="planted"):
        library.load_sampler_library(sp, slot_loop=True)

"""workbench.plot: every helper draws onto an Agg figure with labelled axes (m, %), an equal
aspect for planar plots, limits around all of its data, artists that follow from the data
(one line per path or sample, one red line per crashed sample, one cross per crash), and the
figure saves to PNG."""

from __future__ import annotations

import io
import subprocess
import sys

import matplotlib

matplotlib.use("Agg")
import numpy as np
import pytest
from matplotlib import colormaps
from matplotlib.colors import to_rgba
from matplotlib.figure import Figure

from workbench import plot
from workbench.problem.models import double_integrator
from workbench.problem.obstacles import Circle, scene_vector
from workbench.sampling.mppi import MPPI, MPPIConfig
from workbench.sampling.problem import navigation_costs
from workbench.sampling.samples import SampleTrajectories
from workbench.scenarios.scenes import CircleScene, NavigationScene
from workbench.sim import Episode

CIRCLES = (Circle((2.0, 2.0), 0.8), Circle((3.5, 1.0), 0.5), Circle((1.0, 3.2), 0.6))
RED = to_rgba("red")


def axes():
    return Figure().add_subplot()


def gid(ax, name: str) -> list:
    return [a for a in ax.lines if a.get_gid() == name]


def contains(ax, x, y) -> bool:
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    x, y = np.asarray(x, float), np.asarray(y, float)
    return bool(x0 <= x.min() and x.max() <= x1 and y0 <= y.min() and y.max() <= y1)


def planar(ax) -> None:
    assert ax.get_xlabel() == "x [m]" and ax.get_ylabel() == "y [m]"
    assert ax.get_aspect() == 1.0


def png(ax) -> bytes:
    buf = io.BytesIO()
    ax.figure.savefig(buf, format="png", dpi=40)
    data = buf.getvalue()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 1000
    return data


def test_importing_workbench_plot_does_not_import_matplotlib():
    code = "import sys, workbench.plot; print('matplotlib' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "False"


def test_scene_draws_every_circle_start_and_goal_and_fits_them():
    s = NavigationScene()
    ax = plot.scene(axes(), s)
    discs = [p for p in ax.patches if p.get_gid() == "obstacle"]
    obst = s.obstacles()
    assert len(discs) == len(obst) == 30
    assert sorted(d.radius for d in discs) == sorted(o.radius for o in obst)
    assert len(gid(ax, "start")) == len(gid(ax, "goal")) == 1
    c = np.array([(*o.center, o.radius) for o in obst])
    assert contains(ax, [*(c[:, 0] - c[:, 2]), *(c[:, 0] + c[:, 2]), s.start[0], s.goal[0]],
                    [*(c[:, 1] - c[:, 2]), *(c[:, 1] + c[:, 2]), s.start[1], s.goal[1]])
    planar(ax)
    png(ax)


def test_scene_accepts_vectors_triples_and_bounds():
    vec = scene_vector(CIRCLES, 5)  # 2 inert slots: not drawn
    ax = plot.scene(axes(), vec, start=(0.5, 0.5, 0.0, 0.0), bounds=(-1, 6, -2, 5))
    assert len([p for p in ax.patches if p.get_gid() == "obstacle"]) == 3
    assert contains(ax, [-1, 6], [-2, 5]) and len(gid(ax, "goal")) == 0
    ax = plot.scene(axes(), [(0.0, 0.0, 1.0), Circle((5.0, 5.0), 2.0)])
    assert contains(ax, [-1, 7], [-1, 7])
    ax = plot.scene(axes(), CircleScene(CIRCLES, start=(0.2, 0.2), goal=(4.5, 4.5)))
    assert contains(ax, [0.2, 4.5], [0.2, 4.5])
    with pytest.raises(ValueError, match="scene"):
        plot.scene(axes(), [1.0, 2.0])
    with pytest.raises(ValueError, match="bounds"):
        plot.scene(axes(), CIRCLES, bounds=(1, 0, 0, 1))


def episode(X, crash_step=None) -> Episode:
    X = np.asarray(X, float)
    return Episode(X=X, U=np.zeros((len(X) - 1, 2)), crashed=crash_step is not None,
                   crash_step=crash_step, min_margin=0.0, step_time_s=np.zeros(len(X) - 1))


def test_paths_one_line_per_episode_and_a_red_cross_per_crash():
    t = np.linspace(0, 1, 50)[:, None]
    eps = [episode(np.hstack([5 * t, 5 * t ** 2, 0 * t, 0 * t])),
           episode(np.hstack([-3 * t, 4 * t, 0 * t, 0 * t]), crash_step=49),
           episode(np.hstack([t, -2 * t, 0 * t, 0 * t]), crash_step=49)]
    ax = plot.scene(axes(), CIRCLES)
    before = (ax.get_xlim(), ax.get_ylim())
    plot.paths(ax, eps, label="demo")
    lines, crosses = gid(ax, "path"), gid(ax, "crash")
    assert len(lines) == 3 and len(crosses) == 2
    assert all(to_rgba(c.get_color()) == RED and c.get_marker() == "x" for c in crosses)
    np.testing.assert_array_equal(crosses[0].get_xydata()[0], eps[1].X[49, :2])
    allx = np.concatenate([e.X[:, 0] for e in eps])
    ally = np.concatenate([e.X[:, 1] for e in eps])
    assert contains(ax, allx, ally)
    assert contains(ax, before[0], before[1])  # the scene stays in view
    planar(ax)
    # a single array, fresh axes; position indices chosen
    ax = plot.paths(None, eps[0].X[:, [2, 3, 0, 1]], position=(2, 3))
    assert len(gid(ax, "path")) == 1 and contains(ax, eps[0].X[:, 0], eps[0].X[:, 1])
    png(ax)


def synthetic(nominal: bool = True) -> SampleTrajectories:
    rng = np.random.default_rng(0)
    K, T = 12, 20
    X = np.cumsum(rng.normal(size=(K, T + 1, 4)), axis=1) + 2.0
    w = np.exp(-rng.uniform(0, 30, K))
    w[3] = 0.0  # underflowed weight: the lowest colour
    crashed = np.zeros(K, bool)
    crashed[[1, 4, 7]] = True
    cn = np.zeros(K, bool)
    cn[[4, 9]] = True
    kw = {}
    if nominal:
        kw = {"nominal": X[:, :, :] * 0.5 - 4.0, "controls_nominal": np.zeros((K, T, 2)),
              "crashed_nominal": cn}
    return SampleTrajectories(real=X, controls=np.zeros((K, T, 2)), crashed=crashed,
                              weights=w / w.sum() * 0.7, index=np.arange(K) * 3, n_samples=40,
                              scene=scene_vector(CIRCLES, 3), **kw)


def test_samples_red_per_crash_colours_by_weight_and_fit_everything():
    rec = synthetic()
    ax = plot.samples(axes(), rec)
    real, bad = gid(ax, "sample"), gid(ax, "sample-crashed")
    nom, nom_bad = gid(ax, "nominal"), gid(ax, "nominal-crashed")
    assert len(bad) == rec.n_crashed == 3 and len(nom_bad) == int(rec.crashed_nominal.sum())
    assert len(real) + len(bad) == len(nom) + len(nom_bad) == rec.k
    assert all(to_rgba(ln.get_color()) == RED for ln in bad + nom_bad)
    assert not any(to_rgba(ln.get_color()) == RED for ln in real + nom)
    assert all(ln.get_linestyle() == "-" for ln in real + bad)
    assert all(ln.get_linestyle() == "--" for ln in nom + nom_bad)
    # colours: the heaviest kept sample gets the top of the map, a zero weight the bottom
    cmap = colormaps["viridis"]
    ok = ~rec.crashed
    heavy, zero = np.argmax(np.where(ok, rec.weights, -1)), 3
    by_x = {tuple(ln.get_xydata()[0]): ln for ln in real}
    assert to_rgba(by_x[tuple(rec.real[heavy, 0, :2])].get_color()) == pytest.approx(cmap(1.0))
    assert to_rgba(by_x[tuple(rec.real[zero, 0, :2])].get_color()) == pytest.approx(cmap(0.0))
    assert real[-1].get_xydata()[0] == pytest.approx(rec.real[heavy, 0, :2])  # drawn last
    # the step's scene, every state of both systems in view, colour bar added
    assert len([p for p in ax.patches if p.get_gid() == "obstacle"]) == 3
    for X in (rec.real, rec.nominal):
        assert contains(ax, X[..., 0], X[..., 1])
    assert len(ax.figure.axes) == 2
    planar(ax)
    png(ax)
    ax = plot.samples(axes(), rec, scene=(), nominal=False, colorbar=False)
    assert not ax.patches and not gid(ax, "nominal") and len(ax.figure.axes) == 1
    assert len(gid(ax, "sample-crashed")) == 3


def test_samples_of_a_recorded_step_and_of_a_step_without():
    model = double_integrator(obstacles=CIRCLES, u_limit=5.0)
    sp = navigation_costs(model, S=(10.0, 10.0, 1.0, 1.0))
    cfg = MPPIConfig(n_samples=125, horizon=30, lam=1.3, sigma=(3.0, 2.4), nu_mix=0.1)
    ctrl = MPPI(sp, (4.0, 4.0, 0.0, 0.0), cfg)
    x = np.array([1.0 - 0.9 / np.sqrt(2.0), 1.0 + 0.9 / np.sqrt(2.0), np.sqrt(2.0),
                  np.sqrt(2.0)])
    _, _, info = ctrl.step(ctrl.initial_state(), x, np.random.default_rng(0))
    with pytest.raises(ValueError, match="record_samples"):
        plot.samples(axes(), info)
    ctrl.record_samples(24)
    _, _, info = ctrl.step(ctrl.initial_state(), x, np.random.default_rng(0))
    ax = plot.samples(axes(), info)
    rec = info.samples
    assert len(gid(ax, "sample-crashed")) == rec.n_crashed and 0 < rec.n_crashed < rec.k
    assert len(gid(ax, "sample")) == rec.k - rec.n_crashed
    assert contains(ax, rec.real[..., 0], rec.real[..., 1])
    png(ax)


def test_safety_sweep_in_percent_with_its_band():
    v = np.array([10.0, 0.0, 5.0, 20.0])
    r = np.array([0.8, 1.0, 0.95, 0.5])
    lo, hi = r - np.array([0.1, 0.05, 0.1, 0.12]), np.minimum(r + 0.05, 1.0)
    ax = plot.safety_sweep(axes(), v, r, lo, hi, label="BaS-MPPI",
                           xlabel="disturbance variance [m²/s²]")
    (line,) = gid(ax, "rate")
    order = np.argsort(v)
    np.testing.assert_allclose(line.get_xydata(), np.c_[v[order], 100 * r[order]])
    bands = [c for c in ax.collections if c.get_gid() == "interval"]
    assert len(bands) == 1
    verts = bands[0].get_paths()[0].vertices
    assert verts[:, 1].min() == pytest.approx(100 * lo.min())
    assert verts[:, 1].max() == pytest.approx(100 * hi.max())
    assert ax.get_ylabel() == "safety rate [%]"
    assert ax.get_xlabel() == "disturbance variance [m²/s²]"
    assert contains(ax, v, 100 * np.r_[lo, hi])
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["BaS-MPPI"]
    png(ax)
    ax = plot.safety_sweep(axes(), [1e2, 1e3, 1e4], [0.9, 0.8, 0.7], log_x=True,
                           xlabel="samples N")
    assert ax.get_xscale() == "log" and contains(ax, [1e2, 1e4], [70, 90])
    assert not [c for c in ax.collections if c.get_gid() == "interval"]
    for bad in ({"rates": [90.0, 80.0, 70.0]}, {"low": [0.95, 0.7, 0.6]}):
        kw = {"rates": [0.9, 0.8, 0.7], "low": [0.8, 0.7, 0.6], "high": [1.0, 0.9, 0.8]}
        kw.update(bad)
        with pytest.raises(ValueError, match=r"rates|low"):
            plot.safety_sweep(axes(), [1, 2, 3], **kw)

"""workbench.plot: every helper draws onto an Agg figure with labelled axes (m, %), an equal
aspect for planar plots, limits around all of its data, artists that follow from the data
(one line per path or sample, one red line per crashed sample, one cross per crash), and the
figure saves to PNG."""

from __future__ import annotations

import io
import subprocess
import sys
from dataclasses import replace
from types import SimpleNamespace

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


# --- any model: projections, constraints from h(x), 3-D, the body hook ------------------------

def user_models():
    """examples/user_models.py (not a package), loaded from its path."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).parents[1] / "examples" / "user_models.py"
    spec = importlib.util.spec_from_file_location("user_models", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


UM = user_models()
ARM, POINT_MASS = UM.two_link_arm(), UM.point_mass_3d()
ARM_LINE = np.linspace(UM.ARM_START, UM.ARM_GOAL, 40)
PM_LINE = np.linspace(UM.POINT_MASS_START, UM.POINT_MASS_GOAL, 40)
JOINT_BOUNDS = (-np.pi, np.pi, -np.pi, np.pi)


def at(model, reference, index, coords) -> np.ndarray:
    """States: ``reference`` with the entries ``index`` set to ``coords`` (m, len(index))."""
    X = np.repeat(np.asarray(reference, float)[None, :], len(coords), axis=0)
    X[:, list(index)] = coords
    return X


def min_h(model, X) -> np.ndarray:
    return np.array([model.margins(x).min() for x in X])


def assert_on_zero_set(model, reference, index, vertices, spacing) -> None:
    """Each vertex lies within a quarter of a grid spacing of min h = 0: |min h| /
    |grad min h| (a first-order distance to the zero set, central differences) is below
    spacing / 4 (linear interpolation along the grid's edges does far better; a vertex placed
    anywhere else on a crossing edge would be off by up to half a spacing)."""
    rng = np.random.default_rng(1)
    pick = vertices[rng.choice(len(vertices), size=min(40, len(vertices)), replace=False)]
    X = at(model, reference, index, pick)
    h = min_h(model, X)
    eps = 1e-6
    grad = np.zeros((len(pick), len(index)))
    for d in range(len(index)):
        step = np.zeros(len(index))
        step[d] = eps
        grad[:, d] = (min_h(model, at(model, reference, index, pick + step))
                      - min_h(model, at(model, reference, index, pick - step))) / (2 * eps)
    distance = np.abs(h) / np.linalg.norm(grad, axis=1)
    assert np.all(distance < spacing / 4), (distance.max(), spacing)
    assert np.abs(h).max() < 0.05  # and small in h's own units (m^2, rad^2)


def contour_vertices(artist) -> np.ndarray:
    from matplotlib.path import Path

    out = [p.vertices[p.codes != Path.CLOSEPOLY] if p.codes is not None else p.vertices
           for p in artist.get_paths()]
    return np.concatenate(out)


def artists(ax, name: str) -> list:
    return [a for a in ax.get_children() if a.get_gid() == name]


def test_axis_labels_come_from_state_names_and_units():
    ax = plot.scene(axes(), ARM, states=("q1", "q2"), bounds=JOINT_BOUNDS)
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("q1 [rad]", "q2 [rad]")
    assert ax.get_aspect() == 1.0  # one unit: equal aspect
    ax = plot.paths(axes(), ARM_LINE, model=ARM, states=(0, "dq1"))
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("q1 [rad]", "dq1 [rad/s]")
    assert ax.get_aspect() == "auto"  # two units: no equal aspect
    bare = replace(ARM, state_units=None)
    ax = plot.paths(axes(), ARM_LINE, model=bare, states=("q2", "q1"))
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("q2", "q1")
    np.testing.assert_array_equal(gid(ax, "path")[0].get_xydata(), ARM_LINE[:, [1, 0]])
    # a built-in planar model: its position, in metres
    model = double_integrator(obstacles=CIRCLES)
    ax = plot.scene(axes(), model)
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("px [m]", "py [m]")
    assert len([p for p in ax.patches if p.get_gid() == "obstacle"]) == 3
    assert not artists(ax, "constraint")  # its margins are the circles: drawn as discs


def test_the_projection_is_remembered_on_the_axes():
    ax = plot.scene(axes(), ARM, states=("q1", "q2"), bounds=JOINT_BOUNDS)
    plot.paths(ax, ARM_LINE)  # no model, no states: the axes' projection
    np.testing.assert_array_equal(gid(ax, "path")[0].get_xydata(), ARM_LINE[:, :2])
    assert ax.get_xlabel() == "q1 [rad]"
    plot.paths(ax, ARM_LINE, model=ARM)  # the arm has no position: still the axes' projection
    assert len(gid(ax, "path")) == 2


def test_a_model_without_position_is_refused_until_states_name_what_to_draw():
    with pytest.raises(ValueError, match=r"^states = None is invalid: model 'two_link_arm' "
                       r"has no position to draw by default: name 2 or 3 of its states "
                       r"\('q1', 'q2', 'dq1', 'dq2'\)"):
        plot.scene(axes(), ARM)
    with pytest.raises(ValueError, match=r"^states = None is invalid: .* no position"):
        plot.paths(axes(), ARM_LINE, model=ARM)
    with pytest.raises(ValueError, match=r"^states = \['q1' 'elbow'\] is invalid: 'elbow' is "
                       r"not a state of model 'two_link_arm'; its states are \('q1', 'q2', "
                       r"'dq1', 'dq2'\)"):
        plot.scene(axes(), ARM, states=("q1", "elbow"))
    with pytest.raises(ValueError, match=r"^states = \[0 4\] is invalid: each entry must be a "
                       r"state name or an index in \[0, 3\]"):
        plot.scene(axes(), ARM, states=(0, 4))
    with pytest.raises(ValueError, match=r"^states = \['q1' 'q1'\] is invalid: .* distinct"):
        plot.scene(axes(), ARM, states=("q1", "q1"))
    with pytest.raises(ValueError, match=r"^states = 'q1' is invalid: must be 2 or 3 states"):
        plot.scene(axes(), ARM, states="q1")
    with pytest.raises(ValueError, match=r"^states = \['q1' 'q2'\] is invalid: state names "
                       r"need the model"):
        plot.paths(axes(), ARM_LINE, states=("q1", "q2"))
    with pytest.raises(ValueError, match=r"^ax = 'rectilinear axes' is invalid: drawing 3 "
                       r"states needs 3-D axes"):
        plot.scene(axes(), POINT_MASS)
    with pytest.raises(ValueError, match=r"^paths\[0\] = .* is invalid: need an Episode or "
                       r"states \(n, nx\) with the drawn states \(0, 3\)"):
        plot.paths(axes(), ARM_LINE[:, :2], model=ARM, states=("q1", "dq2"))
    with pytest.raises(ValueError, match=r"^position = .* give states or position"):
        plot.paths(axes(), ARM_LINE, states=(0, 1), position=(0, 1))


def test_constraints_of_h_are_drawn_as_their_zero_level_set_with_the_unsafe_side_shaded():
    ax = plot.scene(axes(), ARM, states=("q1", "q2"), start=UM.ARM_START, goal=UM.ARM_GOAL,
                    bounds=JOINT_BOUNDS)
    (line,) = artists(ax, "constraint")
    (fill,) = artists(ax, "unsafe")
    verts = contour_vertices(line)
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    spacing = max(x1 - x0, y1 - y0) / 200
    assert_on_zero_set(ARM, UM.ARM_START, (0, 1), verts, spacing)
    # every piece of the zero set is there: the elbow limit |q2| = 2.6 and the hand's disc
    assert np.any(np.abs(verts[:, 1] - UM.ELBOW_LIMIT) < 1e-3)
    assert np.any(np.abs(verts[:, 1] + UM.ELBOW_LIMIT) < 1e-3)
    assert np.any(np.abs(verts[:, 1]) < 1.0)
    # the shading covers unsafe joint angles, not safe ones
    probes = np.array([[0.0, 3.0], [0.0, -3.0], [np.pi / 4, 0.0], [0.0, 0.3], [-2.0, 0.0]])
    unsafe = min_h(ARM, at(ARM, UM.ARM_START, (0, 1), probes)) < 0
    assert unsafe.tolist() == [True, True, True, False, False]
    shaded = [any(p.contains_point(q) for p in fill.get_paths()) for q in probes]
    assert shaded == unsafe.tolist()
    assert not artists(ax, "reference")  # h depends on q1, q2 only: nothing to state
    png(ax)


def test_states_not_drawn_are_fixed_at_a_stated_reference():
    bounds = (-0.5, 5.5, 0.0, 2.6)
    with pytest.raises(ValueError, match=r"^reference = None is invalid: the margins of model "
                       r"'point_mass_3d' depend on \('py',\), which are not drawn"):
        plot.constraints(axes(), POINT_MASS, states=("px", "pz"), bounds=bounds)
    with pytest.raises(ValueError, match=r"^bounds = None is invalid: the axes show nothing"):
        plot.constraints(axes(), POINT_MASS, states=("px", "pz"), reference=PM_LINE[0])
    with pytest.raises(ValueError, match=r"^reference = .* is invalid: need a state of model "
                       r"'point_mass_3d': 6 or 6 entries"):
        plot.constraints(axes(), POINT_MASS, states=("px", "pz"), bounds=bounds,
                         reference=(0.0, 0.0))
    ref = np.array([0.0, 0.4, 0.0, 0.0, 0.0, 0.0])
    ax = plot.constraints(axes(), POINT_MASS, states=("px", "pz"), bounds=bounds,
                          reference=ref, resolution=301)
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("px [m]", "pz [m]")
    (text,) = artists(ax, "reference")
    assert text.get_text() == "h = 0 at py = 0.4 m"
    verts = contour_vertices(artists(ax, "constraint")[0])
    assert_on_zero_set(POINT_MASS, ref, (0, 2), verts, 6.0 / 300)
    # at py = 0.4 the first sphere's slice has radius sqrt(0.6^2 - 0.4^2)
    near = verts[np.hypot(verts[:, 0] - 2.0, verts[:, 1] - 1.0) < 0.6]
    assert len(near) and np.allclose(np.hypot(near[:, 0] - 2.0, near[:, 1] - 1.0),
                                     np.sqrt(0.6**2 - 0.4**2), atol=0.01)
    # paths: the first path's first state is the default reference
    ax = plot.paths(axes(), PM_LINE, POINT_MASS, states=("px", "pz"))
    assert artists(ax, "reference")[0].get_text() == "h = 0 at py = 0 m"


def test_circles_are_discs_and_the_other_margins_a_level_set():
    from workbench.problem.vehicles import QUAD_STATE_LIMITS, planar_quadrotor

    quad = planar_quadrotor(obstacles=(Circle((0.5, 1.0), 0.3),))
    x0 = np.array([-1.0, 0.0, 0.5, 0.0, 0.0, 0.0])
    ax = plot.scene(axes(), quad, start=x0, bounds=(-2.5, 2.5, -0.5, 2.5))
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("x [m]", "z [m]")
    assert len([p for p in ax.patches if p.get_gid() == "obstacle"]) == 1
    verts = contour_vertices(artists(ax, "constraint")[0])
    (xlo, xhi), (zlo, zhi) = QUAD_STATE_LIMITS[0], QUAD_STATE_LIMITS[2]
    # the box |x| <= 2, -0.05 <= z <= 2, not the circle (a disc already)
    on_box = (np.isclose(verts[:, 0], xlo, atol=0.03) | np.isclose(verts[:, 0], xhi, atol=0.03)
              | np.isclose(verts[:, 1], zlo, atol=0.03) | np.isclose(verts[:, 1], zhi, atol=0.03))
    assert on_box.all()
    # a navigation set-up: its plant is the model, its start state the reference
    setup = SimpleNamespace(plant=quad, scene=CircleScene((Circle((0.5, 1.0), 0.3),),
                                                          start=(-1.0, 0.5), goal=(1.5, 1.5)),
                            x0=x0)
    ax = plot.scene(axes(), setup, bounds=(-2.5, 2.5, -0.5, 2.5))
    assert len([p for p in ax.patches if p.get_gid() == "obstacle"]) == 1
    assert artists(ax, "constraint") and len(gid(ax, "start")) == 1
    assert gid(ax, "goal")[0].get_xydata()[0] == pytest.approx([1.5, 1.5])
    del setup.x0  # a start position alone does not fix the velocities and the angle
    with pytest.raises(ValueError, match=r"^reference = None is invalid: the margins of model "
                       r"'planar_quadrotor' depend on \('x_dot', 'z_dot', 'theta', "
                       r"'theta_dot'\), which are not drawn"):
        plot.scene(axes(), setup, bounds=(-2.5, 2.5, -0.5, 2.5))


def test_three_position_coordinates_draw_in_3d():
    from matplotlib.figure import Figure

    ax = plot.scene(None, POINT_MASS, start=UM.POINT_MASS_START, goal=UM.POINT_MASS_GOAL,
                    bounds=(-0.5, 5.5, -1.2, 2.2, 0.0, 2.6))
    assert ax.name == "3d"
    assert (ax.get_xlabel(), ax.get_ylabel(), ax.get_zlabel()) == ("px [m]", "py [m]", "pz [m]")
    (surface,) = artists(ax, "constraint")
    tris = np.asarray(surface._faces)  # the triangles in data coordinates
    assert tris.shape[1:] == (3, 3) and len(tris) > 100
    verts = tris.reshape(-1, 3)
    assert_on_zero_set(POINT_MASS, UM.POINT_MASS_START, (0, 1, 2), verts, 6.0 / 35)
    # spheres, floor and ceiling all there, coloured apart
    assert np.any(np.isclose(verts[:, 2], UM.FLOOR, atol=1e-6))
    assert np.any(np.isclose(verts[:, 2], UM.CEILING, atol=1e-6))
    for c, r in UM.SPHERES:
        assert np.any(np.abs(np.linalg.norm(verts - np.array(c), axis=1) - r) < 0.05)
    assert len({tuple(np.round(c, 3)) for c in surface.get_facecolor()[:, :3]}) > 4
    # equal-ish box: proportional to the spans, none below a quarter of the longest
    box = np.asarray(ax.get_box_aspect())
    spans = np.array([6.0, 3.4, 2.6]) * (1 + 2 * 0.03)
    np.testing.assert_allclose(box / box[0], spans / spans[0], rtol=0.02)
    plot.paths(ax, PM_LINE, label="line")
    (line,) = gid(ax, "path")
    np.testing.assert_allclose(np.column_stack(line.get_data_3d()), PM_LINE[:, :3])
    assert len(gid(ax, "start")) == len(gid(ax, "goal")) == 1
    png(ax)
    # samples of a model with a 3-D position
    rng = np.random.default_rng(0)
    K, T = 6, 10
    drift = np.zeros((K, T + 1, 6))
    drift[:, :, 0] = np.linspace(0.0, 2.5, T + 1)  # towards the first sphere
    X = np.cumsum(rng.normal(size=(K, T + 1, 6)) * 0.1, axis=1) + UM.POINT_MASS_START + drift
    rec = SampleTrajectories(real=X, controls=np.zeros((K, T, 3)), crashed=np.eye(K)[1] > 0,
                             weights=np.full(K, 1.0 / K), index=np.arange(K), n_samples=K,
                             position=(0, 1, 2))
    ax = plot.samples(Figure().add_subplot(projection="3d"), rec, model=POINT_MASS)
    lines = gid(ax, "sample") + gid(ax, "sample-crashed")
    assert len(lines) == K and len(gid(ax, "sample-crashed")) == 1
    assert {tuple(np.column_stack(ln.get_data_3d())[0]) for ln in lines} == {
        tuple(x) for x in X[:, 0, :3]}
    assert artists(ax, "constraint")  # the model's surface, over the samples' view
    with pytest.raises(ValueError, match=r"^ax = '3d axes' is invalid: drawing 2 states needs "
                       r"planar axes"):
        plot.paths(ax, PM_LINE, model=POINT_MASS, states=("px", "py"))


def test_samples_of_a_model_without_position_need_states():
    rng = np.random.default_rng(0)
    K, T = 5, 8
    X = np.cumsum(rng.normal(size=(K, T + 1, 4)) * 0.05, axis=1) + UM.ARM_START
    rec = SampleTrajectories(real=X, controls=np.zeros((K, T, 2)), crashed=np.zeros(K, bool),
                             weights=np.full(K, 0.2), index=np.arange(K), n_samples=K,
                             position=None)
    with pytest.raises(ValueError, match=r"^states = None is invalid: the samples' model has "
                       r"no position"):
        plot.samples(axes(), rec)
    with pytest.raises(ValueError, match=r"^states = None is invalid: model 'two_link_arm' "
                       r"has no position"):
        plot.samples(axes(), rec, model=ARM)
    ax = plot.samples(axes(), rec, model=ARM, states=("q1", "q2"), colorbar=False)
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("q1 [rad]", "q2 [rad]")
    assert len(gid(ax, "sample")) == K
    assert contains(ax, X[..., 0], X[..., 1])
    # the level set covers the view of the samples (no zero crossing in so small a view)
    assert not artists(ax, "constraint")


def draw_arm(ax, x):
    (ex, ey), (hx, hy) = UM.arm_points(x[:2])
    return ax.plot([0.0, ex, hx], [0.0, ey, hy], "o-", color="tab:orange")


def test_the_body_hook_draws_the_body_at_chosen_states():
    (cx, cy), r = UM.DISC
    ax = plot.scene(axes(), [(cx, cy, r)])
    plot.bodies(ax, ARM_LINE, draw_arm, steps=4)
    links = gid(ax, "body")
    assert len(links) == 4
    for ln, k in zip(links, [0, 13, 26, 39], strict=True):
        (ex, ey), (hx, hy) = UM.arm_points(ARM_LINE[k, :2])
        np.testing.assert_allclose(ln.get_xydata(), [[0, 0], [ex, ey], [hx, hy]])
    alphas = [ln.get_alpha() for ln in links]
    assert alphas == pytest.approx([0.3, 0.3 + 0.7 / 3, 0.3 + 1.4 / 3, 1.0])
    hands = np.array([UM.arm_points(x[:2])[1] for x in ARM_LINE[[0, 13, 26, 39]]])
    assert contains(ax, [0.0, *hands[:, 0]], [0.0, *hands[:, 1]]) and ax.get_aspect() == 1.0
    ep = episode(ARM_LINE)
    ax = plot.bodies(axes(), ep, draw_arm, steps=[0, -1], fade=False)
    assert [ln.get_alpha() for ln in gid(ax, "body")] == [None, None]
    np.testing.assert_allclose(gid(ax, "body")[1].get_xydata()[0], [0.0, 0.0])
    png(ax)
    with pytest.raises(ValueError, match=r"^draw = 'NoneType' is invalid: must be a callable"):
        plot.bodies(axes(), ARM_LINE, None)
    with pytest.raises(ValueError, match=r"^draw = 'int' is invalid: must return the "
                       r"matplotlib artists"):
        plot.bodies(axes(), ARM_LINE, lambda ax, x: 3)
    with pytest.raises(ValueError, match=r"^steps = .* is invalid: must be a count >= 1 or "
                       r"state indices in \[-40, 39\]"):
        plot.bodies(axes(), ARM_LINE, draw_arm, steps=[0, 40])
    with pytest.raises(ValueError, match=r"^steps = 0 is invalid: must be an integer >= 1"):
        plot.bodies(axes(), ARM_LINE, draw_arm, steps=0)

"""workbench.plot draws every scene kind: circles as discs, moving circles with a velocity arrow,
half-planes as a shaded side and a boundary line, capsules as stadiums, a signed-distance grid
as its zero level set with the inside shaded; the obstacles of a 3-D scene as their section
(the model's level set). Checked by the artists' gids and extents, not by pixels."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import numpy as np
import pytest
from matplotlib.figure import Figure

from workbench import plot
from workbench.plot.obstacles import clip, stadium
from workbench.problem.models import double_integrator
from workbench.problem.obstacles import Circle
from workbench.problem.scene_kinds import Capsule, HalfSpace, MovingCircle, Sphere
from workbench.problem.scene_layout import SceneLayout
from workbench.problem.sdf_grid import SignedDistanceGrid

LAYOUT = SceneLayout.of(circles=2, halfspaces=1, capsules=2, moving=1, grid=(11, 9))


def sdf() -> SignedDistanceGrid:
    xs, ys = np.arange(11) * 0.5, np.arange(9) * 0.5
    return SignedDistanceGrid(np.hypot(xs[:, None] - 4.0, ys[None, :] - 3.0) - 0.7, (0.0, 0.0),
                              0.5)


SCENE = [Circle((1.0, 1.0), 0.4), MovingCircle((2.0, 3.0), 0.3, (1.0, -0.5)),
         HalfSpace((0.0, 1.0), -0.5), Capsule((3.0, 0.5), (4.5, 1.0), 0.25), sdf()]


def axes():
    return Figure().add_subplot()


def with_gid(ax, name: str) -> list:
    return [a for a in ax.get_children() if a.get_gid() == name]


def inside_view(ax, pts) -> bool:
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    pts = np.asarray(pts, float)
    return bool(np.all((x0 <= pts[:, 0]) & (pts[:, 0] <= x1)
                       & (y0 <= pts[:, 1]) & (pts[:, 1] <= y1)))


def check_every_kind(ax) -> None:
    assert len(with_gid(ax, "obstacle")) == 1
    (moving,) = with_gid(ax, "moving-obstacle")
    assert moving.center == (2.0, 3.0) and moving.radius == 0.3
    (arrow,) = with_gid(ax, "velocity")  # to where the centre is 1 s later
    verts = arrow.get_path().vertices
    assert np.allclose(verts[:2], [(2.0, 3.0), (2.5, 2.75)])  # along v, halfway point second
    (capsule,) = with_gid(ax, "capsule")  # one used slot of two
    xy = capsule.get_xy()
    assert np.allclose([xy[:, 0].min(), xy[:, 0].max()], [2.75, 4.75], atol=0.01)
    rel = xy - [3.0, 0.5]
    d = np.abs(rel[:, 0] * 0.5 - rel[:, 1] * 1.5) / np.hypot(1.5, 0.5)  # from the axis line
    assert np.all(d <= 0.25 + 1e-9)
    (side,) = with_gid(ax, "half-plane")
    assert np.all(side.get_xy()[:, 1] <= -0.5 + 1e-9) and inside_view(ax, side.get_xy())
    (line,) = with_gid(ax, "half-plane-boundary")
    assert line.get_transform() is not None
    (boundary,) = with_gid(ax, "grid-boundary")
    ring = np.concatenate([p.vertices for p in boundary.get_paths() if len(p.vertices)])
    assert np.allclose(np.hypot(ring[:, 0] - 4.0, ring[:, 1] - 3.0), 0.7, atol=0.05)
    assert len(with_gid(ax, "grid-unsafe")) == 1
    assert inside_view(ax, [(0.6, 0.6), (5.0, 4.0), (2.0, 3.3), (4.75, 1.0), (2.5, -0.5)])


def test_a_layout_model_draws_each_kind_as_its_shape():
    model = double_integrator(scene_layout=LAYOUT, obstacles=SCENE)
    ax = plot.scene(axes(), model)
    check_every_kind(ax)
    assert not with_gid(ax, "constraint")  # every margin is an obstacle drawn as a shape


def test_objects_and_scene_vectors_draw_the_same_shapes():
    check_every_kind(plot.scene(axes(), SCENE))
    model = double_integrator(scene_layout=LAYOUT, obstacles=SCENE[:1])
    check_every_kind(plot.scene(axes(), model.scene_vector(SCENE), model=model))


def test_a_3d_scene_is_drawn_as_its_section_or_refused_without_its_model():
    layout = SceneLayout.of(dim=3, spheres=1)
    import casadi as ca

    from workbench.problem.models import Model

    x, u, s = ca.SX.sym("x", 6), ca.SX.sym("u", 3), layout.symbol()
    model = Model.from_expressions(
        "di3", x, u, ca.vertcat(x[:3] + 0.1 * x[3:], x[3:] + 0.1 * u), dt=0.1, u_min=-np.ones(3),
        u_max=np.ones(3), h=layout.margins(x[:3], s, "signed_distance"), position=(0, 1, 2),
        scene=s, scene_value=[Sphere((1.0, 1.0, 1.0), 0.5)], scene_layout=layout)
    # the plane z = 1.3 cuts the sphere in a circle of radius 0.4 around (1, 1)
    ax = plot.scene(axes(), model, states=(0, 1), reference=[0, 0, 1.3, 0, 0, 0],
                    bounds=(0, 2, 0, 2))
    (level,) = with_gid(ax, "constraint")
    ring = np.concatenate([p.vertices for p in level.get_paths() if len(p.vertices)])
    assert np.allclose(np.hypot(ring[:, 0] - 1.0, ring[:, 1] - 1.0), 0.4, atol=0.02)
    with pytest.raises(ValueError, match=r"scene\[0\].*3-D obstacle.*model="):
        plot.scene(axes(), [Sphere((1.0, 1.0, 1.0), 0.5)])
    with pytest.raises(ValueError, match=r"scene\[0\].*3-D obstacle"):
        plot.scene(axes(), [Capsule((0, 0, 0), (1, 1, 1), 0.2)])


def test_stadium_and_clip_shapes():
    out = stadium(np.array([0.0, 0.0]), np.array([2.0, 0.0]), 0.5)
    assert np.allclose([out[:, 0].min(), out[:, 0].max()], [-0.5, 2.5])
    assert np.allclose([out[:, 1].min(), out[:, 1].max()], [-0.5, 0.5])
    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    half = clip(square, np.array([1.0, 0.0]), 0.25)  # x >= 0.25
    assert np.allclose(sorted(half[:, 0]), [0.25, 0.25, 1.0, 1.0])
    assert clip(square, np.array([1.0, 0.0]), 2.0).shape == (0, 2)  # nothing of it
    assert len(clip(square, np.array([1.0, 0.0]), -1.0)) == 4  # all of it

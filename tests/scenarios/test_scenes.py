"""The scenes: the default navigation map, the map generator, and field-naming errors."""

from __future__ import annotations

import numpy as np
import pytest

# NavigationScene().obstacles() at commit 59746ed (centre x, centre y, radius): studies depend
# on the default map, so it must never change
DEFAULT_MAP = (
    (3.6, 5.0, 1.0),
    (6.4, 5.0, 1.0),
    (8.177710407756603, 7.205485521961548, 0.6750572799628003),
    (3.4013302792898035, 7.988427563170095, 0.43512431399435514),
    (8.91168118145508, 2.7224695858847916, 0.6733075376646976),
    (5.900316834184246, 1.351536063691067, 0.3961272203147067),
    (2.9801193762186466, 1.0943522043400469, 0.5981240612361025),
    (6.5362569670547135, 2.6048537918959616, 0.4154412863911864),
    (1.0298739364166076, 7.640381838413965, 0.521721786361324),
    (1.474013138764029, 4.10105440888583, 0.6589104403243279),
    (8.829983075289773, 5.719933544084882, 0.5276677029301875),
    (4.5225077375055, 2.9165116946361866, 0.3904728115010212),
    (2.1636796300874153, 2.539707959746659, 0.6418314887155664),
    (5.1899208632838425, 7.982473668518195, 0.5569321478336888),
    (1.213618800690277, 6.206459547377829, 0.39690739616819953),
    (7.082986367921458, 8.94359086998885, 0.38268969260995866),
    (6.701405408491719, 7.602587202400322, 0.3887928892572388),
    (7.936528773886831, 1.045779434987292, 0.8191871725649438),
    (2.5964397486623687, 6.699657548641414, 0.5656286815253313),
    (5.069257882212596, 6.451923698702372, 0.4584678189714996),
    (4.614476367378825, 1.5054366854803254, 0.3191124230427081),
    (1.1105513785387817, 8.975837187616321, 0.37343908978547574),
    (8.134723419716398, 4.066531158500579, 0.3589994498588287),
    (5.636461951445057, 3.4313292021710984, 0.32708807636476),
    (1.0472490997152324, 1.5462408377893073, 0.4270262085296371),
    (8.383640375175865, 8.848284623513528, 0.35061809906955804),
    (3.4098466100518685, 3.277434307267626, 0.3064857233124098),
    (2.5628858912628063, 8.822100253988628, 0.33522505662487273),
    (4.290984776958586, 8.90845975440461, 0.3308706227975195),
    (3.8867801513347935, 6.8960733945788055, 0.3135203013138548),
)


def test_class7_default_map_is_unchanged():
    from workbench.scenarios.scenes import NavigationScene

    got = tuple((o.center[0], o.center[1], o.radius) for o in NavigationScene().obstacles())
    assert got == DEFAULT_MAP  # exact, bit for bit


@pytest.mark.parametrize("seed", [0, 3, 9])
def test_class7_map_generator_succeeds_where_rejection_sampling_jammed(seed):
    """These seeds raised 'NavigationScene.seed = ... could not place 30 obstacles' before."""
    from workbench.scenarios.scenes import NavigationScene

    sc = NavigationScene(seed=seed)
    obs = sc.obstacles()
    assert len(obs) == 30
    C = np.array([o.center for o in obs])
    R = np.array([o.radius for o in obs])
    assert np.all((R[2:] >= sc.radius_range[0] - 1e-12) & (R[2:] <= sc.radius_range[1]))
    assert np.all((C[2:] >= sc.center_range[0] - 1e-9) & (C[2:] <= sc.center_range[1] + 1e-9))
    gaps = np.hypot(*(C[:, None] - C[None]).transpose(2, 0, 1)) - R[:, None] - R[None]
    np.fill_diagonal(gaps, np.inf)
    assert gaps.min() >= sc.edge_gap - 1e-9
    for e in (sc.start, sc.goal):
        assert (np.hypot(*(C[2:] - np.array(e)).T) - R[2:]).min() >= sc.endpoint_clearance - 1e-9


def _one_draw_at_a_time(sc):
    """The rejection sampler as a loop (one radius and one centre per draw), then the grid
    placement: the oracle of the vectorised sampler."""
    from workbench.problem.obstacles import Circle
    from workbench.scenarios.scenes import _DRAWS

    circles = sc._gates()
    rng = np.random.default_rng(sc.seed)
    ends = (np.array(sc.start), np.array(sc.goal))
    for _ in range(_DRAWS):
        if len(circles) == sc.n_obstacles:
            break
        r = rng.uniform(*sc.radius_range)
        c = rng.uniform(*sc.center_range, size=2)
        if any(np.linalg.norm(c - e) - r < sc.endpoint_clearance for e in ends):
            continue
        if any(np.linalg.norm(c - np.array(o.center)) - r - o.radius < sc.edge_gap
               for o in circles):
            continue
        circles.append(Circle((float(c[0]), float(c[1])), float(r)))
    if len(circles) < sc.n_obstacles:
        circles = sc._complete(circles, rng)
    return tuple(circles)


@pytest.mark.parametrize(("seed", "kwargs"), [(0, {}), (7, {}), (1003, {}),
                                              (5, {"n_obstacles": 12}),
                                              (2, {"n_obstacles": 40,
                                                   "radius_range": (0.2, 0.6)})])
def test_vectorised_rejection_sampling_equals_one_draw_at_a_time(seed, kwargs):
    """Bit for bit, on maps that rejection sampling completes (12 circles, the default map)
    and on maps where it jams and the grid placement goes on from the generator's state."""
    from workbench.scenarios.scenes import NavigationScene

    sc = NavigationScene(seed=seed, **kwargs)
    assert sc.obstacles() == _one_draw_at_a_time(sc)


def test_class7_infeasible_map_explains_density_not_seed():
    from workbench.scenarios.scenes import NavigationScene

    with pytest.raises(ValueError, match=r"too dense.*n_obstacles.*radius range.*gaps") as info:
        NavigationScene(n_obstacles=80, radius_range=(0.6, 0.9)).obstacles()
    assert "seed" not in str(info.value)


@pytest.mark.parametrize(("kwargs", "field"), [
    ({"radius_range": (0.9, 0.3)}, "NavigationScene.radius_range"),
    ({"center_range": (9.0, 1.0)}, "NavigationScene.center_range"),
    ({"start": (0.5, 0.5, 0.0)}, "NavigationScene.start"),
    ({"goal": (9.5,)}, "NavigationScene.goal"),
    ({"seed": -1}, "NavigationScene.seed"),
    ({"seed": 2.5}, "NavigationScene.seed"),
    ({"edge_gap": -0.1}, "NavigationScene.edge_gap"),
])
def test_class7_bad_navigation_scene_names_the_field(kwargs, field):
    from workbench.scenarios.scenes import NavigationScene

    with pytest.raises(ValueError, match=rf"^{field} = "):
        NavigationScene(**kwargs)


@pytest.mark.parametrize(("kwargs", "field"), [
    ({"start": (-5.0, 0.0)}, "TrackingScene.start"),
    ({"target": (5.0, 0.0, 0.0, 0.0, 1.0)}, "TrackingScene.target"),
    ({"horizon": 0}, "TrackingScene.horizon"),
])
def test_class7_bad_tracking_scene_names_the_field(kwargs, field):
    from workbench.scenarios.scenes import TrackingScene

    with pytest.raises(ValueError, match=rf"^{field} = "):
        TrackingScene(**kwargs)

# ---------------------------------------------------------------------------------------------
# accepted, then silently wrong


@pytest.mark.parametrize("n", [0, 1, -3, 2.5, True])
def test_class3_n_obstacles_below_two_or_not_an_integer_is_rejected(n):
    from workbench.scenarios.scenes import NavigationScene

    with pytest.raises(ValueError, match=r"^NavigationScene.n_obstacles = .*two gate circles"):
        NavigationScene(n_obstacles=n)


def test_class3_two_obstacles_gives_exactly_the_gates():
    from workbench.scenarios.scenes import NavigationScene

    obs = NavigationScene(n_obstacles=2).obstacles()
    assert len(obs) == 2 and {o.radius for o in obs} == {1.0}


@pytest.mark.parametrize(("field", "point"), [("start", (3.6, 5.0)), ("goal", (6.9, 5.2))])
def test_class3_start_or_goal_inside_an_obstacle_is_rejected(field, point):
    from workbench.scenarios.scenes import NavigationScene

    with pytest.raises(ValueError, match=rf"^NavigationScene.{field} = .*inside obstacle"):
        NavigationScene(**{field: point})

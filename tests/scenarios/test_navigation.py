"""The navigation set-up checks its scene."""

from __future__ import annotations

import pytest


def test_class3_navigation_setup_rejects_a_start_inside_a_custom_map_obstacle():
    from workbench.problem.obstacles import Circle
    from workbench.scenarios.navigation import navigation_setup
    from workbench.scenarios.scenes import NavigationScene

    class OneCircle(NavigationScene):
        def obstacles(self):
            return (Circle((1.0, 1.0), 0.8),)

    with pytest.raises(ValueError, match=r"^scene.start = .*inside obstacle 0"):
        navigation_setup(OneCircle())

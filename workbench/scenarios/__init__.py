"""Scenarios: the paper's scenes, the systems, the safe-sampling methods and the navigation
set-up built from a scene."""

from workbench.scenarios.navigation import NavigationSetup, navigation_setup
from workbench.scenarios.scenes import CircleScene, NavigationScene, TrackingScene
from workbench.scenarios.systems import SYSTEMS, System, register_system, system

__all__ = ["SYSTEMS", "CircleScene", "NavigationScene", "NavigationSetup", "System",
           "TrackingScene", "navigation_setup", "register_system", "system"]

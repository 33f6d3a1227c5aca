"""Scenarios: the paper's scenes, the systems and the navigation set-up built from a scene."""

from workbench.scenarios.navigation import CONTROLLERS, NavigationSetup, navigation_setup
from workbench.scenarios.scenes import CircleScene, NavigationScene, TrackingScene
from workbench.scenarios.systems import SYSTEMS, System, system

__all__ = ["CONTROLLERS", "SYSTEMS", "CircleScene", "NavigationScene", "NavigationSetup", "System",
           "TrackingScene", "navigation_setup", "system"]

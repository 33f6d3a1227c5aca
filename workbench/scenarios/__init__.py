"""Scenarios: the paper's scenes and the navigation set-up built from a scene."""

from workbench.scenarios.navigation import CONTROLLERS, NavigationSetup, navigation_setup
from workbench.scenarios.scenes import CircleScene, NavigationScene, TrackingScene

__all__ = ["CONTROLLERS", "CircleScene", "NavigationScene", "NavigationSetup", "TrackingScene",
           "navigation_setup"]

"""The problem core: models, obstacles, costs, the barrier-state transform and ``Problem``."""

from workbench.problem.barrier import BarrierOptions, embed_barrier
from workbench.problem.costs import Cost, quadratic_tracking
from workbench.problem.models import Model, double_integrator, single_integrator
from workbench.problem.obstacles import Circle, circle_margins, circles_from_arrays
from workbench.problem.problem import Problem

__all__ = ["BarrierOptions", "Circle", "Cost", "Model", "Problem", "circle_margins",
           "circles_from_arrays", "double_integrator", "embed_barrier", "quadratic_tracking",
           "single_integrator"]

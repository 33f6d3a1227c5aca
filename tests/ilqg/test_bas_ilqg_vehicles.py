"""BaS-iLQG on the vehicle models against IPOPT on the same barrier-embedded problem: a straight
reference through one obstacle, from the same initial guess."""

from __future__ import annotations

import numpy as np
import pytest

from workbench.ilqg import ILQGOptions, ilqg
from workbench.ilqg.bas import TrackingWeights, tracking_problem
from workbench.ilqg.oracle import solve_ipopt
from workbench.problem.barrier import BarrierOptions
from workbench.problem.obstacles import Circle
from workbench.problem.vehicles import (
    QUAD_HOVER_THRUST,
    kinematic_bicycle,
    planar_quadrotor,
    unicycle,
)

T = 100  # 2 s at dt = 0.02
# tight iLQG stopping rules, so both solvers stop at the same point to many digits
OPTIONS = ILQGOptions(tol_rel=1e-10, tol_grad=1e-7, max_iter=500)

CASES = {  # model, start, target, tracking weights, u_ref (None: 0)
    "unicycle": (lambda: unicycle(obstacles=(Circle((0.0, 0.1), 0.5),)),
                 (-1.5, 0.0, 0.0), (1.5, 0.0, 0.0),
                 dict(Q=(10, 10, 1), R=(1e-2, 1e-2), S=(1e3, 1e3, 10)), None),
    "bicycle": (lambda: kinematic_bicycle(obstacles=(Circle((0.0, 0.1), 0.5),)),
                (-1.5, 0.0, 0.0, 0.0), (1.5, 0.0, 0.0, 0.0),
                dict(Q=(10, 10, 1, 1), R=(1e-2, 1e-2), S=(1e3, 1e3, 10, 10)), None),
    # the obstacle sits below the reference (z = 1): both solvers pass above it
    "quadrotor": (lambda: planar_quadrotor(obstacles=(Circle((0.0, 0.92), 0.2),)),
                  (-0.5, 0.0, 1.0, 0.0, 0.0, 0.0), (0.5, 0.0, 1.0, 0.0, 0.0, 0.0),
                  dict(Q=(10, 1, 10, 1, 1, 0.1), R=(100, 100), S=(1e3, 100, 1e3, 100, 10, 1)),
                  QUAD_HOVER_THRUST),
}
RUNS = [("unicycle", 1e-2), ("unicycle", 1.0), ("bicycle", 1e-2), ("bicycle", 1.0),
        ("quadrotor", 1e-2)]


@pytest.mark.parametrize(("name", "q_beta"), RUNS)
def test_bas_ilqg_on_a_vehicle_is_safe_and_matches_ipopt(name, q_beta):
    make, x0, target, w, u_ref = CASES[name]
    model = make()
    problem = tracking_problem(model, TrackingWeights(**w, q_beta=q_beta),
                               barrier=BarrierOptions())
    x0, target = np.array(x0), np.array(target)
    ref = x0 + np.linspace(0.0, 1.0, T + 1)[:, None] * (target - x0)
    # the straight reference passes through the obstacle: the barrier keeps the solution safe
    assert min(model.margins(x)[0] for x in ref) < 0
    blocks = {"x_ref": ref, "beta_ref": problem.model.lift(target)[model.nx:]}
    U0 = np.zeros((T, model.nu))
    if u_ref is not None:
        blocks["u_ref"] = np.full(model.nu, u_ref)
        U0 += u_ref
    P = problem.cost.params(T, **blocks)
    res = ilqg(problem, x0, U0, P, OPTIONS)
    assert res.converged
    assert min(problem.model.margins(x).min() for x in res.X) > 0
    pos = list(model.position)
    assert np.linalg.norm(res.X[-1, pos] - target[pos]) < 0.1
    oracle = solve_ipopt(problem, x0, U0, P)
    assert oracle.success
    # measured: |J_ilqg - J_ipopt| / J_ipopt 9e-11 .. 6e-9 (both at the same local minimum)
    assert abs(res.cost - oracle.cost) / oracle.cost < 1e-7

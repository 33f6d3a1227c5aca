"""Your own CasADi model through BaS-iLQG and the sampler.

A unicycle (px, py, heading; controls speed and turn rate) must pass two circles to reach a
goal. 1) BaS-iLQG plans around them (barrier state embedded for you by ``bas_ilqg``).
2) BaS-MPPI drives it there in closed loop: the sampling costs are written in CasADi on the
barrier-embedded model (``SamplingProblem.from_costs``), the compiled sampler kernels are
generated from it and run on ``set_threads`` OpenMP threads.

    .venv/bin/python examples/own_model.py
"""

from __future__ import annotations

import casadi as ca
import numpy as np

import workbench as wb

DT = 0.05
OBSTACLES = (wb.Circle((2.0, 0.05), 0.6), wb.Circle((3.2, 1.2), 0.4))
START, GOAL = np.array([0.0, 0.0, 0.0]), np.array([4.5, 0.5, 0.0])


def unicycle() -> wb.Model:
    x = ca.SX.sym("x", 3)  # px, py, heading
    u = ca.SX.sym("u", 2)  # speed, turn rate
    x_next = x + DT * ca.vertcat(u[0] * ca.cos(x[2]), u[0] * ca.sin(x[2]), u[1])
    return wb.Model.from_expressions(
        "unicycle", x, u, x_next, dt=DT, u_min=[-2.0, -3.0], u_max=[2.0, 3.0],
        h=wb.circle_margins(x[:2], OBSTACLES), state_names=("px", "py", "theta"),
        control_names=("v", "omega"), position=(0, 1), obstacles=OBSTACLES)


def plan(model: wb.Model) -> dict:
    """BaS-iLQG along a straight (unsafe) reference from START to GOAL."""
    T = 80
    x_ref = np.linspace(START, GOAL, T + 1)
    weights = wb.TrackingWeights(Q=(5, 5, 0.1), R=(0.01, 0.01), S=(500, 500, 10), q_beta=0.01)
    result, _ = wb.bas_ilqg(model, x0=START, x_ref=x_ref, target=GOAL, weights=weights)
    return {"converged": bool(result.converged), "cost": float(result.cost),
            "min_h": float(min(model.margins(x[:3]).min() for x in result.X)),
            "final_error": float(np.linalg.norm(result.X[-1, :2] - GOAL[:2]))}


def sampling_problem(model: wb.Model) -> wb.SamplingProblem:
    """State costs in CasADi on the barrier-embedded model: q(x, p), phi(x, p), p = goal."""
    emb = wb.embed_barrier(model, wb.BarrierOptions())  # x = [px, py, theta, beta]; beta = sum 1/h
    x, g = emb.x, ca.SX.sym("goal", emb.nx)
    e = x[:2] - g[:2]
    q = 2.0 * ca.dot(e, e) + 0.01 * (x[3] - g[3]) ** 2  # distance + barrier state
    phi = 20.0 * ca.dot(e, e)
    return wb.SamplingProblem.from_costs(emb, q, phi, g, description="unicycle to a goal")


def drive(model: wb.Model, steps: int = 150, seed: int = 3) -> dict:
    wb.set_threads(2)  # every sampler library, loaded now or later
    sp = sampling_problem(model)
    config = wb.MPPIConfig(n_samples=256, horizon=40, sigma=(1.0, 1.5), lam=1.0)
    ctrl = wb.MPPI(sp, GOAL, config)
    ep = wb.closed_loop(ctrl, model, START, steps, np.random.default_rng(seed),
                        np.random.default_rng(seed + 1))
    return {"crashed": bool(ep.crashed), "min_h": float(ep.min_margin),
            "final_error": float(np.linalg.norm(ep.X[-1, :2] - GOAL[:2])),
            "compiled": ctrl.sampler.lib is not None,
            "median_step_ms": float(1e3 * np.median(ep.step_time_s))}


def main() -> dict:
    model = unicycle()
    out = {"bas_ilqg": plan(model), "bas_mppi": drive(model)}
    p, d = out["bas_ilqg"], out["bas_mppi"]
    print(f"BaS-iLQG: converged {p['converged']}, cost {p['cost']:.3f}, min h {p['min_h']:.3f}, "
          f"final error {p['final_error']:.3f} m")
    print(f"BaS-MPPI: crashed {d['crashed']}, min h {d['min_h']:.3f}, final error "
          f"{d['final_error']:.3f} m, compiled kernels {d['compiled']}, "
          f"{d['median_step_ms']:.2f} ms per step")
    return out


if __name__ == "__main__":
    main()

"""SA-RMPPI on a model of one's own: a kinematic bicycle with a disturbed speed.

A kinematic bicycle (px, py, heading, speed; controls acceleration and steering angle), written
with ``wb.Model.from_expressions``, must pass two circles to reach a goal while the plant's speed
is disturbed (``wb.Disturbance(level, states=("v",))``: a model of one's own names the states a
disturbance acts on). Four controllers drive it in closed loop with the same disturbance draws:

* BaS-iLQG: one open-loop plan (``wb.bas_ilqg``) played back on the disturbed plant;
* BaS-MPPI: MPPI on the barrier-embedded sampling problem;
* RMPPI: Robust MPPI with plain iLQG tracking gains (``wb.ILQGFeedback`` on the physical model);
* SA-RMPPI: Robust MPPI with K_safe (``wb.ILQGFeedback`` on the barrier-embedded model).

Both robust controllers take their selection threshold from ``wb.calibrate`` (one undisturbed,
seeded episode each, with their own feedback law). The last line printed is one JSON object:
per controller, crashed, final distance to the goal, the fraction of steps on which the nominal
state differed from the measured one (``nominal_differs``: the robust part acted) and the
fraction of steps whose feedback gains fell back to the previous ones (``ksafe_fallback``).

    .venv/bin/python examples/own_model_robust.py
"""

from __future__ import annotations

import json

import casadi as ca
import numpy as np

import workbench as wb

DT, WHEELBASE = 0.05, 0.5
OBSTACLES = (wb.Circle((2.0, 0.1), 0.5), wb.Circle((3.3, 1.1), 0.4))
START, GOAL = np.array([0.0, 0.0, 0.0, 0.0]), np.array([4.5, 0.5, 0.0, 0.0])
STEPS, VARIANCE = 150, 30.0  # 7.5 s; speed-disturbance variance (w = dt N(0, VARIANCE))
DISTURBANCE = wb.Disturbance(VARIANCE, states=("v",))
MPPI = wb.MPPIConfig(n_samples=256, horizon=40, sigma=(2.0, 0.4), lam=1.0)
RULE = wb.AlphaRule(kappa=0.1, calibration_steps=STEPS)


def bicycle() -> wb.Model:
    x = ca.SX.sym("x", 4)  # px, py, heading, speed
    u = ca.SX.sym("u", 2)  # acceleration, steering angle
    px, py, th, v = x[0], x[1], x[2], x[3]
    x_next = x + DT * ca.vertcat(v * ca.cos(th), v * ca.sin(th), v / WHEELBASE * ca.tan(u[1]),
                                 u[0])
    return wb.Model.from_expressions(
        "bicycle", x, u, x_next, dt=DT, u_min=[-3.0, -0.6], u_max=[3.0, 0.6],
        h=wb.circle_margins(ca.vertcat(px, py), OBSTACLES),
        state_names=("px", "py", "heading", "v"), control_names=("a", "delta"),
        position=(0, 1), obstacles=OBSTACLES)


def sampling_problem(model: wb.Model) -> wb.SamplingProblem:
    """Distance to the goal, speed at the end and the barrier state, on the embedded model."""
    emb = wb.embed_barrier(model, wb.BarrierOptions())  # x = [px, py, heading, v, beta]
    x, g = emb.x, ca.SX.sym("goal", emb.nx)
    e = x[:2] - g[:2]
    q = 2.0 * ca.dot(e, e) + 0.1 * x[3] ** 2 + 0.01 * (x[4] - g[4]) ** 2
    phi = 20.0 * ca.dot(e, e) + 2.0 * x[3] ** 2
    return wb.SamplingProblem.from_costs(emb, q, phi, g, description="bicycle to a goal")


class OpenLoop:
    """Plays back one control sequence (the BaS-iLQG plan), then holds zero."""

    def __init__(self, U: np.ndarray):
        self.U = np.asarray(U, float)

    def initial_state(self, x0):
        return 0

    def step(self, k, x, rng):
        u = self.U[k] if k < len(self.U) else np.zeros(self.U.shape[1])
        return k + 1, u, None


def bas_ilqg_plan(model: wb.Model) -> OpenLoop:
    x_ref = np.linspace(START, GOAL, STEPS + 1)
    weights = wb.TrackingWeights(Q=(5, 5, 0.1, 0.1), R=(0.1, 0.1), S=(500, 500, 10, 10),
                                 q_beta=0.01)
    result, _ = wb.bas_ilqg(model, x0=START, x_ref=x_ref, target=GOAL, weights=weights)
    return OpenLoop(result.U)


def controllers(model: wb.Model) -> dict:
    sp = sampling_problem(model)
    robust = wb.RMPPIConfig()
    fw = wb.FeedbackWeights.for_model(model, q=300.0)
    out = {"bas_ilqg": bas_ilqg_plan(model), "bas_mppi": wb.MPPI(sp, GOAL, MPPI)}
    for name, fb_model in (("rmppi", model), ("sa_rmppi", sp.model)):
        feedback = wb.ILQGFeedback(fb_model, MPPI.horizon, sp.nx, fw)  # plain iLQG / K_safe
        threshold = wb.calibrate(RULE, sp, GOAL, model, START, MPPI, feedback, robust, seed=0)
        out[name] = wb.RobustMPPI(sp, GOAL, MPPI, robust, feedback, threshold)
    return out


def run(ctrl, model: wb.Model, seed: int) -> dict:
    ep = wb.closed_loop(ctrl, model, START, STEPS, np.random.default_rng(seed),
                        np.random.default_rng(seed + 1), DISTURBANCE)
    robust = [i for i in ep.infos if hasattr(i, "nominal_differs")]  # RMPPIInfo
    return {"crashed": bool(ep.crashed), "steps": len(ep.U),
            "final_distance": round(float(np.linalg.norm(ep.X[-1, :2] - GOAL[:2])), 4),
            "nominal_differs": (round(float(np.mean([i.nominal_differs for i in robust])), 4)
                                if robust else None),
            "ksafe_fallback": (round(float(np.mean([i.ksafe_fallback is not None
                                                    for i in robust])), 4) if robust else None)}


def main(seed: int = 7) -> dict:
    wb.set_threads(2)
    model = bicycle()
    out = {name: run(ctrl, model, seed) for name, ctrl in controllers(model).items()}
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()

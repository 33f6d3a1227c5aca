"""pytorch_mppi (optional ``bench`` extra: torch, pytorch-mppi) on the same plain-MPPI problem as
our plain MPPI iteration: the navigation map (30 circles), planar double integrator, crash cost
only (no barrier state), N=1024, T=100, the same sigma, lambda, limits and costs, float64 on the
CPU with as many torch threads as our kernels use. One ``command()`` call (noise, rollouts,
costs, weights, update) against one kernel MPPI iteration (noise, rollouts, costs, weights,
update). Without torch the record says why it was skipped.
"""

from __future__ import annotations

import importlib.util
import statistics
import time

import numpy as np

from benchmarks.numpy_baseline import VectorisedNavigation
from benchmarks.sampling import _mppi_compiled, _record
from workbench.sampling.kernels.constants import SamplerConstants
from workbench.sampling.sampler import Sampler
from workbench.scenarios.navigation import navigation_setup

NAME = "mppi_plain_vs_pytorch_mppi_N1024_T100"


def _skipped(reason: str) -> dict:
    return {"name": NAME, "value": None, "unit": "ms", "baseline": "pytorch_mppi_command_ms",
            "baseline_value": None, "ratio": None, "skipped": reason,
            "params": {"install": "pip install -e '.[bench]'"}}


def _torch_problem(torch, nav: VectorisedNavigation, g: np.ndarray, crash_cost: float):
    """Dynamics and costs in torch on states [p, v, crashed] (the crash flag is sticky, as in
    our kernels), checked against the NumPy model at random states."""
    dt = nav.dt
    cx = torch.tensor(nav.cx[:, 0])
    cy = torch.tensor(nav.cy[:, 0])
    r2 = torch.tensor(nav.r2[:, 0])
    gt = torch.tensor(g[:4])
    Qp, Qv = torch.tensor(nav.Qp), torch.tensor(nav.Qv)
    S = torch.tensor(nav.S[:4])
    eps_h = nav.eps_h

    def dynamics(x, u):
        p = x[:, :2] + dt * x[:, 2:4]
        if nav.zoh:
            p = p + 0.5 * dt * dt * u
        v = x[:, 2:4] + dt * u
        h = (p[:, :1] - cx) ** 2 + (p[:, 1:2] - cy) ** 2 - r2
        crashed = torch.maximum(x[:, 4], (h <= eps_h).any(dim=1).to(x.dtype))
        return torch.cat([p, v, crashed[:, None]], dim=1)

    def running_cost(x, u):
        e = x[:, :2] - gt[:2]
        return (e * e) @ Qp + (x[:, 2:4] ** 2) @ Qv + crash_cost * x[:, 4]

    def terminal_cost(states, actions):
        e = states[..., -1, :4] - gt
        return (e * e) @ S

    rng = np.random.default_rng(0)
    X = np.column_stack([rng.uniform(0, 10, (64, 2)), rng.normal(0, 2, (64, 2))])
    V = rng.normal(0, 3, (64, 2))
    ours, crashed = nav.step(X.T.copy(), V.T.copy())
    theirs = dynamics(torch.tensor(np.column_stack([X, np.zeros(64)])), torch.tensor(V)).numpy()
    if not (np.allclose(theirs[:, :4], ours.T, rtol=1e-14, atol=1e-14)
            and np.array_equal(theirs[:, 4] > 0, crashed)
            and np.allclose(running_cost(torch.tensor(theirs), None).numpy(),
                            nav.q(ours, g) + crash_cost * crashed, rtol=1e-13)):
        raise AssertionError("torch twin of the navigation problem differs from NumPy")
    return dynamics, running_cost, terminal_cost


def record(repeats: int) -> dict:
    if importlib.util.find_spec("torch") is None or \
            importlib.util.find_spec("pytorch_mppi") is None:
        return _skipped("torch and pytorch-mppi are not installed (optional extra 'bench')")
    try:
        import torch
        from pytorch_mppi import MPPI
    except ImportError as exc:  # installed but broken (e.g. a missing shared library)
        return _skipped(f"torch / pytorch-mppi failed to import: {exc}")

    setup = navigation_setup()
    sp = setup.physical_problem()
    sampler = Sampler(sp, "compiled")
    threads = sampler.lib.cdll.wb_get_threads()
    torch.set_num_threads(threads)
    nav = VectorisedNavigation(sp)
    N, T = 1024, 100
    sigma = np.array(setup.mppi.sigma, float)
    crash_cost = 1e6
    g = np.asarray(setup.goal, float)
    c = SamplerConstants(sigma=sigma, lam=setup.mppi.lam, nu_mix=0.0, u_min=sp.model.u_min,
                         u_max=sp.model.u_max, crash_cost=crash_cost, p=g)
    dyn, cost, term = _torch_problem(torch, nav, g, crash_cost)
    torch.manual_seed(0)
    ctrl = MPPI(dyn, cost, 5, torch.diag(torch.tensor(sigma**2)), num_samples=N, horizon=T,
                device="cpu", terminal_state_cost=term, lambda_=setup.mppi.lam,
                u_min=torch.tensor(sp.model.u_min), u_max=torch.tensor(sp.model.u_max),
                U_init=torch.zeros((T, 2), dtype=torch.float64))
    x0 = torch.tensor([*setup.x0, 0.0], dtype=torch.float64)
    U = np.zeros((T, 2))
    x0_ours = sp.model.lift(setup.x0)
    ctrl.command(x0, shift_nominal_trajectory=False)
    _mppi_compiled(sampler, x0_ours, U, N, c, 0)
    t_ours, t_torch = [], []
    for i in range(max(repeats, 5)):
        t0 = time.perf_counter()
        _mppi_compiled(sampler, x0_ours, U, N, c, i)
        t_ours.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        ctrl.command(x0, shift_nominal_trajectory=False)
        t_torch.append(time.perf_counter() - t0)
    return _record(NAME, 1e3 * statistics.median(t_ours), "ms", "pytorch_mppi_command_ms",
                   1e3 * statistics.median(t_torch), {
                       "N": N, "T": T, "threads": threads, "torch": torch.__version__,
                       "pytorch_mppi": _version("pytorch-mppi"), "dtype": "float64",
                       "problem": "navigation map, double integrator, crash cost only",
                       "includes": "noise + rollouts + costs + weights + update (both)"})


def _version(dist: str) -> str:
    from importlib.metadata import version
    return version(dist)


def records(repeats: int) -> list[dict]:
    return [record(repeats)]

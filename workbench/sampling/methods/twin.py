"""The twin of the safe-MPPI kernel (:mod:`workbench.sampling.kernels.safe`):
:func:`safe_twin`, in plain NumPy, vectorised over samples, fed the same standard-normal noise.

The model (dynamics, margins), the state costs and the discrete CBF values and u-Jacobians
(:func:`workbench.problem.dcbf.discrete_cbf`) are evaluated by the CasADi virtual machine
mapped over samples (or the plain-NumPy navigation model,
:func:`~workbench.sampling.twin_model.model_twin`); the algorithm — clipping, choice of the
most restrictive constraint, the closed-form projection, the counts, the crash rule, the
likelihood ratio on the effective noise and the DCBF violation cost — is written here
independently of the generated step.

Twins follow one convention (:mod:`workbench.sampling.twin`): sample-major arrays, converted
from and to the kernels' lane-major layout at the sampler's boundary
(:class:`~workbench.sampling.methods.sampler.SafeSampler`).

Run-time fallback: :class:`~workbench.sampling.methods.sampler.SafeSampler` runs this twin when
it has no safe library (no C compiler, or the emitter cannot express an operation of the model:
one warning) or with ``backend="numpy"``.
"""

from __future__ import annotations

import numpy as np

from workbench.problem.dcbf import check_gamma, discrete_cbf
from workbench.problem.prediction import predicts, scene_at
from workbench.sampling.kernels.constants import SamplerConstants
from workbench.sampling.kernels.safe import INFEASIBLE_TOL
from workbench.sampling.problem import SamplingProblem
from workbench.sampling.twin_model import model_twin


class _CBF:
    """c (N, nh) and dc/du (N, nh, nu) of N samples, by the CasADi VM."""

    def __init__(self, sp: SamplingProblem, N: int, gamma: float, scene: np.ndarray):
        cbf = discrete_cbf(sp.model)
        self.nh, self.nu = cbf.nh, sp.nu
        self._c = cbf.c.map("dcbf", "serial", N, [2, 3], [])  # gamma and scene shared
        self._J = cbf.jacobian.map("dcbf_jac", "serial", N, [2, 3], [])
        self.gamma, self.scene = gamma, scene

    def c(self, X, V) -> np.ndarray:
        return np.asarray(self._c(X.T, V.T, self.gamma, self.scene)).T

    def jacobian(self, X, V) -> np.ndarray:
        # mapped (nh, nu) blocks side by side: (nh, N nu)
        J = np.asarray(self._J(X.T, V.T, self.gamma, self.scene))
        return J.reshape(self.nh, -1, self.nu).transpose(1, 0, 2)


def safe_twin(sp: SamplingProblem, X0, U, Z, c: SamplerConstants, project: bool,
              w_dcbf: float, gamma: float,
              model_backend: str = "auto") -> dict[str, np.ndarray]:
    """Safe-MPPI rollouts (see :mod:`workbench.sampling.kernels.safe`). X0 (N, nx), U (T, nu),
    Z (N, T, nu) standard normals. Returns S (N,), crashed (N,) bool, v (N, T, nu) applied
    controls, projected and infeasible (N,) step counts, dcbf (N,) violation sums and the
    trajectories X (N, T+1, nx)."""
    X0 = np.asarray(X0, float)
    gamma = check_gamma("gamma", gamma)
    N, T = Z.shape[0], Z.shape[1]
    scene = sp.model.scene_vector(c.scene if np.size(c.scene) else None)
    m = model_twin(sp, N, scene, model_backend)
    cbf = _CBF(sp, N, gamma, scene)
    inv = 1.0 / (c.sigma**2)
    half = 0.5 * c.lam * (1.0 - c.nu_mix)
    X = np.empty((N, T + 1, sp.nx))
    X[:, 0] = X0
    S, dcbf = np.zeros(N), np.zeros(N)
    projected, infeasible = np.zeros(N, int), np.zeros(N, int)
    crashed = np.zeros(N, bool)
    V = np.empty((N, T, sp.nu))
    rows = np.arange(N)
    for t in range(T):
        x, u = X[:, t], U[t]
        if predicts(sp.model):  # the kernel's rule: the constraints in x_t's scene, the step
            # and crash test in x_{t+1}'s
            cbf.scene = scene_at(sp.model, scene, t * sp.model.dt)
            m.at((t + 1) * sp.model.dt)
        v = np.clip(u + c.sigma * Z[:, t], c.u_min, c.u_max)
        acted = np.zeros(N, bool)
        if project:
            cv = cbf.c(x, v)
            i_star = np.argmin(cv, axis=1)
            c_star = cv[rows, i_star]
            g = cbf.jacobian(x, v)[rows, i_star]  # (N, nu)
            acted = c_star < 0
            gg = np.sum(g * g, axis=1)
            step = np.where(gg > 0, -c_star / np.where(gg > 0, gg, 1.0), 0.0)
            moved = np.clip(v + step[:, None] * g, c.u_min, c.u_max)
            v = np.where(acted[:, None], moved, v)
        c_hat = cbf.c(x, v)
        projected += acted
        infeasible += acted & (np.min(c_hat, axis=1) < -INFEASIBLE_TOL)
        viol = np.sum(np.maximum(0.0, -c_hat), axis=1)
        dcbf += viol
        eps = v - u  # the effective noise: clip and projection
        X[:, t + 1] = m.step(x, v)
        crashed |= m.crashed(X[:, t + 1], sp.eps_h)
        S += m.cost(m.q, X[:, t + 1], c.p) + c.crash_cost * crashed
        S += half * (u @ (inv * u) + 2.0 * (eps @ (inv * u)))
        S += w_dcbf * viol
        V[:, t] = v
    S += m.cost(m.phi, X[:, T], c.p)
    return {"S": S, "crashed": crashed, "v": V, "projected": projected,
            "infeasible": infeasible, "dcbf": dcbf, "X": X}

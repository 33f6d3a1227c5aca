"""The slow twin of the sampler kernels: MPPI rollouts, Algorithm 1 (SAIS) and the candidate
evaluation in plain NumPy, vectorised over samples, fed the same standard-normal noise.

The model (dynamics, margins) and the state costs are evaluated by the CasADi virtual machine;
the algorithm — clipping, feedback, crash rule, likelihood-ratio terms, the three SAIS costs —
is written here independently of the generated step functions. Noise is sample-major
(N, T, nu); it is the kernels' (T, nu, N) buffer transposed.
"""

from __future__ import annotations

import numpy as np

from workbench.sampling.kernels.constants import SamplerConstants
from workbench.sampling.numpy_model import numpy_navigation_twin
from workbench.sampling.problem import SamplingProblem


def model_twin(sp: SamplingProblem, N: int, scene, model_backend: str = "auto"):
    """Model evaluation for the twin in ``scene`` (empty: the model's own): plain NumPy for
    the built-in navigation problem (unless ``model_backend == "casadi"``), otherwise the CasADi
    virtual machine mapped over samples."""
    scene = sp.model.scene_vector(scene if np.size(scene) else None)
    if model_backend != "casadi" and sp.weights is not None:
        twin = numpy_navigation_twin(sp.model, sp.weights, sp.functions())
        if twin is not None:
            if sp.model.scene_capacity:  # else the twin holds the baked circles
                twin.set_scene(scene)
            return _NumpyModel(twin)
    return _CasadiModel(sp, N, scene)


class _CasadiModel:
    def __init__(self, sp: SamplingProblem, N: int, scene: np.ndarray):
        f = sp.functions()
        self.dyn = f["dyn"].map("dyn", "serial", N, [2], [])  # the scene is shared
        self.margins = (f["margins"].map("margins", "serial", N, [1], []) if sp.model.nh
                        else None)
        self.q, self.phi = f["q"].map(N), f["phi"].map(N)
        self.scene = scene

    def step(self, X, V):
        return np.asarray(self.dyn(X.T, V.T, self.scene)).T

    def crashed(self, X, eps_h):
        if self.margins is None:
            return np.zeros(X.shape[0], bool)
        return np.any(np.asarray(self.margins(X.T, self.scene)).T <= eps_h, axis=1)

    def cost(self, fn, X, p):
        return np.asarray(fn(X.T, p)).ravel()


class _NumpyModel:
    def __init__(self, twin):
        self.twin = twin
        self.q, self.phi = twin.q, twin.phi
        self.name = "numpy"

    def step(self, X, V):
        return self.twin.step(X, V)

    def crashed(self, X, eps_h):
        return self.twin.crashed(X, eps_h)

    def cost(self, fn, X, p):
        return fn(X, np.asarray(p, float))


def mppi_reference(sp: SamplingProblem, X0, U, Z, c: SamplerConstants,
                   model_backend: str = "auto", delay=None) -> dict[str, np.ndarray]:
    """MPPI rollouts (assumptions §8.1 + 4.6). X0 (N,nx), U (T,nu) or (N,T,nu) per-sample controls,
    Z (N,T,nu) standard normals, delay (N,) leading noise-free steps per sample.
    Returns S (N,), crashed (N,), v (N,T,nu), X (N,T+1,nx)."""
    X0 = np.asarray(X0, float)
    N, T = Z.shape[0], Z.shape[1]
    if delay is not None:
        Z = np.where(np.arange(T)[None, :, None] < np.asarray(delay)[:, None, None], 0.0, Z)
    Ub = np.broadcast_to(U, (N, T, sp.nu))
    m = model_twin(sp, N, c.scene, model_backend)
    inv = 1.0 / (c.sigma**2)
    half = 0.5 * c.lam * (1.0 - c.nu_mix)
    X = np.empty((N, T + 1, sp.nx))
    X[:, 0] = X0
    S = np.zeros(N)
    crashed = np.zeros(N, bool)
    V = np.empty((N, T, sp.nu))
    for t in range(T):
        u = Ub[:, t]
        v = np.clip(u + c.sigma * Z[:, t], c.u_min, c.u_max)
        eps = v - u
        X[:, t + 1] = m.step(X[:, t], v)
        crashed |= m.crashed(X[:, t + 1], sp.eps_h)
        S += m.cost(m.q, X[:, t + 1], c.p) + c.crash_cost * crashed
        S += half * (np.sum(u * inv * u, axis=1) + 2.0 * np.sum(u * inv * eps, axis=1))
        V[:, t] = v
    S += m.cost(m.phi, X[:, T], c.p)
    return {"S": S, "crashed": crashed, "v": V, "X": X}


def sais_reference(sp: SamplingProblem, X0, Xs0, U, K, Z, c: SamplerConstants,
                   model_backend: str = "auto", pure_costs: bool = False) -> dict[str, np.ndarray]:
    """Algorithm 1 (assumptions §10.1) with clip_in_cost: real samples with feedback
    K_k (x - x*), nominal samples without, the same noise for both. X0, Xs0 (N,nx) real and
    nominal starts, U (T,nu), K (T,nu,nx), Z (N,T,nu). Returns the three costs and the pieces
    they are made of and the
    trajectories X, X_nom (N,T+1,nx); with ``pure_costs`` also the pure state costs Sx_real,
    Sx_nom (Σq + φ without crash cost, assumptions §11.2 item 1)."""
    N, T = Z.shape[0], Z.shape[1]
    m = model_twin(sp, N, c.scene, model_backend)
    inv = 1.0 / (c.sigma**2)
    half = 0.5 * c.lam * (1.0 - c.nu_mix)
    X = np.empty((N, T + 1, sp.nx))
    Xs = np.empty((N, T + 1, sp.nx))
    X[:, 0], Xs[:, 0] = X0, Xs0
    S_state_nom, S_hat, S_real, LR, Sx_real, Sx_nom = (np.zeros(N) for _ in range(6))
    cr, cn = np.zeros(N, bool), np.zeros(N, bool)
    Vn, Vr = np.empty((N, T, sp.nu)), np.empty((N, T, sp.nu))
    for t in range(T):
        u = U[t]
        eps = c.sigma * Z[:, t]
        kfb = (X[:, t] - Xs[:, t]) @ K[t].T  # line 5: K_k (x - x*)
        vr = np.clip(u + eps + kfb, c.u_min, c.u_max)  # line 6
        vn = np.clip(u + eps, c.u_min, c.u_max)  # line 7
        eps_eff = vn - u if c.clip_in_cost else eps
        kfb_eff = vr - u - (vn - u) if c.clip_in_cost else kfb
        X[:, t + 1], Xs[:, t + 1] = m.step(X[:, t], vr), m.step(Xs[:, t], vn)
        cr |= m.crashed(X[:, t + 1], sp.eps_h)
        cn |= m.crashed(Xs[:, t + 1], sp.eps_h)
        q_r, q_n = m.cost(m.q, X[:, t + 1], c.p), m.cost(m.q, Xs[:, t + 1], c.p)
        Sx_real += q_r  # pure state costs (assumptions §11.2 item 1)
        Sx_nom += q_n
        qr = q_r + c.crash_cost * cr
        qn = q_n + c.crash_cost * cn
        S_hat += qr + half * np.sum(kfb_eff * inv * kfb_eff, axis=1)  # line 8
        S_state_nom += qn
        S_real += qr + half * np.sum((u + kfb_eff) * inv * (u + 2 * eps_eff + kfb_eff), axis=1)
        LR += half * (u @ (inv * u) + 2.0 * (eps_eff @ (inv * u)))  # line 12, one sum
        Vn[:, t], Vr[:, t] = vn, vr
    phi_r, phi_n = m.cost(m.phi, X[:, T], c.p), m.cost(m.phi, Xs[:, T], c.p)
    S_hat += phi_r
    S_state_nom += phi_n
    S_real += phi_r  # line 10
    Sx_real += phi_r
    Sx_nom += phi_n
    S_nom = 0.5 * S_state_nom + 0.5 * np.maximum(np.minimum(S_hat, c.alpha), S_state_nom) + LR
    out = {"S_nom": S_nom, "S_real": S_real, "S_state_nom": S_state_nom, "S_hat": S_hat,
           "LR": LR, "crashed_real": cr, "crashed_nom": cn, "v_nom": Vn, "v_real": Vr,
           "X": X, "X_nom": Xs}
    if pure_costs:
        out.update(Sx_real=Sx_real, Sx_nom=Sx_nom)
    return out

"""The twin of the sampler kernels (:mod:`workbench.sampling.kernels`): MPPI rollouts
(:func:`mppi_twin`, also the candidate evaluation with per-sample controls and delays) and
Algorithm 1 (:func:`sais_twin`) in plain NumPy, vectorised over samples, fed the same
standard-normal noise.

The model (dynamics, margins) and the state costs come from
:func:`~workbench.sampling.twin_model.model_twin` (plain NumPy for the built-in navigation
problem, else the CasADi virtual machine); the algorithm — clipping, feedback, crash rule,
likelihood-ratio terms, the three SAIS costs — is written here independently of the generated
step functions.

Twins (the same rules in every ``twin.py`` of the workbench): a twin is the plain NumPy
counterpart of a fast path, written independently of it, named ``<fast name>_twin`` and compared
with the fast path element by element at relative tolerance (``tests/test_twins.py``). Batch
layout: twins are sample-major — states (N, T+1, nx), noise and controls (N, T, nu), per-sample
results (N,) — while the kernels are lane-major — (T, nu, N). The conversion happens once, at
the sampler's boundary (:class:`~workbench.sampling.sampler.Sampler`,
:class:`~workbench.sampling.methods.sampler.SafeSampler`): a twin takes the kernels' noise
buffer transposed to (N, T, nu), and its controls v are transposed back to (T, nu, N) before the
batch is returned.

Run-time fallback: :class:`~workbench.sampling.sampler.Sampler` runs these twins when it has no
sampler library (no C compiler, or the emitter cannot express an operation of the model: one
warning) or with ``backend="numpy"``.
"""

from __future__ import annotations

import numpy as np

from workbench.sampling.kernels.constants import SamplerConstants
from workbench.sampling.problem import SamplingProblem
from workbench.sampling.twin_model import model_twin


def lane_major(a: np.ndarray) -> np.ndarray:
    """A twin's sample-major array (N, T, k) in the kernels' lane-major layout (T, k, N) (a
    view): the samplers' one conversion of a twin's result."""
    return np.transpose(a, (1, 2, 0))


def sample_major(a: np.ndarray) -> np.ndarray:
    """A kernel's lane-major array (T, k, N) in the twins' sample-major layout (N, T, k) (a
    view): how a twin is fed the kernels' noise buffer."""
    return np.transpose(a, (2, 0, 1))


def mppi_twin(sp: SamplingProblem, X0, U, Z, c: SamplerConstants,
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
        m.at((t + 1) * sp.model.dt)  # moving circles: the scene of x_{t+1}'s time
        X[:, t + 1] = m.step(X[:, t], v)
        crashed |= m.crashed(X[:, t + 1], sp.eps_h)
        S += m.cost(m.q, X[:, t + 1], c.p) + c.crash_cost * crashed
        S += half * (np.sum(u * inv * u, axis=1) + 2.0 * np.sum(u * inv * eps, axis=1))
        V[:, t] = v
    S += m.cost(m.phi, X[:, T], c.p)
    return {"S": S, "crashed": crashed, "v": V, "X": X}


def sais_twin(sp: SamplingProblem, X0, Xs0, U, K, Z, c: SamplerConstants,
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
        m.at((t + 1) * sp.model.dt)  # moving circles: the scene of x_{t+1}'s time
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

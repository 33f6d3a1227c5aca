"""A well-vectorised NumPy MPPI and SAIS iteration: the honest speed baseline of the kernels.

What a careful Python user writes: states lane-major (nx, N) so every row is contiguous,
vectorised over samples, one Python loop over time, the real and nominal SAIS rollouts
stacked into one (nx, 2N) array so each time step is one set of NumPy calls, the inverse
barrier over all obstacles as one (n_obstacles, 2N) array. It is not the exactness twin
(``workbench/sampling/twin.py``); it is checked equal to the kernels' results when fed the
kernels' noise (``tests/test_bench_baselines.py``, and by ``make bench`` before timing).

Scope: the built-in navigation problem (planar double integrator, Euler or ZOH, circular
obstacles, one summed inverse barrier state with gamma = 0 or no barrier state, SPEC 8.2 costs),
``clip_in_cost`` True (the default).
"""

from __future__ import annotations

import numpy as np

from workbench.sampling.kernels.constants import SamplerConstants
from workbench.sampling.problem import SamplingProblem
from workbench.sampling.twin_model import numpy_navigation_twin


class VectorisedNavigation:
    """Dynamics, crash test and costs on lane-major states X (nx, M), controls V (nu, M)."""

    def __init__(self, sp: SamplingProblem):
        twin = numpy_navigation_twin(sp.model, sp.weights, sp.functions())
        if twin is None:
            raise ValueError("VectorisedNavigation: not the built-in navigation problem")
        spec = sp.model.barrier
        if spec is not None:
            o = spec.options
            if o.kind != "inverse" or len(spec.groups) != 1 or o.gamma != 0.0:
                raise ValueError("VectorisedNavigation: one summed inverse barrier, gamma = 0")
            self.beta_max = o.beta_max
        self.barrier = spec is not None
        self.nx, self.nu = sp.nx, sp.nu
        self.dt, self.zoh = twin.dt, twin.zoh
        self.cx = twin.centers[:, 0:1].copy()
        self.cy = twin.centers[:, 1:2].copy()
        self.r2 = twin.radii2[:, None].copy()
        self.eps_h = sp.eps_h
        w = twin.w
        self.Qp, self.Qv = np.asarray(w["Qp"], float), np.asarray(w["Qv"], float)
        self.q_beta = float(w["q_beta"])
        self.S = np.asarray(w["S"], float)[: self.nx]

    def step(self, X, V) -> tuple[np.ndarray, np.ndarray]:
        """(X_next, crashed (M,)): one Euler/ZOH step and the crash test of the new state."""
        dt = self.dt
        out = np.empty_like(X)
        out[0] = X[0] + dt * X[2]
        out[1] = X[1] + dt * X[3]
        if self.zoh:
            out[0] += 0.5 * dt * dt * V[0]
            out[1] += 0.5 * dt * dt * V[1]
        out[2] = X[2] + dt * V[0]
        out[3] = X[3] + dt * V[1]
        h = out[0] - self.cx
        h *= h
        dy = out[1] - self.cy
        dy *= dy
        h += dy
        h -= self.r2
        crashed = (h <= self.eps_h).any(axis=0)
        if self.barrier:
            with np.errstate(divide="ignore"):
                np.reciprocal(h, out=h)
            beta = np.minimum(h.sum(axis=0), self.beta_max)
            beta[crashed] = self.beta_max
            out[4] = beta
        return out, crashed

    def q(self, X, g) -> np.ndarray:
        ex, ey = X[0] - g[0], X[1] - g[1]
        out = self.Qp[0] * ex * ex + self.Qp[1] * ey * ey
        out += self.Qv[0] * X[2] * X[2] + self.Qv[1] * X[3] * X[3]
        if self.barrier:
            eb = X[4] - g[4]
            out += self.q_beta * eb * eb
        return out

    def phi(self, X, g) -> np.ndarray:
        E = X - g[:, None]
        return self.S @ (E * E)


def mppi_baseline(nav: VectorisedNavigation, x0, U, Z, c: SamplerConstants) -> dict:
    """MPPI rollouts: Z (T, nu, N) standard normals (the kernels' layout). Returns S (N,),
    crashed (N,), v (T, nu, N)."""
    T, _, N = Z.shape
    sig = np.asarray(c.sigma, float)[:, None]
    inv = (1.0 / np.asarray(c.sigma, float) ** 2)[:, None]
    lo, hi = np.asarray(c.u_min, float)[:, None], np.asarray(c.u_max, float)[:, None]
    half = 0.5 * c.lam * (1.0 - c.nu_mix)
    g = np.asarray(c.p, float)
    X = np.repeat(np.asarray(x0, float)[:, None], N, axis=1)
    S = np.zeros(N)
    crashed = np.zeros(N, bool)
    Vs = np.empty(Z.shape)
    for t in range(T):
        u = U[t][:, None]
        v = np.clip(u + sig * Z[t], lo, hi)
        X, cr = nav.step(X, v)
        crashed |= cr
        S += nav.q(X, g) + c.crash_cost * crashed
        ui = u * inv
        S += half * ((u * ui).sum() + 2.0 * (ui * (v - u)).sum(axis=0))
        Vs[t] = v
    S += nav.phi(X, g)
    return {"S": S, "crashed": crashed, "v": Vs}


def sais_baseline(nav: VectorisedNavigation, x0, xs0, U, K, Z, c: SamplerConstants) -> dict:
    """Algorithm 1 (SPEC 10.1, clip_in_cost): Z (T, nu, N), K (T, nu, nx). Returns the three
    costs, the crash flags and the applied controls v_nom, v_real (T, nu, N)."""
    if not c.clip_in_cost:
        raise ValueError("sais_baseline implements clip_in_cost=True only")
    T, nu, N = Z.shape
    sig = np.asarray(c.sigma, float)[:, None]
    inv = (1.0 / np.asarray(c.sigma, float) ** 2)[:, None]
    lo, hi = np.asarray(c.u_min, float)[:, None], np.asarray(c.u_max, float)[:, None]
    half = 0.5 * c.lam * (1.0 - c.nu_mix)
    g = np.asarray(c.p, float)
    # real samples in columns [0, N), nominal samples in [N, 2N)
    X = np.hstack([np.repeat(np.asarray(x0, float)[:, None], N, axis=1),
                   np.repeat(np.asarray(xs0, float)[:, None], N, axis=1)])
    V = np.empty((nu, 2 * N))
    S_hat, S_state_nom, S_real, LR = (np.zeros(N) for _ in range(4))
    crashed = np.zeros(2 * N, bool)
    Vr, Vn = np.empty((T, nu, N)), np.empty((T, nu, N))
    for t in range(T):
        u = U[t][:, None]
        ue = u + sig * Z[t]
        vr = np.clip(ue + K[t] @ (X[:, :N] - X[:, N:]), lo, hi)
        vn = np.clip(ue, lo, hi)
        V[:, :N], V[:, N:] = vr, vn
        X, cr = nav.step(X, V)
        crashed |= cr
        q = nav.q(X, g) + c.crash_cost * crashed
        qr, qn = q[:N], q[N:]
        eps = vn - u  # clipped noise
        kfb = vr - u - eps  # clipped feedback
        ui = u * inv
        S_hat += qr + half * (inv * kfb * kfb).sum(axis=0)
        S_state_nom += qn
        S_real += qr + half * ((u + kfb) * inv * (u + 2 * eps + kfb)).sum(axis=0)
        LR += half * ((u * ui).sum() + 2.0 * (eps * ui).sum(axis=0))
        Vr[t], Vn[t] = vr, vn
    phi = nav.phi(X, g)
    S_hat += phi[:N]
    S_state_nom += phi[N:]
    S_real += phi[:N]
    S_nom = 0.5 * S_state_nom + 0.5 * np.maximum(np.minimum(S_hat, c.alpha), S_state_nom) + LR
    return {"S_nom": S_nom, "S_real": S_real, "S_state_nom": S_state_nom, "S_hat": S_hat,
            "LR": LR, "crashed_real": crashed[:N], "crashed_nom": crashed[N:], "v_nom": Vn,
            "v_real": Vr}

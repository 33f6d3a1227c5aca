/* iLQG passes in C (assumptions §5), compiled together with the CasADi-generated problem functions.
 *
 * Included after the generated code and a block of macros written by workbench/ilqg/compiled.py:
 *   NX NU NP NH              dimensions
 *   WB_SZ_ARG WB_SZ_RES WB_SZ_IW WB_SZ_W   shared work sizes (max over functions)
 *   WB_A_COLIND WB_A_ROW WB_B_COLIND WB_B_ROW   structural nonzeros of A and B (compressed
 *                            columns): the backward pass sums over them only
 * and the generated functions wb_dyn, wb_dyn_jac, wb_dyn_hess, wb_stage, wb_stage_quad, wb_term,
 * wb_term_quad, wb_margins, whose matrix outputs are row-major.
 *
 * All arrays are row-major, batch dimension first: X (T+1,NX), U (T,NU), P (T+1,NP),
 * A (T,NX,NX), B (T,NX,NU), lx (T+1,NX), lu (T,NU), lxx (T+1,NX,NX), luu (T,NU,NU),
 * lux (T,NU,NX), k (T,NU), K (T,NU,NX).
 * The Python twin in workbench/ilqg/reference.py implements the same passes in NumPy; the
 * two are compared in tests/ilqg/test_ilqg.py. Keep them in step.
 */
#include <math.h>
#include <stddef.h>
#include <string.h>

/* Full unrolling of the sparse products: after it, the pattern arrays are constants and the
 * loops straight-line code over the structural nonzeros only. */
#define WB_UNROLL _Pragma("GCC unroll 64")

typedef int (*wb_fn)(const casadi_real**, casadi_real**, casadi_int*, casadi_real*, int);

/* The scene (run-time obstacle data) every generated function takes as its fourth input. Set
 * by wb_set_scene before the passes run; per thread, so that two threads solving the same
 * problem in different scenes do not see each other's. */
static _Thread_local const double* wb_scene = 0;

void wb_set_scene(const double* scene) { wb_scene = scene; }

static int wb_call(wb_fn f, const double* i0, const double* i1, const double* i2,
                   double* o0, double* o1, double* o2, double* o3, double* o4, double* o5) {
  const casadi_real* arg[WB_SZ_ARG];
  casadi_real* res[WB_SZ_RES];
  casadi_int iw[WB_SZ_IW];
  casadi_real w[WB_SZ_W];
  arg[0] = i0; arg[1] = i1; arg[2] = i2; arg[3] = wb_scene;
  res[0] = o0; res[1] = o1; res[2] = o2; res[3] = o3; res[4] = o4; res[5] = o5;
  return f(arg, res, iw, w, 0);
}

static double clampd(double v, double lo, double hi) { return v < lo ? lo : (v > hi ? hi : v); }

/* Closed-loop forward pass: u = clip(ubar + alpha k + K (x - xbar)). Returns the cost,
 * including the crash penalty that wb_step adds (see reference.step_function). */
double wb_forward(int T, const double* x0, const double* X, const double* U, const double* k,
                  const double* K, const double* P, double alpha, const double* umin,
                  const double* umax, int use_policy, double* Xn, double* Un) {
  double J = 0.0, l;
  memcpy(Xn, x0, sizeof(double) * NX);
  for (int t = 0; t < T; ++t) {
    const double* x = Xn + (size_t)t * NX;
    double* u = Un + (size_t)t * NU;
    for (int i = 0; i < NU; ++i) {
      double v = U[t * NU + i];
      if (use_policy) {
        v += alpha * k[t * NU + i];
        const double* Ki = K + ((size_t)t * NU + i) * NX;
        const double* xb = X + (size_t)t * NX;
        for (int j = 0; j < NX; ++j) v += Ki[j] * (x[j] - xb[j]);
      }
      u[i] = clampd(v, umin[i], umax[i]);
    }
    wb_call(wb_step, x, u, P + (size_t)t * NP, Xn + (size_t)(t + 1) * NX, &l, 0, 0, 0, 0);
    J += l;
  }
  wb_call(wb_term, Xn + (size_t)T * NX, P + (size_t)T * NP, 0, &l, 0, 0, 0, 0, 0);
  return J + l;
}

/* Line search over the step sizes (assumptions §5.3): returns the index of the first accepted alpha
 * (z = actual / expected decrease > z_min, finite cost) or -1. out = (J_new, alpha, expected). */
int wb_line_search(int T, const double* x0, const double* X, const double* U, const double* k,
                   const double* K, const double* P, double J, const double* dV,
                   const double* alphas, int n_alpha, double z_min, const double* umin,
                   const double* umax, double* Xn, double* Un, double* out) {
  for (int i = 0; i < n_alpha; ++i) {
    double a = alphas[i];
    double Jn = wb_forward(T, x0, X, U, k, K, P, a, umin, umax, 1, Xn, Un);
    double expected = -a * (dV[0] + a * dV[1]);
    double dJ = J - Jn;
    double z = expected > 0 ? dJ / expected : (dJ > 0 ? 1.0 : (dJ < 0 ? -1.0 : 0.0));
    if (isfinite(Jn) && z > z_min) {
      out[0] = Jn; out[1] = a; out[2] = expected;
      return i;
    }
  }
  return -1;
}

/* Dynamics Jacobians and cost quadratisations along (X, U). */
void wb_derivatives(int T, const double* X, const double* U, const double* P, double* A,
                    double* B, double* lx, double* lu, double* lxx, double* luu, double* lux) {
  double l;
  for (int t = 0; t < T; ++t) {
    const double* x = X + (size_t)t * NX;
    const double* u = U + (size_t)t * NU;
    wb_call(wb_dyn_jac, x, u, 0, A + (size_t)t * NX * NX, B + (size_t)t * NX * NU, 0, 0, 0, 0);
    wb_call(wb_stage_quad, x, u, P + (size_t)t * NP, &l, lx + (size_t)t * NX, lu + (size_t)t * NU,
            lxx + (size_t)t * NX * NX, luu + (size_t)t * NU * NU, lux + (size_t)t * NU * NX);
  }
  wb_call(wb_term_quad, X + (size_t)T * NX, P + (size_t)T * NP, 0, &l, lx + (size_t)T * NX,
          lxx + (size_t)T * NX * NX, 0, 0, 0);
}

/* In-place Cholesky of the n x n leading block of a (row stride ld); 0 on success. */
static int chol(double* a, int n, int ld) {
  for (int j = 0; j < n; ++j) {
    double d = a[j * ld + j];
    for (int p = 0; p < j; ++p) d -= a[j * ld + p] * a[j * ld + p];
    if (!(d > 0.0)) return 1;
    d = sqrt(d);
    a[j * ld + j] = d;
    for (int i = j + 1; i < n; ++i) {
      double s = a[i * ld + j];
      for (int p = 0; p < j; ++p) s -= a[i * ld + p] * a[j * ld + p];
      a[i * ld + j] = s / d;
    }
  }
  return 0;
}

/* Solve (L L') y = b in place, L lower triangular n x n with stride ld. Inlined: the
 * backward pass calls it per column of K with n, ld known at compile time. */
static inline __attribute__((always_inline)) void chol_solve(const double* L, int n, int ld, double* b) {
  for (int i = 0; i < n; ++i) {
    double s = b[i];
    for (int p = 0; p < i; ++p) s -= L[i * ld + p] * b[p];
    b[i] = s / L[i * ld + i];
  }
  for (int i = n - 1; i >= 0; --i) {
    double s = b[i];
    for (int p = i + 1; p < n; ++p) s -= L[p * ld + i] * b[p];
    b[i] = s / L[i * ld + i];
  }
}

static double qval(const double* H, const double* g, const double* x, int n) {
  double v = 0.0;
  for (int i = 0; i < n; ++i) {
    double hx = 0.0;
    for (int j = 0; j < n; ++j) hx += H[i * n + j] * x[j];
    v += x[i] * g[i] + 0.5 * x[i] * hx;
  }
  return v;
}

/* Projected-Newton box QP (Tassa et al. 2014): min ½x'Hx + g'x, lo <= x <= hi.
 * On return x holds the solution, free[i] = 1 for free coordinates, L the Cholesky factor
 * of H restricted to the free set (packed, stride n, free coordinates in order), *nfree.
 * Result codes as in boxQP.m: -1 not PD, 0 no descent, 1 max iter, 2 max line search,
 * 4 small improvement, 5 small gradient, 6 all clamped. */
int wb_box_qp(int n, const double* H, const double* g, const double* lo, const double* hi,
              const double* x0, double* x, int* free, double* L, int* nfree) {
  enum { MAXN = 16 };
  int clamped[MAXN], old_clamped[MAXN], fi[MAXN];
  double grad[MAXN], gc[MAXN], search[MAXN], xc[MAXN], rhs[MAXN];
  const int max_iter = 100;
  const double min_grad = 1e-8, min_rel = 1e-8, step_dec = 0.6, min_step = 1e-22, armijo = 0.1;
  int result = 0, nf = n, iter;
  if (n > MAXN) return -2;
  for (int i = 0; i < n; ++i) {
    x[i] = clampd(isfinite(x0[i]) ? x0[i] : 0.0, lo[i], hi[i]);
    clamped[i] = 0;
    free[i] = 1;
  }
  double value = qval(H, g, x, n), oldvalue = 0.0;
  for (iter = 1; iter <= max_iter; ++iter) {
    if (iter > 1 && (oldvalue - value) < min_rel * fabs(oldvalue)) { result = 4; break; }
    oldvalue = value;
    for (int i = 0; i < n; ++i) {
      double s = g[i];
      for (int j = 0; j < n; ++j) s += H[i * n + j] * x[j];
      grad[i] = s;
    }
    int all = 1, changed = 0;
    for (int i = 0; i < n; ++i) {
      old_clamped[i] = clamped[i];
      clamped[i] = (x[i] == lo[i] && grad[i] > 0) || (x[i] == hi[i] && grad[i] < 0);
      all &= clamped[i];
      changed |= clamped[i] != old_clamped[i];
    }
    if (all) {
      result = 6;
      for (int i = 0; i < n; ++i) free[i] = 0;
      nf = 0;
      break;
    }
    if (iter == 1 || changed) {
      nf = 0;
      for (int i = 0; i < n; ++i) {
        free[i] = !clamped[i];
        if (free[i]) fi[nf++] = i;
      }
      for (int a = 0; a < nf; ++a)
        for (int b = 0; b < nf; ++b) L[a * n + b] = H[fi[a] * n + fi[b]];
      if (chol(L, nf, n)) { result = -1; break; }
    }
    double gnorm = 0.0;
    for (int i = 0; i < n; ++i) if (!clamped[i]) gnorm += grad[i] * grad[i];
    if (sqrt(gnorm) < min_grad) { result = 5; break; }
    for (int i = 0; i < n; ++i) {
      double s = g[i];
      for (int j = 0; j < n; ++j) if (clamped[j]) s += H[i * n + j] * x[j];
      gc[i] = s;
    }
    for (int a = 0; a < nf; ++a) rhs[a] = gc[fi[a]];
    chol_solve(L, nf, n, rhs);
    for (int i = 0; i < n; ++i) search[i] = 0.0;
    for (int a = 0; a < nf; ++a) search[fi[a]] = -rhs[a] - x[fi[a]];
    double sdotg = 0.0;
    for (int i = 0; i < n; ++i) sdotg += search[i] * grad[i];
    if (sdotg >= 0) break;
    double step = 1.0, vc;
    for (int i = 0; i < n; ++i) xc[i] = clampd(x[i] + step * search[i], lo[i], hi[i]);
    vc = qval(H, g, xc, n);
    while ((vc - oldvalue) / (step * sdotg) < armijo) {
      step *= step_dec;
      for (int i = 0; i < n; ++i) xc[i] = clampd(x[i] + step * search[i], lo[i], hi[i]);
      vc = qval(H, g, xc, n);
      if (step < min_step) { result = 2; break; }
    }
    for (int i = 0; i < n; ++i) x[i] = xc[i];
    value = vc;
    if (result) break;
  }
  if (iter > max_iter) result = 1;
  *nfree = nf;
  return result;
}

/* Backward pass. Returns 0 on success, t+1 if Quu (or the box QP) failed at step t.
 * reg: 0 = control-space (Quu + mu I), 1 = state-space (Vxx + mu I). boxed: use the box QP.
 * dV[0] = sum k'Qu, dV[1] = sum ½ k'Quu k.
 * second_order: full DDP, Qxx, Quu, Qux also get sum_i V'_x,i Hess F_i at (X[t], U[t])
 * (wb_dyn_hess with lam = the next value gradient); X is read only then. */
int wb_backward(int T, const double* A, const double* B, const double* lx, const double* lu,
                const double* lxx, const double* luu, const double* lux, const double* U,
                const double* umin, const double* umax, double mu, int reg, int boxed,
                double* k, double* K, double* dV, const double* X, int second_order) {
  double Vx[NX], Vxx[NX * NX], Qx[NX], Qu[NU], Qxx[NX * NX], Quu[NU * NU], Qux[NU * NX];
  double Quu_r[NU * NU], Qux_r[NU * NX], VA[NX * NX], VB[NX * NU], L[NU * NU];
  double lo[NU], hi[NU], warm[NU], kk[NU];
  int free[NU], fi[NU], nf;
  memcpy(Vx, lx + (size_t)T * NX, sizeof Vx);
  memcpy(Vxx, lxx + (size_t)T * NX * NX, sizeof Vxx);
  dV[0] = dV[1] = 0.0;
  for (int t = T - 1; t >= 0; --t) {
    const double* At = A + (size_t)t * NX * NX;
    const double* Bt = B + (size_t)t * NX * NU;
    /* VA = Vxx A, VB = Vxx B; every sum over p runs over the structural nonzeros of column
     * j of A (or B) in increasing p, which adds the same terms in the same order as the dense
     * sum without its exact zeros. */
    WB_UNROLL
    for (int j = 0; j < NX; ++j)
      WB_UNROLL
      for (int i = 0; i < NX; ++i) {
        double s = 0.0;
        WB_UNROLL
        for (int q = WB_A_COLIND[j]; q < WB_A_COLIND[j + 1]; ++q)
          s += Vxx[i * NX + WB_A_ROW[q]] * At[WB_A_ROW[q] * NX + j];
        VA[i * NX + j] = s;
      }
    WB_UNROLL
    for (int j = 0; j < NU; ++j)
      WB_UNROLL
      for (int i = 0; i < NX; ++i) {
        double s = 0.0;
        WB_UNROLL
        for (int q = WB_B_COLIND[j]; q < WB_B_COLIND[j + 1]; ++q)
          s += Vxx[i * NX + WB_B_ROW[q]] * Bt[WB_B_ROW[q] * NU + j];
        VB[i * NU + j] = s;
      }
    WB_UNROLL
    for (int i = 0; i < NX; ++i) {
      double s = lx[(size_t)t * NX + i];
      WB_UNROLL
      for (int q = WB_A_COLIND[i]; q < WB_A_COLIND[i + 1]; ++q)
        s += At[WB_A_ROW[q] * NX + i] * Vx[WB_A_ROW[q]];
      Qx[i] = s;
      WB_UNROLL
      for (int j = i; j < NX; ++j) { /* symmetric: upper triangle, mirrored below */
        double v = lxx[((size_t)t * NX + i) * NX + j];
        WB_UNROLL
        for (int q = WB_A_COLIND[i]; q < WB_A_COLIND[i + 1]; ++q)
          v += At[WB_A_ROW[q] * NX + i] * VA[WB_A_ROW[q] * NX + j];
        Qxx[i * NX + j] = Qxx[j * NX + i] = v;
      }
    }
    WB_UNROLL
    for (int i = 0; i < NU; ++i) {
      double s = lu[(size_t)t * NU + i];
      WB_UNROLL
      for (int q = WB_B_COLIND[i]; q < WB_B_COLIND[i + 1]; ++q)
        s += Bt[WB_B_ROW[q] * NU + i] * Vx[WB_B_ROW[q]];
      Qu[i] = s;
      WB_UNROLL
      for (int j = 0; j < NX; ++j) {
        double v = lux[((size_t)t * NU + i) * NX + j];
        WB_UNROLL
        for (int q = WB_B_COLIND[i]; q < WB_B_COLIND[i + 1]; ++q)
          v += Bt[WB_B_ROW[q] * NU + i] * VA[WB_B_ROW[q] * NX + j];
        Qux[i * NX + j] = v;
        Qux_r[i * NX + j] = v;
      }
      WB_UNROLL
      for (int j = 0; j < NU; ++j) {
        double v = luu[((size_t)t * NU + i) * NU + j];
        WB_UNROLL
        for (int q = WB_B_COLIND[i]; q < WB_B_COLIND[i + 1]; ++q)
          v += Bt[WB_B_ROW[q] * NU + i] * VB[WB_B_ROW[q] * NU + j];
        Quu[i * NU + j] = v;
        Quu_r[i * NU + j] = v;
      }
    }
    if (second_order) {
      double Hxx[NX * NX], Huu[NU * NU], Hux[NU * NX];
      wb_call(wb_dyn_hess, X + (size_t)t * NX, U + (size_t)t * NU, Vx, Hxx, Huu, Hux, 0, 0, 0);
      for (int i = 0; i < NX * NX; ++i) Qxx[i] += Hxx[i];
      for (int i = 0; i < NU * NU; ++i) { Quu[i] += Huu[i]; Quu_r[i] = Quu[i]; }
      for (int i = 0; i < NU * NX; ++i) { Qux[i] += Hux[i]; Qux_r[i] = Qux[i]; }
    }
    if (reg == 0) {
      for (int i = 0; i < NU; ++i) Quu_r[i * NU + i] += mu;
    } else {
      for (int i = 0; i < NU; ++i) {
        for (int j = 0; j < NU; ++j) {
          double s = 0.0;
          for (int p = 0; p < NX; ++p) s += Bt[p * NU + i] * Bt[p * NU + j];
          Quu_r[i * NU + j] += mu * s;
        }
        for (int j = 0; j < NX; ++j) {
          double s = 0.0;
          for (int p = 0; p < NX; ++p) s += Bt[p * NU + i] * At[p * NX + j];
          Qux_r[i * NX + j] += mu * s;
        }
      }
    }
    double* kt = k + (size_t)t * NU;
    double* Kt = K + (size_t)t * NU * NX;
    if (boxed) {
      for (int i = 0; i < NU; ++i) {
        lo[i] = umin[i] - U[t * NU + i];
        hi[i] = umax[i] - U[t * NU + i];
        warm[i] = (t == T - 1) ? 0.0 : k[(size_t)(t + 1) * NU + i];
      }
      int res = wb_box_qp(NU, Quu_r, Qu, lo, hi, warm, kk, free, L, &nf);
      if (res < 1) return t + 1;
      nf = 0;
      for (int i = 0; i < NU; ++i) if (free[i]) fi[nf++] = i;
    } else {
      memcpy(L, Quu_r, sizeof L);
      if (chol(L, NU, NU)) return t + 1;
      for (int i = 0; i < NU; ++i) kk[i] = -Qu[i];
      chol_solve(L, NU, NU, kk);
      nf = NU;
      for (int i = 0; i < NU; ++i) { free[i] = 1; fi[i] = i; }
    }
    memcpy(kt, kk, sizeof kk);
    for (int i = 0; i < NU * NX; ++i) Kt[i] = 0.0;
    for (int j = 0; j < NX; ++j) {
      double col[NU];
      for (int a = 0; a < nf; ++a) col[a] = -Qux_r[fi[a] * NX + j];
      chol_solve(L, nf, NU, col);
      for (int a = 0; a < nf; ++a) Kt[fi[a] * NX + j] = col[a];
    }
    /* dV and the value update with the unregularised Q terms. */
    double Quuk[NU];
    for (int i = 0; i < NU; ++i) {
      double s = 0.0;
      for (int j = 0; j < NU; ++j) s += Quu[i * NU + j] * kt[j];
      Quuk[i] = s;
    }
    for (int i = 0; i < NU; ++i) {
      dV[0] += kt[i] * Qu[i];
      dV[1] += 0.5 * kt[i] * Quuk[i];
    }
    double QuuK[NU * NX]; /* Quu K + Qux: V_xx = Qxx + K'(Quu K + Qux) + Qux' K */
    for (int i = 0; i < NU; ++i)
      for (int j = 0; j < NX; ++j) {
        double s = 0.0;
        for (int p = 0; p < NU; ++p) s += Quu[i * NU + p] * Kt[p * NX + j];
        QuuK[i * NX + j] = s + Qux[i * NX + j];
      }
    for (int i = 0; i < NX; ++i) {
      double s = Qx[i];
      for (int p = 0; p < NU; ++p)
        s += Kt[p * NX + i] * Quuk[p] + Kt[p * NX + i] * Qu[p] + Qux[p * NX + i] * kt[p];
      Vx[i] = s;
      for (int j = i; j < NX; ++j) { /* symmetric: upper triangle, mirrored below */
        double v = Qxx[i * NX + j];
        for (int p = 0; p < NU; ++p)
          v += Kt[p * NX + i] * QuuK[p * NX + j] + Qux[p * NX + i] * Kt[p * NX + j];
        Vxx[i * NX + j] = Vxx[j * NX + i] = v;
      }
    }
  }
  return 0;
}

/* The options of wb_solve, one entry per field: F(C type, name). The struct below, its
 * layout report and the ctypes mirror (compiled.SolveOptions, same names, same order) all
 * follow this list; tests compare the two layouts. */
#define WB_SOLVE_OPTIONS(F) \
  F(int, max_iter)        /* iteration limit (ILQGOptions.max_iter) */ \
  F(int, reg)             /* 0 control-space (Quu + mu I), 1 state-space regularisation */ \
  F(int, boxed)           /* 1: control limits through the box QP */ \
  F(int, second_order)    /* 1: full DDP (dynamics' Hessians in the backward pass) */ \
  F(int, gn_fallback)     /* 1 (second order only): an iteration whose second-order step */ \
                          /*   fails is redone as a Gauss-Newton one (ILQGOptions) */ \
  F(double, fallback_mu)  /*   fails: not positive definite for any mu <= fallback_mu */ \
  F(double, mu_init)      /* first regularisation */ \
  F(double, mu_factor)    /* its growth factor (> 1) */ \
  F(double, mu_min)       /* regularisation floor */ \
  F(double, mu_max)       /* regularisation limit: stop above it */ \
  F(double, z_min)        /* line search: least actual / expected decrease */ \
  F(double, tol_abs)      /* stop when the accepted decrease is <= max(tol_abs, */ \
  F(double, tol_rel)      /*   tol_rel |J|) */ \
  F(double, tol_grad)     /* stop when the mean relative gain is below it (and mu < 1e-5) */

typedef struct {
#define WB_FIELD(type, name) type name;
  WB_SOLVE_OPTIONS(WB_FIELD)
#undef WB_FIELD
} wb_solve_options;

/* The layout of wb_solve_options: out = [sizeof, then offset and size of each field in
 * order] (1 + 2 n entries, n = the number of fields, returned). *names: the field names,
 * space-separated. */
int wb_solve_options_layout(long long* out, const char** names) {
#define WB_NAME(type, name) #name " "
  static const char field_names[] = WB_SOLVE_OPTIONS(WB_NAME);
#undef WB_NAME
  int i = 0;
  out[i++] = (long long)sizeof(wb_solve_options);
#define WB_FIELD(type, name) \
  out[i++] = (long long)offsetof(wb_solve_options, name); \
  out[i++] = (long long)sizeof(((wb_solve_options*)0)->name);
  WB_SOLVE_OPTIONS(WB_FIELD)
#undef WB_FIELD
  *names = field_names;
  return (i - 1) / 2;
}

/* The outer loop of workbench/ilqg/solver.py (ilqg, python loop) in C, for small problems where
 * the Python loop costs more than the passes. Keep the two in step; tests compare them.
 * X, U hold the initial (accepted) rollout and are updated in place; *J its cost.
 * hist rows (max_iter, 8): cost, dJ, expected, alpha, mu, grad_norm, accepted, step (0
 * Gauss-Newton, 1 second order, 2 fallback: the second-order step failed and the iteration
 * was redone as a Gauss-Newton one).
 * out = [stop code (0 max_iter, 1 regularization_limit, 2 gradient, 3 cost_change,
 * 4 line_search_failed), converged, n_hist, final mu]. Work: derivative arrays (7, as
 * wb_derivatives), k2 (T,NU), K2 (T,NU,NX), Xn, Un, ls_out (3). */
void wb_solve(int T, const double* x0, double* X, double* U, double* J, const double* P,
              const double* umin, const double* umax, const wb_solve_options* opt,
              const double* alphas, int n_alpha, double* k, double* K, double* hist,
              double* out, double* A, double* B, double* lx, double* lu, double* lxx,
              double* luu, double* lux, double* k2, double* K2, double* Xn, double* Un,
              double* ls) {
  const int max_iter = opt->max_iter, reg = opt->reg, boxed = opt->boxed;
  const double f = opt->mu_factor, mu_min = opt->mu_min, mu_max = opt->mu_max;
  const double z_min = opt->z_min;
  const double tol_abs = opt->tol_abs, tol_rel = opt->tol_rel, tol_grad = opt->tol_grad;
  const int second_order = opt->second_order, gn_fallback = second_order && opt->gn_fallback;
  const double mu_cap = opt->fallback_mu < mu_max ? opt->fallback_mu : mu_max;
  double mu = opt->mu_init, delta = 1.0, dV[2];
  int d_valid = 0, stop = 0, converged = 0, n_hist = 0;
  for (int it = 1; it <= max_iter; ++it) {
    if (!d_valid) {
      wb_derivatives(T, X, U, P, A, B, lx, lu, lxx, luu, lux);
      d_valid = 1;
    }
    /* the second-order attempt, then (fallback) the Gauss-Newton one from mu0, delta0.
     * outcome: 0 line-searched, 1 not positive definite up to mu_cap (second order),
     * 2 regularisation limit, 3 small gradient */
    const double mu0 = mu, delta0 = delta;
    int second = second_order, outcome, acc = -1;
    double kind = second_order ? 1.0 : 0.0, g = 0.0;
    for (;;) {
      outcome = 0;
      for (;;) {
        if (wb_backward(T, A, B, lx, lu, lxx, luu, lux, U, umin, umax, mu, reg, boxed, k, K,
                        dV, X, second) == 0)
          break;
        delta = delta * f > f ? delta * f : f;
        mu = mu * delta > mu_min ? mu * delta : mu_min;
        if (second && gn_fallback && mu > mu_cap) { outcome = 1; break; }
        if (mu > mu_max) { outcome = 2; break; }
      }
      if (outcome == 0) {
        g = 0.0;
        for (int t = 0; t < T; ++t) {
          double m = 0.0;
          for (int i = 0; i < NU; ++i) {
            const double r = fabs(k[t * NU + i]) / (fabs(U[t * NU + i]) + 1.0);
            if (i == 0 || r > m) m = r;
          }
          g += m;
        }
        g /= T;
        if (g < tol_grad && mu < 1e-5)
          outcome = 3;
        else
          acc = wb_line_search(T, x0, X, U, k, K, P, *J, dV, alphas, n_alpha, z_min, umin, umax,
                               Xn, Un, ls);
      }
      if (outcome >= 2 || !(second && gn_fallback && (outcome == 1 || acc < 0))) break;
      second = 0; kind = 2.0; mu = mu0; delta = delta0;
    }
    if (outcome == 2) { stop = 1; break; }
    double* h = hist + (size_t)n_hist * 8;
    if (outcome == 3) {
      delta = delta / f < 1.0 / f ? delta / f : 1.0 / f;
      mu = mu * delta * (mu > mu_min ? 1.0 : 0.0);
      h[0] = *J; h[1] = h[2] = h[3] = 0.0; h[4] = mu; h[5] = g; h[6] = 0.0; h[7] = kind;
      ++n_hist;
      stop = 2; converged = 1;
      break;
    }
    if (acc >= 0) {
      const double dJ = *J - ls[0];
      delta = delta / f < 1.0 / f ? delta / f : 1.0 / f;
      mu = mu * delta * (mu > mu_min ? 1.0 : 0.0);
      memcpy(X, Xn, sizeof(double) * (size_t)(T + 1) * NX);
      memcpy(U, Un, sizeof(double) * (size_t)T * NU);
      *J = ls[0];
      d_valid = 0;
      h[0] = *J; h[1] = dJ; h[2] = ls[2]; h[3] = ls[1]; h[4] = mu; h[5] = g; h[6] = 1.0;
      h[7] = kind;
      ++n_hist;
      const double tol = tol_abs > tol_rel * fabs(*J) ? tol_abs : tol_rel * fabs(*J);
      if (dJ <= tol) { stop = 3; converged = 1; break; }
    } else {
      delta = delta * f > f ? delta * f : f;
      mu = mu * delta > mu_min ? mu * delta : mu_min;
      h[0] = *J; h[1] = h[2] = h[3] = 0.0; h[4] = mu; h[5] = g; h[6] = 0.0; h[7] = kind;
      ++n_hist;
      if (mu > mu_max) { stop = 4; break; }
    }
  }
  if (!d_valid) { /* gains about the returned trajectory (Gauss-Newton if second order fails) */
    wb_derivatives(T, X, U, P, A, B, lx, lu, lxx, luu, lux);
    int st = wb_backward(T, A, B, lx, lu, lxx, luu, lux, U, umin, umax, mu, reg, boxed, k2, K2,
                         dV, X, second_order);
    if (st != 0 && gn_fallback)
      st = wb_backward(T, A, B, lx, lu, lxx, luu, lux, U, umin, umax, mu, reg, boxed, k2, K2,
                       dV, X, 0);
    if (st == 0) {
      memcpy(k, k2, sizeof(double) * (size_t)T * NU);
      memcpy(K, K2, sizeof(double) * (size_t)T * NU * NX);
    }
  }
  out[0] = stop; out[1] = converged; out[2] = n_hist; out[3] = mu;
}

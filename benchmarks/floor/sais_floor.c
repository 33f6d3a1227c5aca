/* The hand-written floor of the sampler kernels: the SAIS dual rollout (Algorithm 1 with the
   clipped noise and feedback in the costs) and the MPPI rollout of the navigation problem,
   written as plain C loops the compiler vectorises across samples. The noise is an input array
   (no generation here). It is the speed record the generated kernels are compared with in
   `make bench`, and it is checked against the NumPy twin (tests/test_bench_floor.py).

   Problem: planar double integrator, Euler step dt, x = [px, py, vx, vy, beta] with one summed
   inverse barrier state over nc circles (margins h_i = |p - c_i|^2 - r_i^2 at the next state,
   summed pairwise as (h_a + h_b) / (h_a h_b), beta = beta_max when min h <= eps_bar, capped at
   beta_max), crash flag min h <= eps_h (sticky), stage cost
   q = Qp |p - g|^2 + Qv |v|^2 + q_beta (beta - g_beta)^2 + crash * crashed, terminal cost
   phi = sum_i S_i (x_i - g_i)^2, control box [u_min, u_max].

   Layouts (lane-major, every inner loop contiguous): Z, v_nom, v_real, v (T, 2, N); U (T, 2);
   K (T, 2, 5) row-major; scene (nc, 3) as (x, y, r); results (nr, N). N must be a multiple of
   FLOOR_LANES (the caller pads). Parameters prm[FLOOR_NPRM], see the P_* indices below.

   When the library's generator (workbench/sampling/kernels/rng.c, with WB_LANES = FLOOR_LANES)
   is compiled in front of this file, floor_sais_seeded draws the noise inside the rollout as the
   kernels do (the same draws for the same seed) and floor_normals draws it alone. */
#include <math.h>
#include <stddef.h>
#include <stdlib.h>
#ifdef _OPENMP
#include <omp.h>
#endif

#ifndef FLOOR_LANES
#define FLOOR_LANES 8 /* one AVX-512 register of doubles per block */
#endif
#define B FLOOR_LANES
#ifndef FLOOR_GROUP
#define FLOOR_GROUP 2 /* circles per division: 2 as the generated kernels, 4 fewer divisions */
#endif

enum {
  P_DT = 0, P_SIG0, P_SIG1, P_LR, P_UMIN0, P_UMIN1, P_UMAX0, P_UMAX1, P_CRASH,
  P_G0, P_G1, P_G2, P_G3, P_G4, P_QP0, P_QP1, P_QV0, P_QV1, P_QBETA,
  P_S0, P_S1, P_S2, P_S3, P_S4, P_ALPHA, P_EPS_H, P_BETA_MAX, P_EPS_BAR, FLOOR_NPRM
};

int floor_lanes(void) { return B; }
int floor_nprm(void) { return FLOOR_NPRM; }

void floor_set_threads(int n) {
#ifdef _OPENMP
  omp_set_num_threads(n);
#else
  (void)n;
#endif
}

int floor_get_threads(void) {
#ifdef _OPENMP
  return omp_get_max_threads();
#else
  return 1;
#endif
}

static inline double clampd(double v, double lo, double hi) {
  v = v > lo ? v : lo;
  return v < hi ? v : hi;
}

/* Circle data with r^2 precomputed once per call (the radii are run-time inputs). */
typedef struct { double* cx; double* cy; double* r2; } circles;

static circles circles_of(const double* scene, int nc) {
  circles c;
  c.cx = (double*)malloc(sizeof(double) * (size_t)(3 * nc + 1));
  c.cy = c.cx + nc;
  c.r2 = c.cy + nc;
  for (int j = 0; j < nc; ++j) {
    c.cx[j] = scene[3 * j];
    c.cy[j] = scene[3 * j + 1];
    c.r2[j] = scene[3 * j + 2] * scene[3 * j + 2];
  }
  return c;
}

/* Barrier states and crash margins of B positions: the circle loop outside, the lanes inside,
   so the lane loop vectorises and the accumulators stay in registers. */
static inline void barrier(const circles* c, int nc, const double* px, const double* py,
                           double eps_bar, double beta_max, double* beta, double* hmin_out) {
  double acc[B], hmin[B];
  for (int l = 0; l < B; ++l) { acc[l] = 0.0; hmin[l] = INFINITY; }
  int j = 0;
#if FLOOR_GROUP == 4
  /* four circles per division: (n1 d2 + n2 d1) / (d1 d2) with n = ha + hb, d = ha hb */
  for (; j + 3 < nc; j += 4) {
    const double cxa = c->cx[j], cya = c->cy[j], ra = c->r2[j];
    const double cxb = c->cx[j + 1], cyb = c->cy[j + 1], rb = c->r2[j + 1];
    const double cxc = c->cx[j + 2], cyc = c->cy[j + 2], rc = c->r2[j + 2];
    const double cxd = c->cx[j + 3], cyd = c->cy[j + 3], rd = c->r2[j + 3];
    #pragma omp simd
    for (int l = 0; l < B; ++l) {
      const double ax = px[l] - cxa, ay = py[l] - cya, bx = px[l] - cxb, by = py[l] - cyb;
      const double cx = px[l] - cxc, cy = py[l] - cyc, dx = px[l] - cxd, dy = py[l] - cyd;
      const double ha = (ax * ax + ay * ay) - ra, hb = (bx * bx + by * by) - rb;
      const double hc = (cx * cx + cy * cy) - rc, hd = (dx * dx + dy * dy) - rd;
      const double n1 = ha + hb, d1 = ha * hb, n2 = hc + hd, d2 = hc * hd;
      acc[l] += (n1 * d2 + n2 * d1) / (d1 * d2);
      const double m1 = ha < hb ? ha : hb, m2 = hc < hd ? hc : hd;
      const double m = m1 < m2 ? m1 : m2;
      hmin[l] = hmin[l] < m ? hmin[l] : m;
    }
  }
#endif
  for (; j + 1 < nc; j += 2) {
    const double cxa = c->cx[j], cya = c->cy[j], ra = c->r2[j];
    const double cxb = c->cx[j + 1], cyb = c->cy[j + 1], rb = c->r2[j + 1];
    #pragma omp simd
    for (int l = 0; l < B; ++l) {
      const double ax = px[l] - cxa, ay = py[l] - cya, bx = px[l] - cxb, by = py[l] - cyb;
      const double ha = (ax * ax + ay * ay) - ra, hb = (bx * bx + by * by) - rb;
      acc[l] += (ha + hb) / (ha * hb);
      const double m = ha < hb ? ha : hb;
      hmin[l] = hmin[l] < m ? hmin[l] : m;
    }
  }
  if (j < nc) {
    const double cxa = c->cx[j], cya = c->cy[j], ra = c->r2[j];
    #pragma omp simd
    for (int l = 0; l < B; ++l) {
      const double ax = px[l] - cxa, ay = py[l] - cya;
      const double ha = (ax * ax + ay * ay) - ra;
      acc[l] += 1.0 / ha;
      hmin[l] = hmin[l] < ha ? hmin[l] : ha;
    }
  }
  #pragma omp simd
  for (int l = 0; l < B; ++l) {
    const double capped = acc[l] < beta_max ? acc[l] : beta_max;
    beta[l] = hmin[l] <= eps_bar ? beta_max : capped;
    hmin_out[l] = hmin[l];
  }
}

static inline double stage(const double* p, double px, double py, double vx, double vy,
                           double bt) {
  const double ex = px - p[P_G0], ey = py - p[P_G1], eb = bt - p[P_G4];
  return p[P_QP0] * ex * ex + p[P_QP1] * ey * ey + p[P_QV0] * vx * vx + p[P_QV1] * vy * vy
      + p[P_QBETA] * eb * eb;
}

static inline double terminal(const double* p, double px, double py, double vx, double vy,
                              double bt) {
  const double e0 = px - p[P_G0], e1 = py - p[P_G1], e2 = vx - p[P_G2], e3 = vy - p[P_G3],
               e4 = bt - p[P_G4];
  return p[P_S0] * e0 * e0 + p[P_S1] * e1 * e1 + p[P_S2] * e2 * e2 + p[P_S3] * e3 * e3
      + p[P_S4] * e4 * e4;
}

/* SAIS: res rows S_nom, S_real, S_state_nom, S_hat, LR, crashed_real, crashed_nom. */
static inline void sais_impl(int N, int T, int nc, const double* prm, const double* scene,
                             const double* x0, const double* xs0, const double* U,
                             const double* K, const double* Z, double* v_nom, double* v_real,
                             double* res, int gen, unsigned long long seed) {
  (void)gen; (void)seed;
  const circles c = circles_of(scene, nc);
  const double dt = prm[P_DT], s0 = prm[P_SIG0], s1 = prm[P_SIG1];
  const double lo0 = prm[P_UMIN0], lo1 = prm[P_UMIN1], hi0 = prm[P_UMAX0], hi1 = prm[P_UMAX1];
  const double inv0 = 1.0 / (s0 * s0), inv1 = 1.0 / (s1 * s1), half = 0.5 * prm[P_LR];
  const double crash = prm[P_CRASH], eps_h = prm[P_EPS_H], eps_bar = prm[P_EPS_BAR],
               beta_max = prm[P_BETA_MAX], alpha = prm[P_ALPHA];
  const size_t NN = (size_t)N;
  #pragma omp parallel for schedule(static)
  for (int n0 = 0; n0 < N; n0 += B) {
    double px[B], py[B], vx[B], vy[B], bt[B];        /* real samples (with feedback) */
    double qx[B], qy[B], wx[B], wy[B], qb[B];        /* nominal samples */
    double Sn[B], Sh[B], Sr[B], LR[B], cr[B], cn[B];
    for (int l = 0; l < B; ++l) {
      px[l] = x0[0]; py[l] = x0[1]; vx[l] = x0[2]; vy[l] = x0[3]; bt[l] = x0[4];
      qx[l] = xs0[0]; qy[l] = xs0[1]; wx[l] = xs0[2]; wy[l] = xs0[3]; qb[l] = xs0[4];
      Sn[l] = Sh[l] = Sr[l] = LR[l] = cr[l] = cn[l] = 0.0;
    }
#ifdef WB_LANES
    wb_rng_block rng;
    if (gen) wb_block_seed(&rng, seed, (unsigned long long)n0);
#endif
    for (int t = 0; t < T; ++t) {
      const double u0 = U[2 * t], u1 = U[2 * t + 1];
      const double* k0 = K + (size_t)t * 10;
      const double* k1 = k0 + 5;
      const double* z0;
      const double* z1;
#ifdef WB_LANES
      double zb0[B], zb1[B];
      if (gen) {
        wb_block_normals(&rng, zb0);
        wb_block_normals(&rng, zb1);
        z0 = zb0;
        z1 = zb1;
      } else
#endif
      {
        z0 = Z + (2 * (size_t)t) * NN + n0;
        z1 = z0 + NN;
      }
      double* on0 = v_nom + (2 * (size_t)t) * NN + n0;
      double* on1 = on0 + NN;
      double* or0 = v_real + (2 * (size_t)t) * NN + n0;
      double* or1 = or0 + NN;
      const double lr_u = half * (u0 * inv0 * u0 + u1 * inv1 * u1);
      double et0[B], et1[B], kt0[B], kt1[B], hr[B], hn[B];
      #pragma omp simd
      for (int l = 0; l < B; ++l) {
        const double e0 = s0 * z0[l], e1 = s1 * z1[l];
        const double d0 = px[l] - qx[l], d1 = py[l] - qy[l], d2 = vx[l] - wx[l],
                     d3 = vy[l] - wy[l], d4 = bt[l] - qb[l];
        const double f0 = k0[0] * d0 + k0[1] * d1 + k0[2] * d2 + k0[3] * d3 + k0[4] * d4;
        const double f1 = k1[0] * d0 + k1[1] * d1 + k1[2] * d2 + k1[3] * d3 + k1[4] * d4;
        const double vr0 = clampd(u0 + e0 + f0, lo0, hi0), vr1 = clampd(u1 + e1 + f1, lo1, hi1);
        const double vn0 = clampd(u0 + e0, lo0, hi0), vn1 = clampd(u1 + e1, lo1, hi1);
        on0[l] = vn0; on1[l] = vn1; or0[l] = vr0; or1[l] = vr1;
        et0[l] = vn0 - u0; et1[l] = vn1 - u1;               /* clipped noise */
        kt0[l] = vr0 - u0 - et0[l]; kt1[l] = vr1 - u1 - et1[l]; /* clipped feedback */
        /* Euler steps of both systems */
        px[l] += dt * vx[l]; py[l] += dt * vy[l]; vx[l] += dt * vr0; vy[l] += dt * vr1;
        qx[l] += dt * wx[l]; qy[l] += dt * wy[l]; wx[l] += dt * vn0; wy[l] += dt * vn1;
      }
      /* barrier states and crash margins at the new positions */
      barrier(&c, nc, px, py, eps_bar, beta_max, bt, hr);
      barrier(&c, nc, qx, qy, eps_bar, beta_max, qb, hn);
      #pragma omp simd
      for (int l = 0; l < B; ++l) {
        cr[l] = (hr[l] <= eps_h || cr[l] > 0.0) ? 1.0 : 0.0;
        cn[l] = (hn[l] <= eps_h || cn[l] > 0.0) ? 1.0 : 0.0;
        const double qr = stage(prm, px[l], py[l], vx[l], vy[l], bt[l]) + crash * cr[l];
        const double qn = stage(prm, qx[l], qy[l], wx[l], wy[l], qb[l]) + crash * cn[l];
        const double a0 = kt0[l], a1 = kt1[l], b0 = et0[l], b1 = et1[l];
        Sh[l] += qr + half * (a0 * inv0 * a0 + a1 * inv1 * a1);
        Sn[l] += qn;
        Sr[l] += qr + half * ((u0 + a0) * inv0 * (u0 + 2.0 * b0 + a0)
                              + (u1 + a1) * inv1 * (u1 + 2.0 * b1 + a1));
        LR[l] += lr_u + half * 2.0 * (u0 * inv0 * b0 + u1 * inv1 * b1);
      }
    }
    for (int l = 0; l < B; ++l) {
      const double fr = terminal(prm, px[l], py[l], vx[l], vy[l], bt[l]);
      const double fn = terminal(prm, qx[l], qy[l], wx[l], wy[l], qb[l]);
      const double shf = Sh[l] + fr, snf = Sn[l] + fn;
      const double clamped = shf < alpha ? shf : alpha;
      const size_t n = (size_t)(n0 + l);
      res[0 * NN + n] = 0.5 * snf + 0.5 * (clamped > snf ? clamped : snf) + LR[l];
      res[1 * NN + n] = Sr[l] + fr;
      res[2 * NN + n] = snf;
      res[3 * NN + n] = shf;
      res[4 * NN + n] = LR[l];
      res[5 * NN + n] = cr[l];
      res[6 * NN + n] = cn[l];
    }
  }
  free(c.cx);
}

void floor_sais(int N, int T, int nc, const double* prm, const double* scene, const double* x0,
                const double* xs0, const double* U, const double* K, const double* Z,
                double* v_nom, double* v_real, double* res) {
  sais_impl(N, T, nc, prm, scene, x0, xs0, U, K, Z, v_nom, v_real, res, 0, 0);
}

#ifdef WB_LANES
#if WB_LANES != FLOOR_LANES
#error "the generator must use FLOOR_LANES lanes"
#endif
/* As floor_sais, the noise drawn in the rollout from seed (the kernels' draws). */
void floor_sais_seeded(int N, int T, int nc, const double* prm, const double* scene,
                       const double* x0, const double* xs0, const double* U, const double* K,
                       unsigned long long seed, double* v_nom, double* v_real, double* res) {
  sais_impl(N, T, nc, prm, scene, x0, xs0, U, K, NULL, v_nom, v_real, res, 1, seed);
}

/* The standard normals (T, m, N) of samples [0, N): the kernels' draws for seed. */
void floor_normals(int N, int T, int m, unsigned long long seed, double* out) {
  const size_t NN = (size_t)N;
  #pragma omp parallel for schedule(static)
  for (int n0 = 0; n0 < N; n0 += B) {
    wb_rng_block rng;
    wb_block_seed(&rng, seed, (unsigned long long)n0);
    double z[B];
    for (int t = 0; t < T; ++t)
      for (int j = 0; j < m; ++j) {
        wb_block_normals(&rng, z);
        for (int l = 0; l < B; ++l) out[((size_t)t * m + j) * NN + n0 + l] = z[l];
      }
  }
}
#endif

/* MPPI (BaS-MPPI on the same model): res rows S, crashed. */
void floor_mppi(int N, int T, int nc, const double* prm, const double* scene, const double* x0,
                const double* U, const double* Z, double* v, double* res) {
  const circles c = circles_of(scene, nc);
  const double dt = prm[P_DT], s0 = prm[P_SIG0], s1 = prm[P_SIG1];
  const double lo0 = prm[P_UMIN0], lo1 = prm[P_UMIN1], hi0 = prm[P_UMAX0], hi1 = prm[P_UMAX1];
  const double inv0 = 1.0 / (s0 * s0), inv1 = 1.0 / (s1 * s1), half = 0.5 * prm[P_LR];
  const double crash = prm[P_CRASH], eps_h = prm[P_EPS_H], eps_bar = prm[P_EPS_BAR],
               beta_max = prm[P_BETA_MAX];
  const size_t NN = (size_t)N;
  #pragma omp parallel for schedule(static)
  for (int n0 = 0; n0 < N; n0 += B) {
    double px[B], py[B], vx[B], vy[B], bt[B], S[B], cr[B];
    for (int l = 0; l < B; ++l) {
      px[l] = x0[0]; py[l] = x0[1]; vx[l] = x0[2]; vy[l] = x0[3]; bt[l] = x0[4];
      S[l] = cr[l] = 0.0;
    }
    for (int t = 0; t < T; ++t) {
      const double u0 = U[2 * t], u1 = U[2 * t + 1];
      const double* z0 = Z + (2 * (size_t)t) * NN + n0;
      const double* z1 = z0 + NN;
      double* o0 = v + (2 * (size_t)t) * NN + n0;
      double* o1 = o0 + NN;
      const double lr_u = half * (u0 * inv0 * u0 + u1 * inv1 * u1);
      double e0[B], e1[B], h[B];
      #pragma omp simd
      for (int l = 0; l < B; ++l) {
        const double v0 = clampd(u0 + s0 * z0[l], lo0, hi0);
        const double v1 = clampd(u1 + s1 * z1[l], lo1, hi1);
        o0[l] = v0; o1[l] = v1;
        e0[l] = v0 - u0; e1[l] = v1 - u1;
        px[l] += dt * vx[l]; py[l] += dt * vy[l]; vx[l] += dt * v0; vy[l] += dt * v1;
      }
      barrier(&c, nc, px, py, eps_bar, beta_max, bt, h);
      #pragma omp simd
      for (int l = 0; l < B; ++l) {
        cr[l] = (h[l] <= eps_h || cr[l] > 0.0) ? 1.0 : 0.0;
        S[l] += stage(prm, px[l], py[l], vx[l], vy[l], bt[l]) + crash * cr[l]
            + (lr_u + half * 2.0 * (u0 * inv0 * e0[l] + u1 * inv1 * e1[l]));
      }
    }
    for (int l = 0; l < B; ++l) {
      const size_t n = (size_t)(n0 + l);
      res[n] = S[l] + terminal(prm, px[l], py[l], vx[l], vy[l], bt[l]);
      res[NN + n] = cr[l];
    }
  }
  free(c.cx);
}

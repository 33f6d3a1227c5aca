/* Per-sample generator of the sampler kernels: counter-based SplitMix64 (Steele, Lea & Flood
   2014) and a ziggurat standard normal (Marsaglia & Tsang 2000, Doornik 2005 layout) with
   WB_ZIG_LAYERS layers. Draw number c of sample n (c = t m + j: the j-th of the m normals of
   step t) takes its 64 bits from mix(key_n + c G), key_n = mix(mix(seed + G) ^ n K) (G the
   golden-ratio increment): a function of (seed, n, c) only, never of the block width, the
   threads or the other samples. The few draws outside the ziggurat's rectangles (0.4% with 1024
   layers) take further bits from mix(key_n + (c + k 2^40) G), k = 1, 2, ...
   The including code defines wb_zig_x[WB_ZIG_LAYERS + 1], wb_zig_r[WB_ZIG_LAYERS],
   wb_zig_f[WB_ZIG_LAYERS + 1], WB_ZIG_R, WB_ZIG_LAYERS and WB_LANES first
   (workbench/sampling/kernels/emit.py: rng_source). */
#include <math.h>
#include <stdint.h>
#include <stddef.h>
#ifdef _OPENMP
#include <omp.h>
#endif
#define WB_ZIG_MASK ((uint64_t)(WB_ZIG_LAYERS - 1))
#define WB_GAMMA 0x9E3779B97F4A7C15ULL
#define WB_SLOW_STEP (((uint64_t)1 << 40) * WB_GAMMA)
static inline uint64_t wb_mix(uint64_t z) {
  z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ULL;
  z = (z ^ (z >> 27)) * 0x94D049BB133111EBULL;
  return z ^ (z >> 31);
}
static inline uint64_t wb_key(unsigned long long seed, unsigned long long n) {
  return wb_mix(wb_mix((uint64_t)seed + WB_GAMMA) ^ ((uint64_t)n * 0xD1B54A32D192ED03ULL));
}
/* uniform in [0, 1) from the top 53 bits */
static inline double wb_uniform(uint64_t bits) {
  return (double)(int64_t)(bits >> 11) * 0x1p-53;
}
/* the ziggurat's signed uniform in [-1, 1) from the top 53 bits (the layer takes the low bits) */
static inline double wb_signed(uint64_t bits) {
  return (double)(int64_t)(bits >> 11) * 0x1p-52 - 1.0;
}
/* A draw outside its layer's rectangle (x: the draw's counter state key + c G): the wedge test
   (one exp, the layers' edge densities tabulated), the tail beyond WB_ZIG_R (Marsaglia 1964)
   for the base layer, else a new draw; every further draw steps x by 2^40 G. */
static __attribute__((noinline)) double wb_normal_slow(uint64_t x, int i, double u) {
  for (;;) {
    if (fabs(u) < wb_zig_r[i]) return u * wb_zig_x[i];
    if (i == 0) {
      double xt, yt;
      do {
        x += WB_SLOW_STEP;
        xt = -log(1.0 - wb_uniform(wb_mix(x))) / WB_ZIG_R;
        x += WB_SLOW_STEP;
        yt = -log(1.0 - wb_uniform(wb_mix(x)));
      } while (yt + yt < xt * xt);
      return u < 0 ? -(WB_ZIG_R + xt) : WB_ZIG_R + xt;
    }
    const double xx = u * wb_zig_x[i];
    x += WB_SLOW_STEP;
    if (wb_zig_f[i + 1] + wb_uniform(wb_mix(x)) * (wb_zig_f[i] - wb_zig_f[i + 1])
        < exp(-0.5 * (xx * xx)))
      return xx;
    x += WB_SLOW_STEP;
    const uint64_t bits = wb_mix(x);
    i = (int)(bits & WB_ZIG_MASK);
    u = wb_signed(bits);
  }
}
/* One sample's generator: its key and the number of its next draw. */
typedef struct { uint64_t key, ctr; } wb_rng;
static inline void wb_rng_seed(wb_rng* r, unsigned long long seed, unsigned long long n) {
  r->key = wb_key(seed, n);
  r->ctr = 0;
}
static inline double wb_normal(wb_rng* r) {
  const uint64_t x = r->key + (r->ctr++) * WB_GAMMA, bits = wb_mix(x);
  const int i = (int)(bits & WB_ZIG_MASK);
  const double u = wb_signed(bits);
  if (__builtin_expect(fabs(u) < wb_zig_r[i], 1)) return u * wb_zig_x[i];
  return wb_normal_slow(x, i, u);
}
/* The generators of WB_LANES consecutive samples (their keys; one draw counter), so that the
   mixing and the rectangle test vectorise across samples. Each lane draws exactly what its own
   wb_normal would, so results never depend on blocking. */
typedef struct { uint64_t key[WB_LANES]; uint64_t ctr; } wb_rng_block;
static inline void wb_block_seed(wb_rng_block* b, unsigned long long seed, unsigned long long n0) {
  for (int l = 0; l < WB_LANES; ++l) b->key[l] = wb_key(seed, n0 + (unsigned long long)l);
  b->ctr = 0;
}
static inline void wb_block_fix(const wb_rng_block* b, uint64_t step, int l, double* z) {
  const uint64_t x = b->key[l] + step, bits = wb_mix(x);
  z[l] = wb_normal_slow(x, (int)(bits & WB_ZIG_MASK), wb_signed(bits));
}
#if defined(__AVX512F__) && defined(__AVX512DQ__) && WB_LANES % 8 == 0
#include <immintrin.h>
/* AVX-512: the same operations in intrinsics, eight lanes at a time, with the table look-ups
   as gathers (gcc's tuning for AMD targets splits them into scalar loads: measured 2x slower
   in the kernels). Results are bitwise those of the portable loop below. */
static inline __m512i wb_mix8(__m512i z) {
  z = _mm512_mullo_epi64(_mm512_xor_si512(z, _mm512_srli_epi64(z, 30)),
                         _mm512_set1_epi64((long long)0xBF58476D1CE4E5B9ULL));
  z = _mm512_mullo_epi64(_mm512_xor_si512(z, _mm512_srli_epi64(z, 27)),
                         _mm512_set1_epi64((long long)0x94D049BB133111EBULL));
  return _mm512_xor_si512(z, _mm512_srli_epi64(z, 31));
}
static inline void wb_block_normals(wb_rng_block* b, double* z) {
  const uint64_t step = (b->ctr++) * WB_GAMMA;
  __mmask8 ok[WB_LANES / 8];
  int miss = 0;
  for (int c = 0; c < WB_LANES / 8; ++c) {
    const __m512i bits = wb_mix8(_mm512_add_epi64(_mm512_loadu_si512(b->key + 8 * c),
                                                  _mm512_set1_epi64((long long)step)));
    const __m512i idx = _mm512_and_si512(bits, _mm512_set1_epi64((long long)WB_ZIG_MASK));
    const __m512d u = _mm512_sub_pd(
        _mm512_mul_pd(_mm512_cvtepi64_pd(_mm512_srli_epi64(bits, 11)), _mm512_set1_pd(0x1p-52)),
        _mm512_set1_pd(1.0));
    const __m512d x = _mm512_i64gather_pd(idx, wb_zig_x, 8);
    const __m512d r = _mm512_i64gather_pd(idx, wb_zig_r, 8);
    ok[c] = _mm512_cmp_pd_mask(_mm512_abs_pd(u), r, _CMP_LT_OQ);
    miss |= ok[c] != 0xFF;
    _mm512_storeu_pd(z + 8 * c, _mm512_mul_pd(u, x));
  }
  if (__builtin_expect(miss, 0))
    for (int l = 0; l < WB_LANES; ++l)
      if (!((ok[l / 8] >> (l % 8)) & 1)) wb_block_fix(b, step, l, z);
}
#else
static inline void wb_block_normals(wb_rng_block* b, double* z) {
  const uint64_t step = (b->ctr++) * WB_GAMMA;
  double u[WB_LANES], zr[WB_LANES];
  int miss = 0;
  #pragma omp simd reduction(|:miss)
  for (int l = 0; l < WB_LANES; ++l) {
    const uint64_t bits = wb_mix(b->key[l] + step);
    const int64_t i = (int64_t)(bits & WB_ZIG_MASK);
    u[l] = wb_signed(bits);
    z[l] = u[l] * wb_zig_x[i];
    zr[l] = wb_zig_r[i];
    miss |= !(fabs(u[l]) < zr[l]);
  }
  if (__builtin_expect(miss, 0))
    for (int l = 0; l < WB_LANES; ++l)
      if (!(fabs(u[l]) < zr[l])) wb_block_fix(b, step, l, z);
}
#endif
void wb_set_threads(int n) {
#ifdef _OPENMP
  omp_set_num_threads(n);
#else
  (void)n;
#endif
}
int wb_get_threads(void) {
#ifdef _OPENMP
  return omp_get_max_threads();
#else
  return 1;
#endif
}
/* Standard normals of the n samples idx[0..n) (sample indices of a batch) for T steps and m per
   step, written (T, m, n): the draws of those samples in a kernel with the same seed. */
void wb_normals_at(int n, const long long* idx, int T, int m, unsigned long long seed,
                   double* out) {
  for (int i = 0; i < n; ++i) {
    wb_rng r;
    wb_rng_seed(&r, seed, (unsigned long long)idx[i]);
    for (int t = 0; t < T; ++t)
      for (int j = 0; j < m; ++j) out[((size_t)t * m + j) * n + i] = wb_normal(&r);
  }
}
/* Standard normals of samples [0, N) for T steps and m per step, written (T, m, N): exactly
   the draws a kernel with the same seed generates (WB_LANES samples at a time, the rest one by
   one: the same numbers). */
void wb_normals(int N, int T, int m, unsigned long long seed, double* out) {
  const int nblk = N / WB_LANES;
  #pragma omp parallel for schedule(static)
  for (int b = 0; b < nblk; ++b) {
    const int n0 = b * WB_LANES;
    wb_rng_block rng;
    double z[WB_LANES];
    wb_block_seed(&rng, seed, (unsigned long long)n0);
    for (int t = 0; t < T; ++t)
      for (int j = 0; j < m; ++j) {
        wb_block_normals(&rng, z);
        for (int l = 0; l < WB_LANES; ++l) out[((size_t)t * m + j) * N + n0 + l] = z[l];
      }
  }
  for (int n = nblk * WB_LANES; n < N; ++n) {
    wb_rng r;
    wb_rng_seed(&r, seed, (unsigned long long)n);
    for (int t = 0; t < T; ++t)
      for (int j = 0; j < m; ++j) out[((size_t)t * m + j) * N + n] = wb_normal(&r);
  }
}

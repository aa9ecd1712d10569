// sc_selfcal.h -- the board's own calibration: a Gauss-Newton sphere fit from the 25 one-pass
// sums (ScSums), a coarse coverage mask and the held-out score. Shared by the sketch and the
// host test program (arduino/test_vectors/sc_vectors.cpp), which checks it against
// streamcal/fit/sphere_stream.py on the same sums. Single precision, no heap.
//
// The fit is the 4-parameter sphere model of sphere_stream.py: residual r = 1 - |u|^2/R^2,
// u = x - c, x in uT. With d = x - o (o the sums' origin) and c relative to o, r is linear in
// the augmented sample w = (d0, d1, d2, |d|^2, 1):
//   r = a.w,   a(c, R) = (2c/R^2, -1/R^2, 1 - |c|^2/R^2)
// so with the 5x5 moment matrix G = <w w'> (from the 25 sums, mean per sample):
//   cost = a'G a,   J'J = A'G A,   J'r = A'G a,   A = da/d(c, R) (5x4)
//   da/dc_j = 2/R^2 e_j - 2c_j/R^2 e_4,   da/dR = (-4c/R^3, 2/R^3, 2|c|^2/R^3)
// The start is the Kasa fit |d|^2 = 2 c.d + e: least squares of G's rows/columns 0,1,2,4
// against column 3 (the Gauss-Newton step with a_3 held, see sc_sphere_fit).
#ifndef SC_SELFCAL_H
#define SC_SELFCAL_H

#include "sc_protocol.h"

#define SC_NOINLINE __attribute__((noinline, unused))   // one copy: flash, not speed, is short

#ifndef SC_FIT_IDLE
#define SC_FIT_IDLE()   // the sketch keeps polling its sensors between iterations
#endif

#define SC_FIT_MAX_ITER 12
#define SC_FIT_STEP_TOL 1e-5f      // stop when the step is below this fraction of |p|
#define SC_MASK_CELLS 64           // 8 equal-area z bands x 8 sectors of 45 degrees
#define SC_MASK_NEED 56            // cells a window must reach before a fit (7/8 of the sphere)
#define SC_SCORE_CAP 0.0625f       // held-out loss per sample: min((|x|^2 - 1)^2, cap), cap = 0.25^2
#define SC_ACCEPT_LOSS 0.02f       // mean held-out loss a fit needs when no calibration is in force
                                   // (|x|^2 within ~14 %, |x| within ~7 % rms; garbage scores ~cap)

#ifdef __AVR__
#include <avr/pgmspace.h>
#else
#define PROGMEM
#define pgm_read_byte(p) (*(const uint8_t *)(p))
#endif

// For each of the 24 sums s1[3], s2[6], s3[9], s4[6] (their order in ScSums): the entry of G it
// adds to (bit 7: twice), the powers of scale_0 (low nibble) and scale_1 (high nibble), the power
// of scale_2. s1[j] -> G[j][4]; s2 (j, k) -> G[j][k]; s3[3k + j] = sum d_k^2 d_j -> G[j][3];
// s4 (j, k) = sum d_j^2 d_k^2 -> G[3][3], twice if j != k.
static const uint8_t sc_moment_map[72] PROGMEM = {
    0x04, 0x01, 0x00, 0x09, 0x10, 0x00, 0x0E, 0x00, 0x01, 0x00, 0x02, 0x00,
    0x01, 0x11, 0x00, 0x02, 0x01, 0x01, 0x06, 0x20, 0x00, 0x07, 0x10, 0x01,
    0x0C, 0x00, 0x02, 0x03, 0x03, 0x00, 0x08, 0x12, 0x00, 0x0D, 0x02, 0x01,
    0x03, 0x21, 0x00, 0x08, 0x30, 0x00, 0x0D, 0x20, 0x01, 0x03, 0x01, 0x02,
    0x08, 0x10, 0x02, 0x0D, 0x00, 0x03, 0x12, 0x04, 0x00, 0x92, 0x22, 0x00,
    0x92, 0x02, 0x02, 0x12, 0x40, 0x00, 0x92, 0x20, 0x02, 0x12, 0x00, 0x04};

// G = <w w'> (5x5, row-major), w = (d, |d|^2, 1) in uT about the sums' origin; `scale` uT per
// count per axis. Returns false if s.n < 4.
static SC_NOINLINE bool sc_moments(const ScSums &s, const float scale[3], float *G) {
  if (s.n < 4) return false;
  float inv = 1.0f / (float)s.n;
  memset(G, 0, 25 * sizeof(float));
  const int64_t *sum = s.s1;                   // s1, s2, s3, s4 lie one after another
  const uint8_t *e = sc_moment_map;
  for (uint8_t i = 0; i < 24; ++i, e += 3) {
    uint8_t g = pgm_read_byte(e), p01 = pgm_read_byte(e + 1);
    uint8_t pw[3] = {(uint8_t)(p01 & 15), (uint8_t)(p01 >> 4), pgm_read_byte(e + 2)};
    float f = (float)sum[i] * inv;
    if (g & 0x80) f += f;
    for (uint8_t j = 0; j < 3; ++j)
      for (uint8_t k = pw[j]; k; --k) f *= scale[j];
    G[g & 31] += f;
  }
  G[19] = G[0] + G[6] + G[12];                 // <|d|^2>
  G[24] = 1.0f;
  for (uint8_t i = 1; i < 5; ++i)
    for (uint8_t k = 0; k < i; ++k) G[5 * i + k] = G[5 * k + i];
  return true;
}

// Z[i zs + j] = sum_k X[i xr + k xc] Y[k yr + j yc], i < n, j < m, k < p (strides in floats; a
// stride 0 repeats a vector). Every product the fit needs is this one routine: less flash than
// each written out.
static SC_NOINLINE void sc_mm(const float *X, uint8_t xr, uint8_t xc, const float *Y, uint8_t yr, uint8_t yc,
                              float *Z, uint8_t zs, uint8_t n, uint8_t m, uint8_t p) {
  SC_FIT_IDLE();
  for (uint8_t i = 0; i < n; ++i)
    for (uint8_t j = 0; j < m; ++j) {
      float t = 0.0f;
      for (uint8_t k = 0; k < p; ++k) t += X[i * xr + k * xc] * Y[k * yr + j * yc];
      Z[i * zs + j] = t;
    }
}

// a'G a (the mean squared residual of a); v = G a.
static SC_NOINLINE float sc_quad(const float *G, const float a[5], float v[5]) {
  float q;
  sc_mm(G, 5, 1, a, 1, 0, v, 1, 5, 1, 5);
  sc_mm(a, 0, 1, v, 1, 0, &q, 1, 1, 1, 5);
  return q;
}

// Solve H x = h, H symmetric positive definite 4x4 (4 rows of 5 in a, h the last column), in place
// by elimination without pivoting (stable for such H); false if a pivot falls to 1e-6 of its
// diagonal entry before elimination or below (the samples do not fix the fit).
static SC_NOINLINE bool sc_solve4(float *a, float *x) {
  float d[4];
  for (uint8_t i = 0; i < 4; ++i) d[i] = a[6 * i];
  for (uint8_t c = 0; c < 4; ++c) {
    float *pc = a + 6 * c;
    if (!(*pc > 1e-6f * d[c])) return false;
    for (float *pr = pc + 5; pr < a + 20; pr += 5) {
      float f = *pr / *pc;
      for (uint8_t k = 0; k < 5 - c; ++k) pr[k] -= f * pc[k];
    }
  }
  for (int8_t r = 3; r >= 0; --r) {
    const float *pr = a + 5 * r;
    float v = pr[4];
    for (uint8_t k = r + 1; k < 4; ++k) v -= pr[k] * x[k];
    x[r] = v / pr[r];
  }
  return true;
}

// a_4 on the sphere manifold: 1 - |c|^2/R^2 = 1 + (a_0^2 + a_1^2 + a_2^2) / (4 a_3).
static SC_NOINLINE float sc_a4(const float a[5]) {
  return 1.0f + (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]) / (4.0f * a[3]);
}

// One Gauss-Newton step on a'G a for a = a(p), da/dp = A (5x4, row-major), linearised in a:
// H = A'G A, h = A'G a, a -= A H^-1 h. Returns |step|^2 / |a_0..3|^2, or -1 if H is singular.
static SC_NOINLINE float sc_gn_step(const float *G, float a[5], const float *A) {
  float B[20], H[20], v[5], step[4], n2 = 0.0f, p2 = 0.0f;
  sc_mm(G, 5, 1, A, 4, 1, B, 4, 5, 4, 5);        // B = G A
  sc_mm(A, 1, 4, B, 4, 1, H, 5, 4, 4, 5);        // H = A'B
  sc_mm(G, 5, 1, a, 1, 0, v, 1, 5, 1, 5);        // v = G a
  sc_mm(A, 1, 4, v, 1, 0, H + 4, 5, 4, 1, 5);    // h = A'v
  if (!sc_solve4(H, step)) return -1.0f;
  sc_mm(A, 4, 1, step, 1, 0, v, 1, 5, 1, 4);     // v = A step
  for (uint8_t l = 0; l < 5; ++l) a[l] -= v[l];
  for (uint8_t k = 0; k < 4; ++k) { n2 += step[k] * step[k]; p2 += a[k] * a[k]; }
  return n2 / p2;
}

// The fit's result: centre b (uT, sensor frame), radius R (uT), mean squared residual, iterations.
struct ScSphereFit { float b[3], R, cost; uint8_t iters; };

// Gauss-Newton sphere fit from the sums: the minimum of SphereStats.fit() in sphere_stream.py
// (same residual, same Kasa start). The Kasa fit is one (linear) step over a_0, a_1, a_2, a_4 with
// a_3 = -1 held, scaled to a_3 = -1/R^2; the sphere fit then steps in p = (a_0, a_1, a_2, a_3)
// with a_4 = sc_a4(p): A = [I; q'], q = (a_j / (2 a_3), -(a_4 - 1) / a_3). From the Kasa start
// the full steps converge (no step halving). max_iter 0: the Kasa fit alone. False if the samples
// do not determine a sphere.
static SC_NOINLINE bool sc_sphere_fit(const ScSums &s, const float scale[3], ScSphereFit &out,
                                      uint8_t max_iter = SC_FIT_MAX_ITER) {
  // Static, not on the stack (an AVR frame over 63 bytes costs 8 bytes of code per access), and
  // reached through a pointer the compiler cannot see through (2-byte indexed loads, not 4-byte
  // absolute ones).
  static float work[55];
  float *G = work;
  __asm__("" : "+r"(G));
  float *A = G + 25, *v = G + 45, *a = G + 50;
  if (!sc_moments(s, scale, G)) return false;
  memset(A, 0, 20 * sizeof(float));
  memset(a, 0, 5 * sizeof(float));
  a[3] = -1.0f;
  A[0] = A[5] = A[10] = A[19] = 1.0f;
  if (sc_gn_step(G, a, A) < 0.0f) return false;
  float r2 = a[4] - sc_a4(a) + 1.0f;           // x_3 + |c|^2, c = a_j / 2
  if (!(r2 > 0.0f)) return false;
  for (uint8_t j = 0; j < 4; ++j) a[j] /= r2;
  uint8_t it = 0;
  while (it < max_iter) {
    a[4] = sc_a4(a);
    A[15] = 1.0f;
    for (uint8_t j = 0; j < 3; ++j) A[16 + j] = a[j] / (2.0f * a[3]);
    A[19] = (1.0f - a[4]) / a[3];
    float rel = sc_gn_step(G, a, A);
    if (rel < 0.0f) return false;
    ++it;
    if (rel <= SC_FIT_STEP_TOL * SC_FIT_STEP_TOL) break;
  }
  if (!(a[3] < 0.0f)) return false;
  a[4] = sc_a4(a);
  out.cost = sc_quad(G, a, v);
  float R2 = -1.0f / a[3];
  for (uint8_t j = 0; j < 3; ++j) out.b[j] = 0.5f * a[j] * R2 + (float)s.center[j] * scale[j];
  out.R = sqrtf(R2);
  out.iters = it;
  return isfinite(out.R);
}

// Coverage cell (0..63) of the direction u = m - centre (uT): equal-area band of u_z/|u| (8 bands
// of 1/4 in z, Archimedes) times the 45-degree sector of (u_x, u_y).
static SC_NOINLINE uint8_t sc_cell(const float u[3]) {
  float r = sqrtf(u[0] * u[0] + u[1] * u[1] + u[2] * u[2]);
  int8_t band = (int8_t)((u[2] / r + 1.0f) * 4.0f);
  if (band < 0 || r == 0.0f) band = 0;
  if (band > 7) band = 7;
  uint8_t sec = (uint8_t)((u[0] < 0 ? 4 : 0) | (((u[0] < 0) != (u[1] < 0)) ? 2 : 0) |
                          (((fabsf(u[0]) < fabsf(u[1])) != ((u[0] < 0) != (u[1] < 0))) ? 1 : 0));
  return (uint8_t)(band * 8 + sec);
}

static SC_NOINLINE uint8_t sc_mask_count(const uint8_t mask[8]) {
  uint8_t n = 0;
  for (uint8_t i = 0; i < 8; ++i)
    for (uint8_t v = mask[i]; v; v &= (uint8_t)(v - 1)) ++n;
  return n;
}

// Held-out loss of one sample m (uT) under a calibration: min((|K^-1 (m - b)|^2 - 1)^2, cap).
static SC_NOINLINE float sc_score(const ScCal &c, const float m[3]) {
  float x[3];
  sc_cal_apply(c, m, x);
  float e = x[0] * x[0] + x[1] * x[1] + x[2] * x[2] - 1.0f;
  e *= e;
  return e < SC_SCORE_CAP ? e : SC_SCORE_CAP;
}

// A sphere as a calibration block: K = R I, b = centre (uT), CRC filled in.
static SC_NOINLINE void sc_cal_from_sphere(ScCal &c, uint16_t cal_id, const float b[3], float R) {
  memset(c.k, 0, sizeof c.k);
  c.cal_id = cal_id;
  c.k[0] = c.k[3] = c.k[5] = R;
  memcpy(c.b, b, sizeof c.b);
  c.crc = sc_cal_crc(c);
}

#endif  // SC_SELFCAL_H

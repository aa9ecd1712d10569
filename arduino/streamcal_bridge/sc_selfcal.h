// sc_selfcal.h -- the board's own calibration: a Gauss-Newton sphere fit from the 25 one-pass
// sums (ScSums), a coarse coverage mask and the held-out score. Shared by the sketch and the
// host test program (arduino/test_vectors/sc_vectors.cpp), which checks it against
// streamcal/fit/sphere_stream.py on the same sums. Single precision, no heap.
//
// The fit is the 4-parameter sphere model of sphere_stream.py: residual r = 1 - |u|^2/R^2,
// u = x - c, x in uT. Every entry of J'J and J'r at (c, R) needs only these centred means:
//   M1 = <u>, M2 = <u u'>, T = <|u|^2 u>, Q = <|u|^4>
// and they follow from seven raw means about the sums' origin o (x = o + d):
//   m1 = <d>, S2 = <d d'>, P = <|d|^2 d>, D2 = <|d|^2>, D4 = <|d|^4>
// by expanding |u|^2 = |d|^2 - 2 c.d + |c|^2 with c relative to o:
//   M1 = m1 - c
//   M2 = S2 - c m1' - m1 c' + c c'
//   T  = P - 2 S2 c + |c|^2 m1 - D2 c + 2 (c.m1) c - |c|^2 c
//   Q  = D4 + 4 c'S2 c + |c|^4 - 4 c.P + 2 |c|^2 D2 - 4 |c|^2 (c.m1)
// Then, per sample (the 1/n cancels in the step):
//   J'J = [ 4/R^4 M2     4/R^5 T  ]     J'r = [ 2/R^2 (M1 - T/R^2)   ]
//         [ 4/R^5 T'     4/R^6 Q  ]           [ 2/R^3 (trM2 - Q/R^2) ]
//   cost = 1 - 2 trM2/R^2 + Q/R^4
// The start is the Kasa fit |x|^2 = 2 c.x + e on the same means.
#ifndef SC_SELFCAL_H
#define SC_SELFCAL_H

#include "sc_protocol.h"

#ifndef SC_FIT_IDLE
#define SC_FIT_IDLE()   // the sketch keeps polling its sensors between iterations
#endif

#define SC_FIT_MAX_ITER 12
#define SC_FIT_STEP_TOL 1e-5f      // stop when the step is below this fraction of R
#define SC_MASK_CELLS 64           // 8 equal-area z bands x 8 sectors of 45 degrees
#define SC_MASK_NEED 56            // cells a window must reach before a fit (7/8 of the sphere)
#define SC_SCORE_CAP 0.0625f       // held-out loss per sample: min((|x|^2 - 1)^2, cap), cap = 0.25^2

// Seven means about the sums' origin, uT (see above).
struct ScMoments { float m1[3], s2[6], p[3], d2, d4; };
static const uint8_t sc_pj[6] = {0, 0, 0, 1, 1, 2}, sc_pk[6] = {0, 1, 2, 1, 2, 2};

static inline uint8_t sc_pair(uint8_t j, uint8_t k) {
  if (j > k) { uint8_t t = j; j = k; k = t; }
  return (uint8_t)(j == 0 ? k : j + k + 1);      // index into the 6 symmetric entries
}

// Raw count sums -> means in uT; `scale` uT per count per axis. Returns false if s.n < 4.
static inline bool sc_moments(const ScSums &s, const float scale[3], ScMoments &m) {
  if (s.n < 4) return false;
  float inv = 1.0f / (float)s.n;
  m.d2 = m.d4 = 0.0f;
  for (uint8_t j = 0; j < 3; ++j) {
    m.m1[j] = (float)s.s1[j] * scale[j] * inv;
    float pj = 0.0f;
    for (uint8_t k = 0; k < 3; ++k) pj += (float)s.s3[3 * k + j] * scale[k] * scale[k];
    m.p[j] = pj * scale[j] * inv;
  }
  for (uint8_t q = 0; q < 6; ++q) {
    float sj = scale[sc_pj[q]], sk = scale[sc_pk[q]];
    m.s2[q] = (float)s.s2[q] * sj * sk * inv;
    float w = (sc_pj[q] == sc_pk[q]) ? 1.0f : 2.0f;
    m.d4 += w * (float)s.s4[q] * sj * sj * sk * sk * inv;
    if (w == 1.0f) m.d2 += m.s2[q];
  }
  return true;
}

// Solve the 4x4 system a x = a[.][4] in place (Gaussian elimination, partial pivoting); false if a
// pivot is below 1e-6 of the largest diagonal entry (the samples do not fix the fit).
static inline bool sc_solve4(float a[4][5], float x[4]) {
  float big = 0.0f;
  for (uint8_t i = 0; i < 4; ++i) big = fmaxf(big, fabsf(a[i][i]));
  for (uint8_t c = 0; c < 4; ++c) {
    uint8_t p = c;
    for (uint8_t r = c + 1; r < 4; ++r) if (fabsf(a[r][c]) > fabsf(a[p][c])) p = r;
    if (!(fabsf(a[p][c]) > 1e-6f * big)) return false;
    for (uint8_t k = 0; k < 5; ++k) { float t = a[c][k]; a[c][k] = a[p][k]; a[p][k] = t; }
    for (uint8_t r = c + 1; r < 4; ++r) {
      float f = a[r][c] / a[c][c];
      for (uint8_t k = c; k < 5; ++k) a[r][k] -= f * a[c][k];
    }
  }
  for (int8_t r = 3; r >= 0; --r) {
    float v = a[r][4];
    for (uint8_t k = r + 1; k < 4; ++k) v -= a[r][k] * x[k];
    x[r] = v / a[r][r];
  }
  return true;
}

// Kasa start: centre c (relative to the origin) and R; false if undetermined.
static inline bool sc_kasa(const ScMoments &m, float c[3], float &R) {
  float a[4][5], x[4];
  for (uint8_t j = 0; j < 3; ++j) {
    for (uint8_t k = 0; k < 3; ++k) a[j][k] = 4.0f * m.s2[sc_pair(j, k)];
    a[j][3] = a[3][j] = 2.0f * m.m1[j];
    a[j][4] = 2.0f * m.p[j];
  }
  a[3][3] = 1.0f;
  a[3][4] = m.d2;
  if (!sc_solve4(a, x)) return false;
  float r2 = x[3] + x[0] * x[0] + x[1] * x[1] + x[2] * x[2];
  if (!(r2 > 0.0f)) return false;
  for (uint8_t j = 0; j < 3; ++j) c[j] = x[j];
  R = sqrtf(r2);
  return true;
}

// Centred means at c (relative to the origin): m2 (6), t (3), trM2 and Q.
static inline void sc_centred(const ScMoments &m, const float c[3], float m2[6], float t[3],
                              float &tr, float &q) {
  float cc = 0.0f, cm = 0.0f, cp = 0.0f, cs2c = 0.0f, s2c[3];
  for (uint8_t j = 0; j < 3; ++j) {
    s2c[j] = 0.0f;
    for (uint8_t k = 0; k < 3; ++k) s2c[j] += m.s2[sc_pair(j, k)] * c[k];
    cc += c[j] * c[j]; cm += c[j] * m.m1[j]; cp += c[j] * m.p[j];
  }
  for (uint8_t j = 0; j < 3; ++j) cs2c += c[j] * s2c[j];
  for (uint8_t p = 0; p < 6; ++p) {
    uint8_t j = sc_pj[p], k = sc_pk[p];
    m2[p] = m.s2[p] - c[j] * m.m1[k] - m.m1[j] * c[k] + c[j] * c[k];
  }
  for (uint8_t j = 0; j < 3; ++j)
    t[j] = m.p[j] - 2.0f * s2c[j] + cc * m.m1[j] - m.d2 * c[j] + 2.0f * cm * c[j] - cc * c[j];
  tr = m.d2 - 2.0f * cm + cc;
  q = m.d4 + 4.0f * cs2c + cc * cc - 4.0f * cp + 2.0f * cc * m.d2 - 4.0f * cc * cm;
}

static inline float sc_sphere_cost(const ScMoments &m, const float c[3], float R) {
  float m2[6], t[3], tr, q, a = 1.0f / (R * R);
  sc_centred(m, c, m2, t, tr, q);
  return 1.0f - 2.0f * tr * a + q * a * a;
}

// The fit's result: centre b (uT, sensor frame), radius R (uT), mean squared residual, iterations.
struct ScSphereFit { float b[3], R, cost; uint8_t iters; };

// Gauss-Newton sphere fit from the sums, as SphereStats.fit() in sphere_stream.py (same start,
// same step halving); false if the samples do not determine a sphere.
static inline bool sc_sphere_fit(const ScSums &s, const float scale[3], ScSphereFit &out) {
  ScMoments m;
  float c[3], R;
  if (!sc_moments(s, scale, m) || !sc_kasa(m, c, R)) return false;
  float cost = sc_sphere_cost(m, c, R);
  uint8_t it = 0;
  for (; it < SC_FIT_MAX_ITER; ++it) {
    SC_FIT_IDLE();
    float m2[6], t[3], tr, q, a[4][5], step[4];
    sc_centred(m, c, m2, t, tr, q);
    float i2 = 1.0f / (R * R), i3 = i2 / R;
    for (uint8_t j = 0; j < 3; ++j) {
      for (uint8_t k = 0; k < 3; ++k) a[j][k] = 4.0f * i2 * i2 * m2[sc_pair(j, k)];
      a[j][3] = a[3][j] = 4.0f * i2 * i3 * t[j];
      a[j][4] = -2.0f * i2 * (m.m1[j] - c[j] - t[j] * i2);
    }
    a[3][3] = 4.0f * i3 * i3 * q;
    a[3][4] = -2.0f * i3 * (tr - q * i2);
    if (!sc_solve4(a, step)) return false;
    float norm2 = step[0] * step[0] + step[1] * step[1] + step[2] * step[2] + step[3] * step[3];
    float tol2 = SC_FIT_STEP_TOL * SC_FIT_STEP_TOL * R * R;
    while (norm2 > tol2) {                       // step halving keeps the cost decreasing
      float tc[3] = {c[0] + step[0], c[1] + step[1], c[2] + step[2]}, tR = R + step[3];
      float tcost = tR > 0.0f ? sc_sphere_cost(m, tc, tR) : INFINITY;
      if (tcost <= cost) {
        c[0] = tc[0]; c[1] = tc[1]; c[2] = tc[2]; R = tR; cost = tcost;
        break;
      }
      for (uint8_t k = 0; k < 4; ++k) step[k] *= 0.5f;
      norm2 *= 0.25f;
    }
    if (norm2 <= tol2) break;
  }
  for (uint8_t j = 0; j < 3; ++j) out.b[j] = c[j] + (float)s.center[j] * scale[j];
  out.R = R;
  out.cost = cost;
  out.iters = it;
  return isfinite(R) && R > 0.0f;
}

// Coverage cell (0..63) of the direction u = m - centre (uT): equal-area band of u_z/|u| (8 bands
// of 1/4 in z, Archimedes) times the 45-degree sector of (u_x, u_y).
static inline uint8_t sc_cell(const float u[3]) {
  float r = sqrtf(u[0] * u[0] + u[1] * u[1] + u[2] * u[2]);
  int8_t band = (int8_t)((u[2] / r + 1.0f) * 4.0f);
  if (band < 0 || r == 0.0f) band = 0;
  if (band > 7) band = 7;
  uint8_t sec = (uint8_t)((u[0] < 0 ? 4 : 0) | (((u[0] < 0) != (u[1] < 0)) ? 2 : 0) |
                          (((fabsf(u[0]) < fabsf(u[1])) != ((u[0] < 0) != (u[1] < 0))) ? 1 : 0));
  return (uint8_t)(band * 8 + sec);
}

static inline uint8_t sc_mask_count(const uint8_t mask[8]) {
  uint8_t n = 0;
  for (uint8_t i = 0; i < 8; ++i)
    for (uint8_t v = mask[i]; v; v &= (uint8_t)(v - 1)) ++n;
  return n;
}

// Held-out loss of one sample m (uT) under a calibration: min((|K^-1 (m - b)|^2 - 1)^2, cap).
static inline float sc_score(const ScCal &c, const float m[3]) {
  float x[3];
  sc_cal_apply(c, m, x);
  float e = x[0] * x[0] + x[1] * x[1] + x[2] * x[2] - 1.0f;
  return fminf(e * e, SC_SCORE_CAP);
}

// A sphere as a calibration block: K = R I, b = centre (uT), CRC filled in.
static inline void sc_cal_from_sphere(ScCal &c, uint16_t cal_id, const float b[3], float R) {
  c.cal_id = cal_id;
  for (uint8_t i = 0; i < 6; ++i) c.k[i] = (i == 0 || i == 3 || i == 5) ? R : 0.0f;
  for (uint8_t i = 0; i < 3; ++i) c.b[i] = b[i];
  c.crc = sc_cal_crc(c);
}

#endif  // SC_SELFCAL_H

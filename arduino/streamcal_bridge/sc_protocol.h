// sc_protocol.h -- streamcal serial frame protocol v1, shared by the sketch and the host test
// program (arduino/test_vectors). Mirror of firmware_bridge/frames.py; spec in
// firmware_bridge/PROTOCOL.md.
//
//   frame   = COBS(header | body | crc16) 0x00
//   header  = version:u8 type:u8 seq:u16        every multi-byte field little-endian
//   crc16   = CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF) over header|body
//
// Payloads are at most SC_MAX_PAYLOAD = 253 bytes, so COBS never emits a 0xFF block and a frame
// can be encoded in place: the caller's buffer keeps byte 0 free for the first COBS code.
// Plain C-style code (no heap, no exceptions) so it builds with avr-gcc and g++ alike.
#ifndef SC_PROTOCOL_H
#define SC_PROTOCOL_H

#include <math.h>
#include <stdint.h>
#include <string.h>

#define SC_PROTOCOL_VERSION 1
#define SC_MAX_PAYLOAD 253
#define SC_HEADER_SIZE 4
#define SC_CRC_SIZE 2
// Bytes a frame buffer needs for a body of `body` bytes: COBS code + header + body + CRC + 0x00.
#define SC_FRAME_BUF(body) (1 + SC_HEADER_SIZE + (body) + SC_CRC_SIZE + 1)

enum ScType {
  SC_HELLO = 0x01, SC_SAMPLE = 0x02, SC_CAL_SAMPLE = 0x03, SC_SPHERE_SUMS = 0x04,
  SC_CAL_REPORT = 0x05, SC_ACK = 0x06, SC_NAK = 0x07, SC_SELF_CAL = 0x08,
  SC_GET_INFO = 0x10, SC_START = 0x11, SC_STOP = 0x12, SC_SET_CAL = 0x13,
  SC_QUERY_CAL = 0x14, SC_CLEAR_CAL = 0x15
};

// Body sizes, bytes (frames.py: Message.body_size()).
enum ScSize {
  SC_SIZE_HELLO = 37, SC_SIZE_SAMPLE = 25, SC_SIZE_CAL_SAMPLE = 17, SC_SIZE_SPHERE_SUMS = 206,
  SC_SIZE_CAL = 40, SC_SIZE_CAL_REPORT = 41, SC_SIZE_ACK = 3, SC_SIZE_NAK = 4, SC_SIZE_START = 7,
  SC_SIZE_SELF_CAL = 74
};

enum ScStatus {
  SC_ST_MAG_VALID = 0x01, SC_ST_MAG_OVERFLOW = 0x02, SC_ST_MAG_OVERRUN = 0x04,
  SC_ST_ACCEL_VALID = 0x08, SC_ST_GYRO_VALID = 0x10, SC_ST_TEMP_VALID = 0x20,
  SC_ST_I2C_ERROR = 0x40, SC_ST_CAL_ACTIVE = 0x80
};
enum ScHelloFlags { SC_HF_CAL_LOADED = 0x01, SC_HF_MAG_PRESENT = 0x02, SC_HF_STREAMING = 0x04,
                    SC_HF_SELF_CAL = 0x08 };
// SELF_CAL: what happened, why, and where the calibration in force came from.
enum ScSelfCalEvent { SC_SE_FITTED = 1, SC_SE_ACCEPTED = 2, SC_SE_REJECTED = 3, SC_SE_FIT_FAILED = 4 };
enum ScSelfCalReason { SC_SR_NONE = 0, SC_SR_NO_CAL_IN_FORCE = 1, SC_SR_BEATS_IN_FORCE = 2,
                       SC_SR_NOT_BETTER = 3, SC_SR_EEPROM_FAILED = 4, SC_SR_UNDETERMINED = 5,
                       SC_SR_TOO_POOR = 6 };
enum ScCalOrigin { SC_ORIGIN_NONE = 0, SC_ORIGIN_HOST = 1, SC_ORIGIN_BOARD = 2, SC_ORIGIN_BUILTIN = 3 };
enum ScOutput { SC_OUT_SAMPLES = 0x01, SC_OUT_CALIBRATED = 0x02, SC_OUT_SPHERE_SUMS = 0x04,
                SC_OUT_RESET_SUMS = 0x08 };
enum ScNakReason { SC_NAK_BAD_CAL_CRC = 1, SC_NAK_BAD_CAL_VALUES = 2, SC_NAK_UNKNOWN_TYPE = 3,
                   SC_NAK_BAD_LENGTH = 4, SC_NAK_BAD_VERSION = 5, SC_NAK_EEPROM_FAILED = 6 };

// ---- CRC-16/CCITT-FALSE, bitwise (no 512-byte table: RAM/flash matter more than speed here) ----
static inline uint16_t sc_crc16_update(uint16_t crc, uint8_t byte) {
  crc ^= (uint16_t)byte << 8;
  for (uint8_t i = 0; i < 8; ++i) crc = (crc & 0x8000) ? (uint16_t)((crc << 1) ^ 0x1021) : (uint16_t)(crc << 1);
  return crc;
}
static inline uint16_t sc_crc16(const uint8_t *p, uint16_t n) {
  uint16_t crc = 0xFFFF;
  while (n--) crc = sc_crc16_update(crc, *p++);
  return crc;
}

// ---- little-endian field access ----
struct ScWriter { uint8_t *p; };
static inline void sc_put_u8(ScWriter &w, uint8_t v) { *w.p++ = v; }
static inline void sc_put_u16(ScWriter &w, uint16_t v) { *w.p++ = (uint8_t)v; *w.p++ = (uint8_t)(v >> 8); }
static inline void sc_put_u32(ScWriter &w, uint32_t v) {
  for (uint8_t i = 0; i < 4; ++i) { *w.p++ = (uint8_t)v; v >>= 8; }
}
static inline void sc_put_i16(ScWriter &w, int16_t v) { sc_put_u16(w, (uint16_t)v); }
static inline void sc_put_i64(ScWriter &w, int64_t v) {
  uint64_t u = (uint64_t)v;
  for (uint8_t i = 0; i < 8; ++i) { *w.p++ = (uint8_t)u; u >>= 8; }
}
static inline void sc_put_f32(ScWriter &w, float f) {  // IEEE-754 binary32 on both targets
  uint32_t u; memcpy(&u, &f, 4); sc_put_u32(w, u);
}

struct ScReader { const uint8_t *p; };
static inline uint8_t sc_get_u8(ScReader &r) { return *r.p++; }
static inline uint16_t sc_get_u16(ScReader &r) { uint16_t v = r.p[0] | ((uint16_t)r.p[1] << 8); r.p += 2; return v; }
static inline uint32_t sc_get_u32(ScReader &r) {
  uint32_t v = 0;
  for (int8_t i = 3; i >= 0; --i) v = (v << 8) | r.p[i];
  r.p += 4; return v;
}
static inline int16_t sc_get_i16(ScReader &r) { return (int16_t)sc_get_u16(r); }
static inline int64_t sc_get_i64(ScReader &r) {
  uint64_t v = 0;
  for (int8_t i = 7; i >= 0; --i) v = (v << 8) | r.p[i];
  r.p += 8; return (int64_t)v;
}
static inline float sc_get_f32(ScReader &r) { uint32_t u = sc_get_u32(r); float f; memcpy(&f, &u, 4); return f; }

// ---- messages ----
struct ScHello {
  uint8_t fw_major, fw_minor, whoami, ak_wia, flags;
  uint32_t period_us;
  float accel_scale, gyro_scale, temp_scale, temp_offset, mag_scale[3];
};
struct ScSample { uint32_t t_us; int16_t mag[3], accel[3], gyro[3], temp; uint8_t status; };
struct ScCalSample { uint32_t t_us; float x[3]; uint8_t status; };
struct ScCal { uint16_t cal_id; float k[6]; float b[3]; uint16_t crc; };  // k: k11 k12 k13 k22 k23 k33
struct ScAck { uint8_t acked_type; uint16_t acked_seq; uint8_t reason; };  // reason: NAK only
struct ScStart { uint8_t outputs; uint32_t period_us; uint16_t sums_every; };
// The board's own calibration: event, reason, origin and id of the calibration in force after it,
// coverage cells of the window that ended, samples fitted / scored, fit's mean squared residual,
// mean held-out losses of the candidate and of the calibration in force (NaN: none), the fit's
// cycles and one magnetometer sample's calibration work in cycles, and the candidate block.
struct ScSelfCal {
  uint8_t event, reason, origin;
  uint16_t in_force_id;
  uint8_t cells;
  uint32_t n_fit, n_check;
  float fit_cost, loss_new, loss_old;
  uint32_t fit_cycles, sample_cycles;
  ScCal cand;
};
// The 25 one-pass sphere-fit statistics over d = m - center (mag counts), see SphereSums in frames.py.
struct ScSums {
  uint32_t n, rejected;
  int16_t center[3];
  int64_t s1[3], s2[6], s3[9], s4[6];
};

static inline void sc_put_hello(ScWriter &w, const ScHello &h) {
  sc_put_u8(w, h.fw_major); sc_put_u8(w, h.fw_minor); sc_put_u8(w, h.whoami);
  sc_put_u8(w, h.ak_wia); sc_put_u8(w, h.flags); sc_put_u32(w, h.period_us);
  sc_put_f32(w, h.accel_scale); sc_put_f32(w, h.gyro_scale);
  sc_put_f32(w, h.temp_scale); sc_put_f32(w, h.temp_offset);
  for (uint8_t i = 0; i < 3; ++i) sc_put_f32(w, h.mag_scale[i]);
}
static inline void sc_get_hello(ScReader &r, ScHello &h) {
  h.fw_major = sc_get_u8(r); h.fw_minor = sc_get_u8(r); h.whoami = sc_get_u8(r);
  h.ak_wia = sc_get_u8(r); h.flags = sc_get_u8(r); h.period_us = sc_get_u32(r);
  h.accel_scale = sc_get_f32(r); h.gyro_scale = sc_get_f32(r);
  h.temp_scale = sc_get_f32(r); h.temp_offset = sc_get_f32(r);
  for (uint8_t i = 0; i < 3; ++i) h.mag_scale[i] = sc_get_f32(r);
}
static inline void sc_put_sample(ScWriter &w, const ScSample &s) {
  sc_put_u32(w, s.t_us);
  for (uint8_t i = 0; i < 3; ++i) sc_put_i16(w, s.mag[i]);
  for (uint8_t i = 0; i < 3; ++i) sc_put_i16(w, s.accel[i]);
  for (uint8_t i = 0; i < 3; ++i) sc_put_i16(w, s.gyro[i]);
  sc_put_i16(w, s.temp); sc_put_u8(w, s.status);
}
static inline void sc_get_sample(ScReader &r, ScSample &s) {
  s.t_us = sc_get_u32(r);
  for (uint8_t i = 0; i < 3; ++i) s.mag[i] = sc_get_i16(r);
  for (uint8_t i = 0; i < 3; ++i) s.accel[i] = sc_get_i16(r);
  for (uint8_t i = 0; i < 3; ++i) s.gyro[i] = sc_get_i16(r);
  s.temp = sc_get_i16(r); s.status = sc_get_u8(r);
}
static inline void sc_put_cal_sample(ScWriter &w, const ScCalSample &c) {
  sc_put_u32(w, c.t_us);
  for (uint8_t i = 0; i < 3; ++i) sc_put_f32(w, c.x[i]);
  sc_put_u8(w, c.status);
}
static inline void sc_get_cal_sample(ScReader &r, ScCalSample &c) {
  c.t_us = sc_get_u32(r);
  for (uint8_t i = 0; i < 3; ++i) c.x[i] = sc_get_f32(r);
  c.status = sc_get_u8(r);
}
static inline void sc_put_cal(ScWriter &w, const ScCal &c) {
  sc_put_u16(w, c.cal_id);
  for (uint8_t i = 0; i < 6; ++i) sc_put_f32(w, c.k[i]);
  for (uint8_t i = 0; i < 3; ++i) sc_put_f32(w, c.b[i]);
  sc_put_u16(w, c.crc);
}
static inline void sc_get_cal(ScReader &r, ScCal &c) {
  c.cal_id = sc_get_u16(r);
  for (uint8_t i = 0; i < 6; ++i) c.k[i] = sc_get_f32(r);
  for (uint8_t i = 0; i < 3; ++i) c.b[i] = sc_get_f32(r);
  c.crc = sc_get_u16(r);
}
static inline void sc_put_self_cal(ScWriter &w, const ScSelfCal &f) {
  sc_put_u8(w, f.event); sc_put_u8(w, f.reason); sc_put_u8(w, f.origin);
  sc_put_u16(w, f.in_force_id); sc_put_u8(w, f.cells);
  sc_put_u32(w, f.n_fit); sc_put_u32(w, f.n_check);
  sc_put_f32(w, f.fit_cost); sc_put_f32(w, f.loss_new); sc_put_f32(w, f.loss_old);
  sc_put_u32(w, f.fit_cycles); sc_put_u32(w, f.sample_cycles);
  sc_put_cal(w, f.cand);
}
static inline void sc_get_self_cal(ScReader &r, ScSelfCal &f) {
  f.event = sc_get_u8(r); f.reason = sc_get_u8(r); f.origin = sc_get_u8(r);
  f.in_force_id = sc_get_u16(r); f.cells = sc_get_u8(r);
  f.n_fit = sc_get_u32(r); f.n_check = sc_get_u32(r);
  f.fit_cost = sc_get_f32(r); f.loss_new = sc_get_f32(r); f.loss_old = sc_get_f32(r);
  f.fit_cycles = sc_get_u32(r); f.sample_cycles = sc_get_u32(r);
  sc_get_cal(r, f.cand);
}
static inline void sc_put_start(ScWriter &w, const ScStart &s) {
  sc_put_u8(w, s.outputs); sc_put_u32(w, s.period_us); sc_put_u16(w, s.sums_every);
}
static inline void sc_get_start(ScReader &r, ScStart &s) {
  s.outputs = sc_get_u8(r); s.period_us = sc_get_u32(r); s.sums_every = sc_get_u16(r);
}
static inline void sc_put_sums(ScWriter &w, const ScSums &s) {
  sc_put_u32(w, s.n); sc_put_u32(w, s.rejected);
  for (uint8_t i = 0; i < 3; ++i) sc_put_i16(w, s.center[i]);
  for (uint8_t i = 0; i < 3; ++i) sc_put_i64(w, s.s1[i]);
  for (uint8_t i = 0; i < 6; ++i) sc_put_i64(w, s.s2[i]);
  for (uint8_t i = 0; i < 9; ++i) sc_put_i64(w, s.s3[i]);
  for (uint8_t i = 0; i < 6; ++i) sc_put_i64(w, s.s4[i]);
}
static inline void sc_get_sums(ScReader &r, ScSums &s) {
  s.n = sc_get_u32(r); s.rejected = sc_get_u32(r);
  for (uint8_t i = 0; i < 3; ++i) s.center[i] = sc_get_i16(r);
  for (uint8_t i = 0; i < 3; ++i) s.s1[i] = sc_get_i64(r);
  for (uint8_t i = 0; i < 6; ++i) s.s2[i] = sc_get_i64(r);
  for (uint8_t i = 0; i < 9; ++i) s.s3[i] = sc_get_i64(r);
  for (uint8_t i = 0; i < 6; ++i) s.s4[i] = sc_get_i64(r);
}

// ---- framing ----
// Write the header into buf[1..4]; return a writer positioned at the body.
static inline ScWriter sc_begin(uint8_t *buf, uint8_t type, uint16_t seq) {
  ScWriter w = {buf + 1};
  sc_put_u8(w, SC_PROTOCOL_VERSION); sc_put_u8(w, type); sc_put_u16(w, seq);
  return w;
}
// Append the CRC, COBS-encode buf[1..n] in place into buf[0..n], add the 0x00 delimiter.
// `w` is the writer after the body. Returns the number of bytes to send.
static inline uint16_t sc_finish(uint8_t *buf, ScWriter w) {
  uint16_t n = (uint16_t)(w.p - (buf + 1));
  sc_put_u16(w, sc_crc16(buf + 1, n));
  n += SC_CRC_SIZE;
  // Walk back from the virtual zero after the data: every zero (and the leading code byte)
  // becomes the distance to the next zero. Valid because n <= 253 (no 0xFF blocks).
  uint16_t next = n + 1;
  for (int16_t i = (int16_t)n; i >= 0; --i) {
    if (i == 0 || buf[i] == 0) { buf[i] = (uint8_t)(next - i); next = (uint16_t)i; }
  }
  buf[n + 1] = 0;
  return n + 2;
}

// COBS-decode buf[0..n) in place; return the decoded length or -1 if the codes are inconsistent.
static inline int16_t sc_cobs_decode(uint8_t *buf, uint16_t n) {
  uint16_t r = 0, w = 0;
  while (r < n) {
    uint8_t code = buf[r];
    if (code == 0 || (uint16_t)(r + code) > n) return -1;
    ++r;
    for (uint8_t i = 1; i < code; ++i) buf[w++] = buf[r++];
    if (code != 0xFF && r != n) buf[w++] = 0;
  }
  return (int16_t)w;
}

// Byte-at-a-time receiver with a caller-provided buffer. Counts damage, never blocks.
struct ScDecoder {
  uint8_t *buf;
  uint16_t cap, len;
  uint8_t discarding;
  uint16_t crc_errors, cobs_errors, truncated, oversized;
};
static inline void sc_decoder_init(ScDecoder &d, uint8_t *buf, uint16_t cap) {
  memset(&d, 0, sizeof d); d.buf = buf; d.cap = cap;
}
// Feed one byte. Returns the payload length without CRC (>= SC_HEADER_SIZE) when a frame with a
// good CRC ended at this byte: buf[0] version, buf[1] type, buf[2..3] seq, body from buf[4].
// Returns 0 otherwise (damaged frames are counted).
static inline int16_t sc_decoder_feed(ScDecoder &d, uint8_t byte) {
  if (byte != 0) {
    if (d.discarding) return 0;
    if (d.len >= d.cap) { d.discarding = 1; d.len = 0; ++d.oversized; return 0; }
    d.buf[d.len++] = byte;
    return 0;
  }
  uint16_t n = d.len;
  d.len = 0;
  if (d.discarding) { d.discarding = 0; return 0; }
  if (n == 0) return 0;  // idle delimiter
  int16_t m = sc_cobs_decode(d.buf, n);
  if (m < 0) { ++d.cobs_errors; return 0; }
  if (m < SC_HEADER_SIZE + SC_CRC_SIZE) { ++d.truncated; return 0; }
  m -= SC_CRC_SIZE;
  uint16_t crc = d.buf[m] | ((uint16_t)d.buf[m + 1] << 8);
  if (sc_crc16(d.buf, (uint16_t)m) != crc) { ++d.crc_errors; return 0; }
  return m;
}

// ---- calibration on the board ----
static inline uint16_t sc_cal_crc(const ScCal &c) {
  uint8_t tmp[SC_SIZE_CAL];
  ScWriter w = {tmp};
  sc_put_cal(w, c);
  return sc_crc16(tmp, SC_SIZE_CAL - 2);
}
// 0 if usable, else the NAK reason.
static inline uint8_t sc_cal_check(const ScCal &c) {
  if (sc_cal_crc(c) != c.crc) return SC_NAK_BAD_CAL_CRC;
  for (uint8_t i = 0; i < 6; ++i) if (!isfinite(c.k[i])) return SC_NAK_BAD_CAL_VALUES;
  for (uint8_t i = 0; i < 3; ++i) if (!isfinite(c.b[i])) return SC_NAK_BAD_CAL_VALUES;
  if (!(c.k[0] > 0.0f && c.k[3] > 0.0f && c.k[5] > 0.0f)) return SC_NAK_BAD_CAL_VALUES;
  return 0;
}
// x = K^-1 (m - b) by back substitution (K upper triangular), single precision; m in uT.
static inline void sc_cal_apply(const ScCal &c, const float m[3], float x[3]) {
  float d0 = m[0] - c.b[0], d1 = m[1] - c.b[1], d2 = m[2] - c.b[2];
  x[2] = d2 / c.k[5];
  x[1] = (d1 - c.k[4] * x[2]) / c.k[3];
  x[0] = (d0 - c.k[1] * x[1] - c.k[2] * x[2]) / c.k[0];
}

// ---- sphere sums ----
#define SC_SUMS_MAX_N 524288UL   // 2^19 samples of |d| <= 2047 keep every int64 sum in range
#define SC_SUMS_MAX_D 2047
static inline void sc_sums_reset(ScSums &s) { memset(&s, 0, sizeof s); }
// Add one mag sample (counts); the first sample after a reset becomes the center.
static inline void sc_sums_add(ScSums &s, const int16_t m[3]) {
  if (s.n == 0 && s.rejected == 0) { s.center[0] = m[0]; s.center[1] = m[1]; s.center[2] = m[2]; }
  int32_t d[3];
  for (uint8_t j = 0; j < 3; ++j) {
    d[j] = (int32_t)m[j] - s.center[j];
    if (d[j] > SC_SUMS_MAX_D || d[j] < -SC_SUMS_MAX_D) { ++s.rejected; return; }
  }
  if (s.n >= SC_SUMS_MAX_N) { ++s.rejected; return; }
  int32_t q[3] = {d[0] * d[0], d[1] * d[1], d[2] * d[2]};
  static const uint8_t pj[6] = {0, 0, 0, 1, 1, 2}, pk[6] = {0, 1, 2, 1, 2, 2};
  for (uint8_t j = 0; j < 3; ++j) {
    s.s1[j] += d[j];
    for (uint8_t k = 0; k < 3; ++k) s.s3[3 * j + k] += (int64_t)q[j] * d[k];
  }
  for (uint8_t p = 0; p < 6; ++p) {
    s.s2[p] += (int64_t)(d[pj[p]] * d[pk[p]]);
    s.s4[p] += (int64_t)q[pj[p]] * q[pk[p]];
  }
  ++s.n;
}

#endif  // SC_PROTOCOL_H

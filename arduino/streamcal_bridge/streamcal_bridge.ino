// streamcal_bridge -- MPU-9250 (+ AK8963) to USB serial, streamcal frame protocol v1.
//
// Streams SAMPLE frames (raw counts, body axes) at a fixed period, CAL_SAMPLE frames
// (x = K^-1 (m - b), computed here) when a calibration is held, and the 25 one-pass sphere-fit
// sums. Accepts SET_CAL (validated, stored in EEPROM with its own CRC, loaded at boot), QUERY_CAL,
// CLEAR_CAL, START/STOP and GET_INFO. Protocol: firmware_bridge/PROTOCOL.md; codec: sc_protocol.h.
//
// Self-calibration (sc_selfcal.h; off with -DSC_NO_SELFCAL): the magnetometer samples are cut into
// windows, each ending when its coverage mask holds SC_MASK_NEED of 64 cells. At a window's end
// the sphere fitted to it becomes the candidate, and the next window is its held-out check: each
// of its samples is scored under the candidate and under the calibration in force. At that
// window's end the candidate replaces the calibration in force only if it scores better by a
// quarter (or none is in force and it is good enough); it is then stored in EEPROM and applied at
// once. Every fit and decision is announced in a SELF_CAL frame.
// A header sc_initial_cal.h beside the sketch (streamcal export --format c-header) gives the
// calibration to start from while the EEPROM holds none.
// Register facts: HARDWARE.md sections 2-4 (MPU-9250 register map, AK8963 datasheet).
#include <EEPROM.h>

#include "sc_protocol.h"
#include "sc_twi.h"
#include "sc_uart.h"

#if defined(__has_include)
#if __has_include("sc_initial_cal.h")
#include "sc_initial_cal.h"
#endif
#endif

#define FW_MAJOR 1
#define FW_MINOR 0
#define BAUD 115200UL
// Sample period: 5 ms = 200 Hz, the accel/gyro output rate set below and twice the AK8963's
// 100 Hz, so a poll that comes late by up to 5 ms still reads every magnetometer sample (at
// 10 ms, the magnetometer's own period, timing jitter made ~1 % of them overrun). Serial budget
// at 115200 8N1 (11520 B/s): SAMPLE 33 B x 200/s + CAL_SAMPLE 25 B x 100/s + SPHERE_SUMS
// 215 B x 1/s = 9.3 kB/s (81 %).
#define PERIOD_US 5000UL

// MPU-9250 (RM-MPU-9250A-00): address with AD0 = 0, registers.
#define MPU_ADDR 0x68
#define MPU_SMPLRT_DIV 0x19
#define MPU_CONFIG 0x1A
#define MPU_GYRO_CONFIG 0x1B
#define MPU_ACCEL_CONFIG 0x1C
#define MPU_ACCEL_CONFIG2 0x1D
#define MPU_INT_PIN_CFG 0x37
#define MPU_ACCEL_XOUT_H 0x3B   // 14 bytes: ax ay az temp gx gy gz, big-endian
#define MPU_USER_CTRL 0x6A
#define MPU_PWR_MGMT_1 0x6B
#define MPU_WHO_AM_I 0x75
#define MPU_BYPASS_EN 0x02      // INT_PIN_CFG bit 1: host bus straight through to the AK8963
#define GYRO_FS_2000DPS 0x18    // GYRO_CONFIG FS_SEL = 3: 16.4 LSB/(deg/s)
#define ACCEL_FS_4G 0x08        // ACCEL_CONFIG AFS_SEL = 1: 8192 LSB/g

// AK8963 (AK8963 datasheet), reachable in bypass mode.
#define AK_ADDR 0x0C
#define AK_WIA 0x00
#define AK_ST1 0x02             // 8 bytes 0x02..0x09: ST1, HXL..HZH (little-endian), ST2 (read last)
#define AK_CNTL1 0x0A
#define AK_ASAX 0x10
#define AK_WIA_VALUE 0x48
#define AK_ST1_DRDY 0x01
#define AK_ST1_DOR 0x02
#define AK_ST2_HOFL 0x08
#define AK_MODE_POWER_DOWN 0x00
#define AK_MODE_FUSE_ROM 0x0F
#define AK_MODE_CONT2_16BIT 0x16   // continuous mode 2 (100 Hz), BIT = 1 (16-bit output)
// 16-bit scale: 4912 uT full scale over 32760 counts = 0.149939 uT/LSB (RM-MPU-9250A-00 p50;
// the "0.15" of the datasheet table is this value rounded). Same as registers.mag_scale(16).
#define AK_UT_PER_LSB (4912.0f / 32760.0f)

// Scales announced in HELLO (PS-MPU-9250A-01 p8/p9/p12).
#define ACCEL_SCALE (9.80665f / 8192.0f)                 // m/s^2 per count
#define GYRO_SCALE (3.14159265f / 180.0f / 16.4f)        // rad/s per count
#define TEMP_SCALE (1.0f / 333.87f)                      // degC per count
#define TEMP_OFFSET 21.0f

// EEPROM layout 2: two slots of 46 bytes, layout u8, origin u8, seq u16, the 40-byte calibration
// block, crc u16 over the 44 bytes before it. The newer valid slot is in force; a write goes to
// the other one, so a reset in the middle of it leaves the previous calibration in force.
#define EE_LAYOUT 2
#define EE_SLOT_SIZE 46
#define EE_SLOT_A 0
#define EE_SLOT_B 64

static uint8_t g_tx[SC_FRAME_BUF(SC_SIZE_SPHERE_SUMS)];
static uint8_t g_rx_buf[SC_SIZE_CAL + SC_HEADER_SIZE + SC_CRC_SIZE + 2];
static ScDecoder g_rx;
static ScSums g_sums;
static ScCal g_cal;
static bool g_cal_valid;
static uint8_t g_origin;         // ScCalOrigin of g_cal
static uint8_t g_slot;           // EEPROM slot holding g_cal (0/1), 0xFF none
static uint16_t g_ee_seq;        // sequence number of the newest slot written
static float g_mag_scale[3];     // uT per count along body x, y, z (ASA applied)
static uint16_t g_seq;
static uint8_t g_whoami, g_ak_wia, g_outputs;
static bool g_streaming, g_mag_present;
static uint32_t g_period_us = PERIOD_US, g_next_due;
static uint16_t g_sums_every = 100, g_sums_since;
static ScSample g_held;          // read while the line was busy, sent next (poll_while_busy)
static bool g_have_held;

// ---- I2C ----
static bool write_reg(uint8_t addr, uint8_t reg, uint8_t value) {
  return sc_twi_write(addr, reg, &value, 1, false);
}

static bool read_regs(uint8_t addr, uint8_t reg, uint8_t *out, uint8_t n) {
  return sc_twi_read(addr, reg, out, n);
}

static uint8_t read_reg(uint8_t addr, uint8_t reg) {
  uint8_t v = 0;
  read_regs(addr, reg, &v, 1);
  return v;
}

static void sensor_setup() {
  write_reg(MPU_ADDR, MPU_PWR_MGMT_1, 0x80);   // H_RESET
  delay(100);
  write_reg(MPU_ADDR, MPU_PWR_MGMT_1, 0x01);   // clock: PLL if ready
  delay(10);
  write_reg(MPU_ADDR, MPU_CONFIG, 0x03);       // DLPF 41 Hz, 1 kHz internal rate
  write_reg(MPU_ADDR, MPU_SMPLRT_DIV, 0x04);   // 200 Hz output rate
  write_reg(MPU_ADDR, MPU_GYRO_CONFIG, GYRO_FS_2000DPS);
  write_reg(MPU_ADDR, MPU_ACCEL_CONFIG, ACCEL_FS_4G);
  write_reg(MPU_ADDR, MPU_ACCEL_CONFIG2, 0x03);
  write_reg(MPU_ADDR, MPU_USER_CTRL, 0x00);    // I2C_MST_EN = 0, required for bypass
  write_reg(MPU_ADDR, MPU_INT_PIN_CFG, MPU_BYPASS_EN);
  g_whoami = read_reg(MPU_ADDR, MPU_WHO_AM_I);

  g_ak_wia = read_reg(AK_ADDR, AK_WIA);
  g_mag_present = g_ak_wia == AK_WIA_VALUE;
  uint8_t asa[3] = {128, 128, 128};
  if (g_mag_present) {
    write_reg(AK_ADDR, AK_CNTL1, AK_MODE_POWER_DOWN);
    delay(10);
    write_reg(AK_ADDR, AK_CNTL1, AK_MODE_FUSE_ROM);
    delay(10);
    read_regs(AK_ADDR, AK_ASAX, asa, 3);
    write_reg(AK_ADDR, AK_CNTL1, AK_MODE_POWER_DOWN);
    delay(10);
    write_reg(AK_ADDR, AK_CNTL1, AK_MODE_CONT2_16BIT);
    delay(10);
  }
  // Hadj = H (ASA + 128) / 256; body axes: x = Hy, y = Hx, z = -Hz (sign applied to the counts).
  g_mag_scale[0] = AK_UT_PER_LSB * (asa[1] + 128) / 256.0f;
  g_mag_scale[1] = AK_UT_PER_LSB * (asa[0] + 128) / 256.0f;
  g_mag_scale[2] = AK_UT_PER_LSB * (asa[2] + 128) / 256.0f;
}

// ---- frames out ----
static void poll_while_busy();
#ifndef SC_NO_SELFCAL
#define SC_FIT_IDLE() poll_while_busy()
#include "sc_selfcal.h"
#endif

// Write a frame; while the 64-byte transmit ring is full, keep polling the sensors (a
// 215-byte SPHERE_SUMS frame holds the line for ~19 ms, long enough for the AK8963 to overwrite
// an unread sample).
static void send(ScWriter w) {
  uint8_t n = (uint8_t)sc_finish(g_tx, w);
  for (uint8_t i = 0; i < n;) {
    if (sc_uart_room() == 0) { poll_while_busy(); continue; }
    sc_uart_put(g_tx[i++]);
  }
  ++g_seq;
}

// The AVR is little-endian and lays these structs out without padding (the static_asserts), so
// each is its frame body byte for byte, as sc_put_* would write it (those are checked against the
// Python encoder by arduino/test_vectors; these frames end to end by tests/test_simavr.py).
static_assert(sizeof(ScHello) == SC_SIZE_HELLO && sizeof(ScSample) == SC_SIZE_SAMPLE &&
              sizeof(ScCalSample) == SC_SIZE_CAL_SAMPLE && sizeof(ScSums) == SC_SIZE_SPHERE_SUMS &&
              sizeof(ScSelfCal) == SC_SIZE_SELF_CAL, "a message struct is not its packed frame body");
static __attribute__((noinline)) void send_body(uint8_t type, const void *body, uint8_t n) {
  ScWriter w = sc_begin(g_tx, type, g_seq);
  memcpy(w.p, body, n);
  w.p += n;
  send(w);
}

static void send_hello() {
  ScHello h;
  h.fw_major = FW_MAJOR; h.fw_minor = FW_MINOR; h.whoami = g_whoami; h.ak_wia = g_ak_wia;
  h.flags = (g_cal_valid ? SC_HF_CAL_LOADED : 0) | (g_mag_present ? SC_HF_MAG_PRESENT : 0) |
            (g_streaming ? SC_HF_STREAMING : 0);
#ifndef SC_NO_SELFCAL
  h.flags |= SC_HF_SELF_CAL;
#endif
  h.period_us = g_period_us;
  h.accel_scale = ACCEL_SCALE; h.gyro_scale = GYRO_SCALE;
  h.temp_scale = TEMP_SCALE; h.temp_offset = TEMP_OFFSET;
  for (uint8_t i = 0; i < 3; ++i) h.mag_scale[i] = g_mag_scale[i];
  send_body(SC_HELLO, &h, SC_SIZE_HELLO);
}

static void send_ack(uint8_t type, uint16_t seq, uint8_t reason) {
  ScWriter w = sc_begin(g_tx, reason ? SC_NAK : SC_ACK, g_seq);
  sc_put_u8(w, type);
  sc_put_u16(w, seq);
  if (reason) sc_put_u8(w, reason);
  send(w);
}

static void send_cal_report() {
  ScWriter w = sc_begin(g_tx, SC_CAL_REPORT, g_seq);
  sc_put_u8(w, g_cal_valid ? 1 : 0);
  sc_put_cal(w, g_cal);
  send(w);
}

static void send_sums() {
  send_body(SC_SPHERE_SUMS, &g_sums, SC_SIZE_SPHERE_SUMS);
}

// ---- calibration in EEPROM ----
static bool read_slot(uint8_t slot, ScCal &c, uint8_t &origin, uint16_t &seq) {
  uint8_t b[EE_SLOT_SIZE];
  uint16_t at = slot ? EE_SLOT_B : EE_SLOT_A;
  for (uint8_t i = 0; i < EE_SLOT_SIZE; ++i) b[i] = EEPROM.read(at + i);
  ScReader r = {b};
  if (sc_get_u8(r) != EE_LAYOUT) return false;
  origin = sc_get_u8(r);
  seq = sc_get_u16(r);
  sc_get_cal(r, c);
  return sc_get_u16(r) == sc_crc16(b, EE_SLOT_SIZE - 2) && sc_cal_check(c) == 0;
}

static void load_calibration() {
  g_cal_valid = false;
  g_origin = SC_ORIGIN_NONE;
  g_slot = 0xFF;
  ScCal c;
  uint8_t origin;
  uint16_t seq;
  for (uint8_t i = 0; i < 2; ++i) {
    if (!read_slot(i, c, origin, seq)) continue;
    if (g_cal_valid && (int16_t)(seq - g_ee_seq) <= 0) continue;
    g_cal = c; g_cal_valid = true; g_origin = origin; g_slot = i; g_ee_seq = seq;
  }
#ifdef SC_INITIAL_CAL_K
  if (!g_cal_valid) {
    static const float k0[6] PROGMEM = SC_INITIAL_CAL_K;
    static const float b0[3] PROGMEM = SC_INITIAL_CAL_B;
    c.cal_id = 0;
    memcpy_P(c.k, k0, sizeof c.k);
    memcpy_P(c.b, b0, sizeof c.b);
    c.crc = sc_cal_crc(c);
    if (sc_cal_check(c) == 0) { g_cal = c; g_cal_valid = true; g_origin = SC_ORIGIN_BUILTIN; }
  }
#endif
}

// Write c to the slot not in force, read it back, then make it the calibration in force.
static uint8_t store_calibration(const ScCal &c, uint8_t origin) {
  uint8_t b[EE_SLOT_SIZE];
  uint8_t slot = g_slot == 0 ? 1 : 0;
  uint16_t at = slot ? EE_SLOT_B : EE_SLOT_A, seq = g_ee_seq + 1;
  ScWriter w = {b};
  sc_put_u8(w, EE_LAYOUT); sc_put_u8(w, origin); sc_put_u16(w, seq);
  sc_put_cal(w, c);
  sc_put_u16(w, sc_crc16(b, EE_SLOT_SIZE - 2));
  for (uint8_t i = 0; i < EE_SLOT_SIZE; ++i) EEPROM.update(at + i, b[i]);
  for (uint8_t i = 0; i < EE_SLOT_SIZE; ++i)
    if (EEPROM.read(at + i) != b[i]) return SC_NAK_EEPROM_FAILED;
  g_cal = c; g_cal_valid = true; g_origin = origin; g_slot = slot; g_ee_seq = seq;
  return 0;
}

// ---- commands in ----
static void handle_frame(int16_t n) {
  const uint8_t *p = g_rx_buf;
  uint8_t type = p[1];
  uint16_t seq = p[2] | ((uint16_t)p[3] << 8);
  uint8_t body_len = n - SC_HEADER_SIZE;
  ScReader r = {p + SC_HEADER_SIZE};
  if (p[0] != SC_PROTOCOL_VERSION) { send_ack(type, seq, SC_NAK_BAD_VERSION); return; }
  switch (type) {
    case SC_GET_INFO:
      if (body_len != 0) break;
      send_hello();
      return;
    case SC_QUERY_CAL:
      if (body_len != 0) break;
      send_cal_report();
      return;
    case SC_STOP:
      if (body_len != 0) break;
      g_streaming = false;
      g_have_held = false;
      send_ack(type, seq, 0);
      return;
    case SC_CLEAR_CAL:
      if (body_len != 0) break;
      EEPROM.update(EE_SLOT_A, 0xFF);
      EEPROM.update(EE_SLOT_B, 0xFF);
      g_cal_valid = false;
      g_origin = SC_ORIGIN_NONE;
      g_slot = 0xFF;
      send_ack(type, seq, 0);
      return;
    case SC_START: {
      if (body_len != SC_SIZE_START) break;
      ScStart s;
      sc_get_start(r, s);
      g_outputs = s.outputs;
      if (s.period_us >= 2000) g_period_us = s.period_us;
      g_sums_every = s.sums_every;
      if (s.outputs & SC_OUT_RESET_SUMS) { sc_sums_reset(g_sums); g_sums_since = 0; }
      g_streaming = true;
      g_next_due = micros();
      send_ack(type, seq, 0);
      return;
    }
    case SC_SET_CAL: {
      if (body_len != SC_SIZE_CAL) break;
      ScCal c;
      sc_get_cal(r, c);
      uint8_t reason = sc_cal_check(c);
      if (reason == 0) reason = store_calibration(c, SC_ORIGIN_HOST);
      send_ack(type, seq, reason);
      return;
    }
    default:
      send_ack(type, seq, SC_NAK_UNKNOWN_TYPE);
      return;
  }
  send_ack(type, seq, SC_NAK_BAD_LENGTH);
}

// ---- sampling ----
static void read_sample(ScSample &s) {
  memset(&s, 0, sizeof s);
  s.t_us = micros();
  uint8_t raw[14];
  if (read_regs(MPU_ADDR, MPU_ACCEL_XOUT_H, raw, 14)) {
    int16_t v[7];
    for (uint8_t i = 0; i < 7; ++i) v[i] = (int16_t)((raw[2 * i] << 8) | raw[2 * i + 1]);
    for (uint8_t i = 0; i < 3; ++i) { s.accel[i] = v[i]; s.gyro[i] = v[4 + i]; }
    s.temp = v[3];
    s.status |= SC_ST_ACCEL_VALID | SC_ST_GYRO_VALID | SC_ST_TEMP_VALID;
  } else {
    s.status |= SC_ST_I2C_ERROR;
  }
  if (g_mag_present) {
    uint8_t m[8];
    if (!read_regs(AK_ADDR, AK_ST1, m, 8)) {
      s.status |= SC_ST_I2C_ERROR;
    } else if (m[0] & AK_ST1_DRDY) {
      if (m[0] & AK_ST1_DOR) s.status |= SC_ST_MAG_OVERRUN;
      if (m[7] & AK_ST2_HOFL) {
        s.status |= SC_ST_MAG_OVERFLOW;
      } else {
        int16_t hx = (int16_t)(m[1] | (m[2] << 8)), hy = (int16_t)(m[3] | (m[4] << 8)),
                hz = (int16_t)(m[5] | (m[6] << 8));
        s.mag[0] = hy; s.mag[1] = hx; s.mag[2] = -hz;   // |H| <= 32760, negation is safe
        s.status |= SC_ST_MAG_VALID;
      }
    }
  }
  if (g_cal_valid) s.status |= SC_ST_CAL_ACTIVE;
}

// Next poll time; a schedule more than one period late restarts from now (missed polls would
// only repeat the current reading, in a burst the line cannot carry).
static void advance_schedule() {
  g_next_due += g_period_us;
  uint32_t now = micros();
  if ((int32_t)(now - g_next_due) > (int32_t)g_period_us) g_next_due = now;
}

// A poll that comes due while send() waits for the line is read into g_held and sent by loop()
// afterwards. One sample is held: a held sample without new magnetometer data gives way to a
// newer one (that accel/gyro reading is not sent); one with magnetometer data is kept, and the
// AK8963 holds the next, so two magnetometer samples (20 ms) wait without loss.
static void poll_while_busy() {
  if (!g_streaming || (int32_t)(micros() - g_next_due) < 0) return;
  if (g_have_held && (g_held.status & SC_ST_MAG_VALID)) return;
  advance_schedule();
  read_sample(g_held);
  g_have_held = true;
}

#ifndef SC_NO_SELFCAL
// ---- self-calibration ----
static uint8_t g_mask[8];        // coverage cells of the current window
static float g_mask_c[3], g_mask_r;  // centre and radius (uT) the cells are counted about; r 0: none
// The SELF_CAL frame body, kept up to date: n_fit, fit_cost, fit_cycles and cand (the candidate
// sphere, K = R I, b in uT; k 0: none) between windows, n_check while one is scored.
static ScSelfCal g_sc;
static bool g_have_cand;
static float g_loss_new, g_loss_old;
static uint32_t g_proc_us, g_proc_n;

static __attribute__((noinline)) void announce(uint8_t event, uint8_t reason, uint8_t cells) {
  g_sc.event = event;
  g_sc.reason = reason;
  g_sc.origin = g_cal_valid ? g_origin : SC_ORIGIN_NONE;
  g_sc.in_force_id = g_cal_valid ? g_cal.cal_id : 0;
  g_sc.cells = cells;
  g_sc.sample_cycles = g_proc_n ? g_proc_us * 16 / g_proc_n : 0;
  send_body(SC_SELF_CAL, &g_sc, SC_SIZE_SELF_CAL);
}

// A window has reached its coverage: judge the pending candidate on it, fit the next one to it.
static __attribute__((noinline)) void window_end() {
  uint8_t cells = sc_mask_count(g_mask);
  // the losses as scored, before a decision changes what is in force (NaN: nothing was)
  g_sc.loss_new = g_loss_new / g_sc.n_check;
  g_sc.loss_old = g_cal_valid ? g_loss_old / g_sc.n_check : NAN;
  if (g_have_cand) {
    uint8_t event = SC_SE_REJECTED, reason = SC_SR_NOT_BETTER;
    if (g_cal_valid ? 4.0f * g_loss_new < 3.0f * g_loss_old : g_loss_new < SC_ACCEPT_LOSS * g_sc.n_check) {
      reason = g_cal_valid ? SC_SR_BEATS_IN_FORCE : SC_SR_NO_CAL_IN_FORCE;
      if (store_calibration(g_sc.cand, SC_ORIGIN_BOARD) == 0) event = SC_SE_ACCEPTED;
      else reason = SC_SR_EEPROM_FAILED;
    } else if (!g_cal_valid) {
      reason = SC_SR_TOO_POOR;
    }
    announce(event, reason, cells);
  }
  ScSphereFit f;
  uint32_t t0 = micros();
  bool ok = sc_sphere_fit(g_sums, g_mag_scale, f);
  g_sc.fit_cycles = (micros() - t0) * 16;
  // A fit that does not even match its own window (a magnet went by) is no candidate, and its
  // centre would skew the next window's cells.
  uint8_t why = ok ? SC_SR_TOO_POOR : SC_SR_UNDETERMINED;
  ok = ok && f.cost < SC_ACCEPT_LOSS;
  g_sc.n_fit = g_sums.n;
  g_sc.fit_cost = f.cost;
  g_have_cand = ok;
  // cal_id of a board fit: 0xB000 + a 12-bit counter
  sc_cal_from_sphere(g_sc.cand, 0xB000 | ((g_sc.cand.cal_id + 1) & 0x0FFF), f.b, ok ? f.R : 0.0f);
  if (ok) {
    memcpy(g_mask_c, f.b, sizeof f.b);
    g_mask_r = f.R;
  }
  g_sc.n_check = 0;
  g_loss_new = g_loss_old = 0.0f;
  g_sc.loss_new = g_sc.loss_old = NAN;
  announce(ok ? SC_SE_FITTED : SC_SE_FIT_FAILED, ok ? SC_SR_NONE : why, cells);
  sc_sums_reset(g_sums);
  g_sums_since = 0;
  g_proc_us = g_proc_n = 0;
  memset(g_mask, 0, sizeof g_mask);
}

// Per magnetometer sample m (uT), after it was summed: coverage cell and held-out scores.
// Returns true when the window is complete.
static __attribute__((noinline)) bool selfcal_sample(const float m[3]) {
  if (!g_have_cand && (g_sums.n & 63) == 0) {
    // No candidate yet: count cells about the Kasa centre of the window so far (the Gauss-Newton
    // iterations here would hold the loop long enough to cost ~4 % of the 5 ms polls), and start
    // again when that centre moves by more than an eighth of the radius.
    ScSphereFit f;
    if (sc_sphere_fit(g_sums, g_mag_scale, f, 0)) {
      float d2 = 0.0f;
      for (uint8_t j = 0; j < 3; ++j) d2 += (f.b[j] - g_mask_c[j]) * (f.b[j] - g_mask_c[j]);
      if (64.0f * d2 > f.R * f.R) memset(g_mask, 0, sizeof g_mask);
      memcpy(g_mask_c, f.b, sizeof f.b);
      g_mask_r = f.R;
    }
  }
  if (g_mask_r == 0.0f) return false;
  float u[3];
  for (uint8_t j = 0; j < 3; ++j) u[j] = m[j] - g_mask_c[j];
  uint8_t cell = sc_cell(u);
  g_mask[cell >> 3] |= (uint8_t)(1 << (cell & 7));
  if (g_have_cand) {
    g_loss_new += sc_score(g_sc.cand, m);
    if (g_cal_valid) g_loss_old += sc_score(g_cal, m);
    ++g_sc.n_check;
  }
  return sc_mask_count(g_mask) >= SC_MASK_NEED;
}
#endif

static void emit_sample(const ScSample &s) {
  if (g_outputs & SC_OUT_SAMPLES) {
    send_body(SC_SAMPLE, &s, SC_SIZE_SAMPLE);
  }
  if (!(s.status & SC_ST_MAG_VALID)) return;
  float m[3];
  for (uint8_t i = 0; i < 3; ++i) m[i] = s.mag[i] * g_mag_scale[i];
  if (g_cal_valid && (g_outputs & SC_OUT_CALIBRATED)) {
    ScCalSample c;
    sc_cal_apply(g_cal, m, c.x);
    c.t_us = s.t_us;
    c.status = s.status;
    send_body(SC_CAL_SAMPLE, &c, SC_SIZE_CAL_SAMPLE);
  }
#ifndef SC_NO_SELFCAL
  uint32_t t0 = micros();
  sc_sums_add(g_sums, s.mag);
  bool done = selfcal_sample(m);
  g_proc_us += micros() - t0;
  ++g_proc_n;
#else
  sc_sums_add(g_sums, s.mag);
#endif
  if ((g_outputs & SC_OUT_SPHERE_SUMS) && g_sums_every && ++g_sums_since >= g_sums_every) {
    g_sums_since = 0;
    send_sums();
  }
#ifndef SC_NO_SELFCAL
  if (done) window_end();
#endif
}

void setup() {
  sc_uart_begin(BAUD);
  sc_twi_begin();
  sc_decoder_init(g_rx, g_rx_buf, sizeof g_rx_buf);
  sc_sums_reset(g_sums);
  sensor_setup();
  load_calibration();
  g_outputs = SC_OUT_SAMPLES | SC_OUT_CALIBRATED | SC_OUT_SPHERE_SUMS;
  g_streaming = true;
  send_hello();
  g_next_due = micros();
}

void loop() {
  for (int16_t c; (c = sc_uart_get()) >= 0;) {
    int16_t n = sc_decoder_feed(g_rx, (uint8_t)c);
    if (n > 0) handle_frame(n);
  }
  if (!g_streaming) return;
  ScSample s;
  if (g_have_held) {
    s = g_held;
    g_have_held = false;
  } else if ((int32_t)(micros() - g_next_due) >= 0) {
    advance_schedule();
    read_sample(s);
  } else {
    return;
  }
  emit_sample(s);
}

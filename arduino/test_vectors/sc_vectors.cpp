// Host-side check of sc_protocol.h (the sketch's codec) against the Python encoder.
// Build: g++ -std=c++11 -Wall -Wextra -O1 -o sc_vectors sc_vectors.cpp
// Reads commands on stdin, one per line; every number is a decimal integer and every float is
// passed as its IEEE-754 binary32 bit pattern (so nothing is lost in text):
//   enc TYPE SEQ V1 V2 ...   -> the wire frame (hex, delimiter included)
//   dec HEX                  -> "TYPE SEQ V1 V2 ..." for the first frame in HEX, or "ERR <what>"
//   acc X Y Z X Y Z ...      -> the SPHERE_SUMS body values after adding these mag samples
//   app K6 B3 M3             -> the three float bits of x = K^-1 (m - b) (sc_cal_apply)
//   chk K6 B3 ID             -> "<crc> <sc_cal_check reason with that crc>"
//   fit SCALE3 SUMS29        -> "OK B3 R COST ITERS" (float bits) of sc_sphere_fit, or "FAIL"
//   cel U3 ...               -> the sc_cell index of each direction u (float bits)
//   scr K6 B3 M3             -> float bits of sc_score (held-out loss of m under K, b)
// tests/test_arduino_build.py drives it with arduino/test_vectors/vectors.json.
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include <string>
#include <vector>

#include "../streamcal_bridge/sc_protocol.h"
#include "../streamcal_bridge/sc_selfcal.h"

typedef std::vector<long long> Values;

static float f_of(long long bits) { uint32_t u = (uint32_t)bits; float f; memcpy(&f, &u, 4); return f; }
static long long bits_of(float f) { uint32_t u; memcpy(&u, &f, 4); return (long long)u; }

static bool encode(int type, int seq, const Values &v, uint8_t *buf, uint16_t *len) {
  ScWriter w = sc_begin(buf, (uint8_t)type, (uint16_t)seq);
  size_t i = 0, need = 0;
  switch (type) {
    case SC_HELLO: need = 13; break;
    case SC_SAMPLE: need = 12; break;
    case SC_CAL_SAMPLE: need = 5; break;
    case SC_SPHERE_SUMS: need = 29; break;
    case SC_CAL_REPORT: need = 12; break;
    case SC_SET_CAL: need = 11; break;
    case SC_ACK: need = 2; break;
    case SC_NAK: need = 3; break;
    case SC_START: need = 3; break;
    case SC_SELF_CAL: need = 23; break;
    case SC_GET_INFO: case SC_STOP: case SC_QUERY_CAL: case SC_CLEAR_CAL: need = 0; break;
    default: return false;
  }
  if (v.size() != need) return false;
  switch (type) {
    case SC_HELLO: {
      ScHello h;
      h.fw_major = v[i++]; h.fw_minor = v[i++]; h.whoami = v[i++]; h.ak_wia = v[i++];
      h.flags = v[i++]; h.period_us = v[i++];
      h.accel_scale = f_of(v[i++]); h.gyro_scale = f_of(v[i++]);
      h.temp_scale = f_of(v[i++]); h.temp_offset = f_of(v[i++]);
      for (int j = 0; j < 3; ++j) h.mag_scale[j] = f_of(v[i++]);
      sc_put_hello(w, h); break;
    }
    case SC_SAMPLE: {
      ScSample s;
      s.t_us = v[i++];
      for (int j = 0; j < 3; ++j) s.mag[j] = v[i++];
      for (int j = 0; j < 3; ++j) s.accel[j] = v[i++];
      for (int j = 0; j < 3; ++j) s.gyro[j] = v[i++];
      s.temp = v[i++]; s.status = v[i++];
      sc_put_sample(w, s); break;
    }
    case SC_CAL_SAMPLE: {
      ScCalSample c;
      c.t_us = v[i++];
      for (int j = 0; j < 3; ++j) c.x[j] = f_of(v[i++]);
      c.status = v[i++];
      sc_put_cal_sample(w, c); break;
    }
    case SC_SPHERE_SUMS: {
      ScSums s;
      s.n = v[i++]; s.rejected = v[i++];
      for (int j = 0; j < 3; ++j) s.center[j] = v[i++];
      for (int j = 0; j < 3; ++j) s.s1[j] = v[i++];
      for (int j = 0; j < 6; ++j) s.s2[j] = v[i++];
      for (int j = 0; j < 9; ++j) s.s3[j] = v[i++];
      for (int j = 0; j < 6; ++j) s.s4[j] = v[i++];
      sc_put_sums(w, s); break;
    }
    case SC_CAL_REPORT: case SC_SET_CAL: {
      if (type == SC_CAL_REPORT) sc_put_u8(w, (uint8_t)v[i++]);
      ScCal c;
      c.cal_id = v[i++];
      for (int j = 0; j < 6; ++j) c.k[j] = f_of(v[i++]);
      for (int j = 0; j < 3; ++j) c.b[j] = f_of(v[i++]);
      c.crc = v[i++];
      sc_put_cal(w, c); break;
    }
    case SC_ACK: case SC_NAK:
      sc_put_u8(w, v[0]); sc_put_u16(w, v[1]);
      if (type == SC_NAK) sc_put_u8(w, v[2]);
      break;
    case SC_START: {
      ScStart s; s.outputs = v[0]; s.period_us = v[1]; s.sums_every = v[2];
      sc_put_start(w, s); break;
    }
    case SC_SELF_CAL: {
      ScSelfCal f;
      f.event = v[i++]; f.reason = v[i++]; f.origin = v[i++]; f.in_force_id = v[i++]; f.cells = v[i++];
      f.n_fit = v[i++]; f.n_check = v[i++];
      f.fit_cost = f_of(v[i++]); f.loss_new = f_of(v[i++]); f.loss_old = f_of(v[i++]);
      f.fit_cycles = v[i++]; f.sample_cycles = v[i++];
      f.cand.cal_id = v[i++];
      for (int j = 0; j < 6; ++j) f.cand.k[j] = f_of(v[i++]);
      for (int j = 0; j < 3; ++j) f.cand.b[j] = f_of(v[i++]);
      f.cand.crc = v[i++];
      sc_put_self_cal(w, f); break;
    }
  }
  *len = sc_finish(buf, w);
  return true;
}

static void print_sums(const ScSums &s) {
  printf("%lu %lu", (unsigned long)s.n, (unsigned long)s.rejected);
  for (int j = 0; j < 3; ++j) printf(" %d", s.center[j]);
  for (int j = 0; j < 3; ++j) printf(" %lld", (long long)s.s1[j]);
  for (int j = 0; j < 6; ++j) printf(" %lld", (long long)s.s2[j]);
  for (int j = 0; j < 9; ++j) printf(" %lld", (long long)s.s3[j]);
  for (int j = 0; j < 6; ++j) printf(" %lld", (long long)s.s4[j]);
}

static void print_cal(const ScCal &c) {
  printf(" %u", c.cal_id);
  for (int j = 0; j < 6; ++j) printf(" %lld", bits_of(c.k[j]));
  for (int j = 0; j < 3; ++j) printf(" %lld", bits_of(c.b[j]));
  printf(" %u", c.crc);
}

static int expected_size(int type) {
  switch (type) {
    case SC_HELLO: return SC_SIZE_HELLO;
    case SC_SAMPLE: return SC_SIZE_SAMPLE;
    case SC_CAL_SAMPLE: return SC_SIZE_CAL_SAMPLE;
    case SC_SPHERE_SUMS: return SC_SIZE_SPHERE_SUMS;
    case SC_CAL_REPORT: return SC_SIZE_CAL_REPORT;
    case SC_SET_CAL: return SC_SIZE_CAL;
    case SC_ACK: return SC_SIZE_ACK;
    case SC_NAK: return SC_SIZE_NAK;
    case SC_START: return SC_SIZE_START;
    case SC_SELF_CAL: return SC_SIZE_SELF_CAL;
    case SC_GET_INFO: case SC_STOP: case SC_QUERY_CAL: case SC_CLEAR_CAL: return 0;
  }
  return -1;
}

static void decode(const std::string &hex) {
  static uint8_t rx[SC_MAX_PAYLOAD + 2];
  ScDecoder d;
  sc_decoder_init(d, rx, sizeof rx);
  for (size_t i = 0; i + 1 < hex.size(); i += 2) {
    int n = sc_decoder_feed(d, (uint8_t)strtol(hex.substr(i, 2).c_str(), NULL, 16));
    if (n <= 0) continue;
    ScReader r = {rx + SC_HEADER_SIZE};
    int version = rx[0], type = rx[1], seq = rx[2] | (rx[3] << 8);
    if (version != SC_PROTOCOL_VERSION) { printf("ERR version\n"); return; }
    if (n - SC_HEADER_SIZE != expected_size(type)) { printf("ERR length\n"); return; }
    printf("%d %d", type, seq);
    switch (type) {
      case SC_HELLO: {
        ScHello h; sc_get_hello(r, h);
        printf(" %u %u %u %u %u %lu %lld %lld %lld %lld", h.fw_major, h.fw_minor, h.whoami, h.ak_wia,
               h.flags, (unsigned long)h.period_us, bits_of(h.accel_scale), bits_of(h.gyro_scale),
               bits_of(h.temp_scale), bits_of(h.temp_offset));
        for (int j = 0; j < 3; ++j) printf(" %lld", bits_of(h.mag_scale[j]));
        break;
      }
      case SC_SAMPLE: {
        ScSample s; sc_get_sample(r, s);
        printf(" %lu", (unsigned long)s.t_us);
        for (int j = 0; j < 3; ++j) printf(" %d", s.mag[j]);
        for (int j = 0; j < 3; ++j) printf(" %d", s.accel[j]);
        for (int j = 0; j < 3; ++j) printf(" %d", s.gyro[j]);
        printf(" %d %u", s.temp, s.status);
        break;
      }
      case SC_CAL_SAMPLE: {
        ScCalSample c; sc_get_cal_sample(r, c);
        printf(" %lu", (unsigned long)c.t_us);
        for (int j = 0; j < 3; ++j) printf(" %lld", bits_of(c.x[j]));
        printf(" %u", c.status);
        break;
      }
      case SC_SPHERE_SUMS: { ScSums s; sc_get_sums(r, s); printf(" "); print_sums(s); break; }
      case SC_CAL_REPORT: { printf(" %u", sc_get_u8(r)); ScCal c; sc_get_cal(r, c); print_cal(c); break; }
      case SC_SET_CAL: { ScCal c; sc_get_cal(r, c); print_cal(c); break; }
      case SC_SELF_CAL: {
        ScSelfCal f; sc_get_self_cal(r, f);
        printf(" %u %u %u %u %u %lu %lu %lld %lld %lld %lu %lu", f.event, f.reason, f.origin, f.in_force_id,
               f.cells, (unsigned long)f.n_fit, (unsigned long)f.n_check, bits_of(f.fit_cost),
               bits_of(f.loss_new), bits_of(f.loss_old), (unsigned long)f.fit_cycles,
               (unsigned long)f.sample_cycles);
        print_cal(f.cand);
        break;
      }
      case SC_ACK: case SC_NAK: {
        unsigned t = sc_get_u8(r), s = sc_get_u16(r);
        printf(" %u %u", t, s);
        if (type == SC_NAK) printf(" %u", sc_get_u8(r));
        break;
      }
      case SC_START: {
        ScStart s; sc_get_start(r, s);
        printf(" %u %lu %u", s.outputs, (unsigned long)s.period_us, s.sums_every);
        break;
      }
    }
    printf("\n");
    return;
  }
  printf("ERR crc=%u cobs=%u truncated=%u oversized=%u\n", d.crc_errors, d.cobs_errors, d.truncated,
         d.oversized);
}

int main() {
  static char line[65536];
  while (fgets(line, sizeof line, stdin)) {
    char *save = NULL, *tok = strtok_r(line, " \t\r\n", &save);
    if (!tok) continue;
    std::string cmd = tok;
    Values v;
    std::string arg;
    while ((tok = strtok_r(NULL, " \t\r\n", &save))) {
      if (cmd == "dec") arg = tok; else v.push_back(strtoll(tok, NULL, 10));
    }
    if (cmd == "enc") {
      uint8_t buf[SC_FRAME_BUF(SC_MAX_PAYLOAD)];
      uint16_t len = 0;
      if (v.size() < 2 || !encode((int)v[0], (int)v[1], Values(v.begin() + 2, v.end()), buf, &len)) {
        printf("ERR bad enc arguments\n");
        continue;
      }
      for (uint16_t i = 0; i < len; ++i) printf("%02x", buf[i]);
      printf("\n");
    } else if (cmd == "dec") {
      decode(arg);
    } else if (cmd == "acc") {
      ScSums s; sc_sums_reset(s);
      for (size_t i = 0; i + 2 < v.size(); i += 3) {
        int16_t m[3] = {(int16_t)v[i], (int16_t)v[i + 1], (int16_t)v[i + 2]};
        sc_sums_add(s, m);
      }
      print_sums(s); printf("\n");
    } else if (cmd == "fit") {
      if (v.size() != 32) { printf("ERR fit needs 3 scales and 29 sums values\n"); continue; }
      float scale[3] = {f_of(v[0]), f_of(v[1]), f_of(v[2])};
      ScSums s;
      size_t i = 3;
      s.n = v[i++]; s.rejected = v[i++];
      for (int j = 0; j < 3; ++j) s.center[j] = v[i++];
      for (int j = 0; j < 3; ++j) s.s1[j] = v[i++];
      for (int j = 0; j < 6; ++j) s.s2[j] = v[i++];
      for (int j = 0; j < 9; ++j) s.s3[j] = v[i++];
      for (int j = 0; j < 6; ++j) s.s4[j] = v[i++];
      ScSphereFit f;
      if (!sc_sphere_fit(s, scale, f)) { printf("FAIL\n"); continue; }
      printf("OK %lld %lld %lld %lld %lld %u\n", bits_of(f.b[0]), bits_of(f.b[1]), bits_of(f.b[2]),
             bits_of(f.R), bits_of(f.cost), f.iters);
    } else if (cmd == "cel") {
      for (size_t i = 0; i + 2 < v.size(); i += 3) {
        float u[3] = {f_of(v[i]), f_of(v[i + 1]), f_of(v[i + 2])};
        printf(i ? " %u" : "%u", sc_cell(u));
      }
      printf("\n");
    } else if (cmd == "app" || cmd == "chk" || cmd == "scr") {
      ScCal c; memset(&c, 0, sizeof c);
      for (int j = 0; j < 6; ++j) c.k[j] = f_of(v.at(j));
      for (int j = 0; j < 3; ++j) c.b[j] = f_of(v.at(6 + j));
      if (cmd == "chk") {
        c.cal_id = (uint16_t)v.at(9);
        c.crc = sc_cal_crc(c);
        printf("%u %u\n", c.crc, sc_cal_check(c));
        continue;
      }
      float m[3] = {f_of(v.at(9)), f_of(v.at(10)), f_of(v.at(11))}, x[3];
      if (cmd == "scr") { printf("%lld\n", bits_of(sc_score(c, m))); continue; }
      sc_cal_apply(c, m, x);
      printf("%lld %lld %lld\n", bits_of(x[0]), bits_of(x[1]), bits_of(x[2]));
    } else {
      printf("ERR unknown command\n");
    }
    fflush(stdout);
  }
  return 0;
}

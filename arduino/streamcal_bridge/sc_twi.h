// sc_twi.h -- small blocking I2C master on the ATmega328P TWI (datasheet section 22), for the sketch's
// register reads and writes. Replaces the Arduino Wire library (interrupt-driven, buffered, with
// slave mode: ~2 KB flash and ~200 B RAM the sketch does not need). Every wait is bounded, so a
// missing or stuck device gives an error instead of a hang.
#ifndef SC_TWI_H
#define SC_TWI_H

#include <avr/interrupt.h>
#include <avr/io.h>

#define SC_TWI_HZ 400000UL
#define SC_TWI_SPINS 60000u  // polls of TWINT before giving up (one byte at 400 kHz is ~25 us, ~70 polls)

// TWSR status codes (ATmega328P datasheet tables 22-2, 22-3).
#define SC_TW_START 0x08
#define SC_TW_REP_START 0x10
#define SC_TW_MT_SLA_ACK 0x18
#define SC_TW_MT_DATA_ACK 0x28
#define SC_TW_MR_SLA_ACK 0x40
#define SC_TW_MR_DATA_ACK 0x50
#define SC_TW_MR_DATA_NACK 0x58

static void sc_twi_begin() {
  PORTC |= _BV(PORTC4) | _BV(PORTC5);   // internal pull-ups on SDA/SCL, as Wire.begin() sets
  TWSR = 0;                             // prescaler 1
  TWBR = (uint8_t)((F_CPU / SC_TWI_HZ - 16) / 2);
  TWCR = _BV(TWEN);
}

static volatile uint8_t sc_twi_status;   // TWSR of the last completed action, 0xFF while one runs

// TWINT is taken from this interrupt, not polled: simavr 1.6 (the firmware-in-the-loop tests) still
// shows TWINT set right after the write that clears it. Clearing TWIE (and leaving TWINT alone)
// stops the level-triggered interrupt until the next action.
ISR(TWI_vect) {
  sc_twi_status = TWSR & 0xF8;
  TWCR = _BV(TWEN);
}

// Run one bus action (TWINT|TWEN|TWIE plus `bits`), wait for it; the status, or 0 on time-out.
static __attribute__((noinline)) uint8_t sc_twi_do(uint8_t bits) {
  sc_twi_status = 0xFF;
  TWCR = _BV(TWINT) | _BV(TWEN) | _BV(TWIE) | bits;
  for (uint16_t n = SC_TWI_SPINS; n; --n)
    if (sc_twi_status != 0xFF) return sc_twi_status;
  return 0;
}

static void sc_twi_stop() {
  TWCR = _BV(TWINT) | _BV(TWEN) | _BV(TWSTO);
  for (uint16_t n = SC_TWI_SPINS; n && (TWCR & _BV(TWSTO)); --n) {}
}

// START (or repeated START) and the address byte; true if the device acknowledged.
static __attribute__((noinline)) bool sc_twi_address(uint8_t sla_rw) {
  uint8_t st = sc_twi_do(_BV(TWSTA));
  if (st != SC_TW_START && st != SC_TW_REP_START) return false;
  TWDR = sla_rw;
  st = sc_twi_do(0);
  // simavr 1.6 (Debian) reports an acknowledged SLA+W as 0x28 (data ACK); Wire's interrupt
  // handler treats 0x18 and 0x28 alike, and so does this (a real TWI never gives 0x28 here).
  return st == SC_TW_MT_SLA_ACK || st == SC_TW_MT_DATA_ACK || st == SC_TW_MR_SLA_ACK;
}

// Write `reg` then, if n > 0, the n bytes of `data`; stop unless `hold` (a read follows).
static __attribute__((noinline)) bool sc_twi_write(uint8_t addr, uint8_t reg, const uint8_t *data,
                                                   uint8_t n, bool hold) {
  bool ok = sc_twi_address((uint8_t)(addr << 1));
  if (ok) {
    TWDR = reg;
    ok = sc_twi_do(0) == SC_TW_MT_DATA_ACK;
  }
  for (uint8_t i = 0; ok && i < n; ++i) {
    TWDR = data[i];
    ok = sc_twi_do(0) == SC_TW_MT_DATA_ACK;
  }
  if (!ok || !hold) sc_twi_stop();
  return ok;
}

// Read n >= 1 bytes from register `reg` onwards (write the register, repeated START, read).
static __attribute__((noinline)) bool sc_twi_read(uint8_t addr, uint8_t reg, uint8_t *out, uint8_t n) {
  if (!sc_twi_write(addr, reg, 0, 0, true)) return false;
  bool ok = sc_twi_address((uint8_t)((addr << 1) | 1));
  for (uint8_t i = 0; ok && i < n; ++i) {
    bool more = i + 1 < n;
    ok = sc_twi_do(more ? _BV(TWEA) : 0) == (more ? SC_TW_MR_DATA_ACK : SC_TW_MR_DATA_NACK);
    out[i] = TWDR;
  }
  sc_twi_stop();
  return ok;
}

#endif  // SC_TWI_H

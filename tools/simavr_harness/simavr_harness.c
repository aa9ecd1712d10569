/*
 * simavr_harness -- run the compiled streamcal_bridge sketch (Arduino Uno, ATmega328P at 16 MHz)
 * in simavr with a register-level MPU-9250 (0x68) and AK8963 (0x0C) on its I2C bus, replaying
 * raw counts from a file, and its UART0 on a pseudo-terminal of its own.
 *
 * Copyright (C) 2024 the streamcal authors.
 *
 * This program is free software: you can redistribute it and/or modify it under the terms of
 * the GNU General Public License as published by the Free Software Foundation, either version 3
 * of the License, or (at your option) any later version. It links libsimavr (GPL-3+), so it is a
 * separate GPL-3 program, not part of the streamcal Python package. See COPYING.
 *
 *   simavr_harness FIRMWARE.elf REPLAY.bin [--eeprom FILE] [--stats FILE] [--tail SECONDS]
 *                  [--reset-at-eeprom-write N]
 *
 * Prints the slave pty path on stdout (one line; a second line "replay-end" when the replay and
 * its tail are over and real time begins), then waits for the host's first byte before
 * releasing the AVR from reset (an Uno resets when its port is opened, so the host sees the boot
 * HELLO). The AVR runs as fast as the host can take its output: the UART is modelled at its
 * baud rate in simulated time, and the simulation stalls while more than OUT_HIGH_WATER bytes
 * wait for the pty. Once simulated time passes the end of the replay plus --tail seconds, the
 * AVR runs in real time (a board whose sensor has stopped changing: still answers commands,
 * idles the CPU). SIGTERM/SIGINT/SIGHUP end it cleanly: EEPROM saved (--eeprom), counters
 * written (--stats, JSON) and echoed on stderr. simavr's logger goes to stderr.
 *
 * Slave behaviour mirrors firmware_bridge/fake_mpu9250.py (clock mode), register facts from
 * HARDWARE.md sections 1-4: WHO_AM_I, PWR_MGMT_1 H_RESET/SLEEP, INT_PIN_CFG.BYPASS_EN (and
 * USER_CTRL.I2C_MST_EN clear) gating the AK8963, big-endian 14-byte accel/temp/gyro burst from
 * one instant, AK8963 WIA, ST1 DRDY/DOR, little-endian HXL..HZH, ST2 HOFL/BITM ending the read,
 * CNTL1 modes through power-down, fuse ROM readable in fuse-ROM mode, CNTL2 soft reset.
 *
 * EEPROM byte writes (EECR.EEPE strobes) are counted ("eeprom_writes" in the stats);
 * --reset-at-eeprom-write N resets the AVR right after the instruction that starts the N-th one
 * (a power glitch in the middle of an EEPROM update; the chips keep their state).
 *
 * Replay file (little-endian; written by firmware_bridge/simavr_board.py):
 *   "SCSIMRP1"  u32 n_acc n_gyr n_tmp n_mag  u8 whoami ak_wia has_mag asa[3] pad[2]
 *   i64 acc_cycle[n_acc]  i16 acc[n_acc][4 fs][3]      (raw counts per ACCEL_FS_SEL)
 *   i64 gyr_cycle[n_gyr]  i16 gyr[n_gyr][4 fs][3]      (raw counts per GYRO_FS_SEL)
 *   i64 tmp_cycle[n_tmp]  i16 tmp[n_tmp]
 *   i64 mag_cycle[n_mag]  i16 mag[n_mag][2][3]         ([0] 14-bit, [1] 16-bit; AK8963 axes)
 *                         u8 hofl[n_mag][2]
 * A row becomes the chip's current value at its cycle (16 MHz cycles since reset).
 */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <inttypes.h>
#include <poll.h>
#include <pty.h>
#include <signal.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include <simavr/avr_eeprom.h>
#include <simavr/avr_twi.h>
#include <simavr/avr_uart.h>
#include <simavr/sim_avr.h>
#include <simavr/sim_elf.h>
#include <simavr/sim_io.h>
#include <simavr/sim_irq.h>

#define F_CPU_HZ 16000000u
#define MCU_NAME "atmega328p"
#define EEPROM_SIZE 1024
#define BATCH_CYCLES 16000u          /* 1 ms of simulated time between I/O polls */
#define OUT_CAP (1u << 16)
#define OUT_HIGH_WATER 1024u         /* bytes waiting for the pty before the simulation stalls */
#define IN_CAP 4096u
#define UART_BYTE_CYCLES (F_CPU_HZ * 10u / 115200u)   /* 8N1 at 115200 baud */

/* MPU-9250 registers (HARDWARE.md §2, §3) */
#define MPU_ADDR 0x68
#define R_INT_PIN_CFG 0x37
#define R_INT_ENABLE 0x38
#define R_INT_STATUS 0x3A
#define R_ACCEL_XOUT_H 0x3B
#define R_TEMP_OUT_H 0x41
#define R_GYRO_XOUT_H 0x43
#define R_ACCEL_CONFIG 0x1C
#define R_GYRO_CONFIG 0x1B
#define R_USER_CTRL 0x6A
#define R_PWR_MGMT_1 0x6B
#define R_WHO_AM_I 0x75
#define IMU_BURST 14
/* AK8963 registers (HARDWARE.md §4) */
#define AK_ADDR 0x0C
#define AK_SIZE 0x13
#define A_WIA 0x00
#define A_INFO 0x01
#define A_ST1 0x02
#define A_HXL 0x03
#define A_ST2 0x09
#define A_CNTL1 0x0A
#define A_CNTL2 0x0B
#define A_ASTC 0x0C
#define A_I2CDIS 0x0F
#define A_ASAX 0x10
#define AK_INFO_VALUE 0x9A           /* undocumented content; the Python fake uses the same */
#define MODE_POWER_DOWN 0x0
#define MODE_CONT_8HZ 0x2
#define MODE_CONT_100HZ 0x6
#define MODE_FUSE_ROM 0xF

/* ---- replay data ---------------------------------------------------------------------------- */
typedef struct {
    uint32_t n;
    int64_t *cycle;
    int16_t *counts;   /* n x stride */
    uint8_t *hofl;     /* mag only: n x 2 */
} channel_t;

static struct {
    channel_t acc, gyr, tmp, mag;
    uint8_t whoami, ak_wia, has_mag, asa[3];
    int64_t last_cycle;
} R;

static void die(const char *fmt, ...) {
    va_list ap;
    va_start(ap, fmt);
    fputs("simavr_harness: ", stderr);
    vfprintf(stderr, fmt, ap);
    fputc('\n', stderr);
    va_end(ap);
    exit(2);
}

static void read_exact(FILE *f, void *p, size_t n, const char *what, const char *path) {
    if (n && fread(p, 1, n, f) != n) die("%s: truncated replay file (reading %s)", path, what);
}

static void read_channel(FILE *f, channel_t *c, size_t stride, const char *what, const char *path) {
    c->cycle = malloc(sizeof(int64_t) * (c->n ? c->n : 1));
    c->counts = malloc(sizeof(int16_t) * stride * (c->n ? c->n : 1));
    if (!c->cycle || !c->counts) die("out of memory for %u %s rows", c->n, what);
    read_exact(f, c->cycle, sizeof(int64_t) * c->n, what, path);
    read_exact(f, c->counts, sizeof(int16_t) * stride * c->n, what, path);
    for (uint32_t i = 1; i < c->n; ++i)
        if (c->cycle[i] < c->cycle[i - 1]) die("%s: %s times decrease at row %u", path, what, i);
    if (c->n && c->cycle[c->n - 1] > R.last_cycle) R.last_cycle = c->cycle[c->n - 1];
}

static void load_replay(const char *path) {
    FILE *f = fopen(path, "rb");
    if (!f) die("%s: cannot open replay file (%s)", path, strerror(errno));
    char magic[8];
    uint32_t n[4];
    uint8_t meta[8];
    read_exact(f, magic, 8, "magic", path);
    if (memcmp(magic, "SCSIMRP1", 8) != 0) die("%s: not a replay file (bad magic)", path);
    read_exact(f, n, sizeof n, "counts", path);
    read_exact(f, meta, sizeof meta, "header", path);
    R.acc.n = n[0]; R.gyr.n = n[1]; R.tmp.n = n[2]; R.mag.n = n[3];
    R.whoami = meta[0]; R.ak_wia = meta[1]; R.has_mag = meta[2];
    memcpy(R.asa, meta + 3, 3);
    read_channel(f, &R.acc, 12, "accel", path);
    read_channel(f, &R.gyr, 12, "gyro", path);
    read_channel(f, &R.tmp, 1, "temp", path);
    read_channel(f, &R.mag, 6, "mag", path);
    R.mag.hofl = malloc(2 * (R.mag.n ? R.mag.n : 1));
    if (!R.mag.hofl) die("out of memory");
    read_exact(f, R.mag.hofl, 2 * R.mag.n, "mag overflow flags", path);
    fclose(f);
}

/* Number of rows with cycle <= now (searchsorted side="right"). */
static uint32_t rows_until(const channel_t *c, int64_t now) {
    uint32_t lo = 0, hi = c->n;
    while (lo < hi) {
        uint32_t mid = lo + (hi - lo) / 2;
        if (c->cycle[mid] <= now) lo = mid + 1; else hi = mid;
    }
    return lo;
}

/* ---- the two chips ---------------------------------------------------------------------------- */
static struct {
    avr_t *avr;
    avr_irq_t *irq;           /* [0] to the AVR's TWI input, [1] from its TWI output */
    uint8_t mpu[128], ak[AK_SIZE];
    uint8_t mpu_ptr, ak_ptr;
    uint8_t selected;         /* 7-bit address of the addressed chip, 0 if none */
    uint32_t index;           /* bytes written since START (first is the register pointer) */
    uint8_t burst[IMU_BURST]; /* accel/temp/gyro registers latched at the START of a read */
    int64_t imu_seen;
    int64_t ak_k;             /* magnetometer row held in the data registers, -1 none */
    uint32_t ak_next;
    int drdy, dor, reading;
    /* counters (same names as FakeMPU9250Bus.counters) */
    uint64_t transactions, refused_absent, samples_latched, skipped, dor_reported, hofl, resets;
    uint64_t violations;
} B;

static int64_t now_cycle(void) { return (int64_t)B.avr->cycle; }

static void mpu_power_on(void) {
    memset(B.mpu, 0, sizeof B.mpu);
    B.mpu[R_PWR_MGMT_1] = 0x01;          /* reset values [RM p9] */
    B.mpu[R_WHO_AM_I] = R.whoami;
    B.imu_seen = -1;
}

static void ak_power_on(void) {
    memset(B.ak, 0, sizeof B.ak);
    B.ak[A_WIA] = R.ak_wia;
    B.ak[A_INFO] = AK_INFO_VALUE;
    B.ak_next = R.mag.n;                 /* nothing is measured until a continuous mode */
    B.ak_k = -1;
    B.drdy = B.dor = B.reading = 0;
}

static int ak_mode(void) { return B.ak[A_CNTL1] & 0x0F; }
static int ak_continuous(void) { return ak_mode() == MODE_CONT_8HZ || ak_mode() == MODE_CONT_100HZ; }

static int present(uint8_t addr7) {
    if (addr7 == MPU_ADDR) return 1;
    if (addr7 == AK_ADDR && R.has_mag)
        return (B.mpu[R_INT_PIN_CFG] & 0x02) && !(B.mpu[R_USER_CTRL] & 0x20);
    return 0;
}

static void ak_latch(int64_t k, uint64_t skipped) {
    if (B.drdy) skipped += 1;            /* the unread sample is overwritten */
    if (skipped) { B.dor = 1; B.skipped += skipped; }
    B.ak_k = k;
    B.drdy = 1;
    B.samples_latched += 1;
}

/* Latch the newest magnetometer row whose time has come (registers protected mid-read). */
static void ak_sync(void) {
    if (!R.has_mag || !ak_continuous() || B.reading) return;
    uint32_t end = rows_until(&R.mag, now_cycle());
    if (end > B.ak_next) {
        ak_latch((int64_t)end - 1, end - 1 - B.ak_next);
        B.ak_next = end;
    }
}

static uint8_t ak_wrap(uint8_t reg) {   /* auto-increment wraps inside 0x00-0x0C and 0x10-0x12 */
    if (reg <= 0x0C) return reg == 0x0C ? 0x00 : reg + 1;
    if (reg >= 0x10 && reg <= 0x12) return reg == 0x12 ? 0x10 : reg + 1;
    return (uint8_t)((reg + 1) % AK_SIZE);
}

static void ak_write(uint8_t reg, uint8_t v) {
    if (reg == A_CNTL2) {
        if (v & 0x01) ak_power_on();
        return;
    }
    if (reg == A_CNTL1) {
        int old = ak_mode(), mode = v & 0x0F;
        if (old != MODE_POWER_DOWN && mode != MODE_POWER_DOWN && mode != old) {
            B.violations += 1;           /* mode change without power-down: ignored */
            fprintf(stderr, "simavr_harness: AK8963 mode 0x%X -> 0x%X without power-down\n", old, mode);
            return;
        }
        B.ak[A_CNTL1] = v;
        if ((mode == MODE_CONT_8HZ || mode == MODE_CONT_100HZ) && old != mode)
            B.ak_next = rows_until(&R.mag, now_cycle());
        return;
    }
    if (reg == A_ASTC || reg == A_I2CDIS) B.ak[reg] = v;
    /* WIA, INFO, ST1, data, ST2, ASA are read-only */
}

static uint8_t ak_read(uint8_t reg) {
    int bits16 = (B.ak[A_CNTL1] & 0x10) != 0;
    uint8_t st2 = bits16 ? 0x10 : 0x00;  /* BITM mirrors CNTL1.BIT */
    int over = B.ak_k >= 0 && R.mag.hofl[2 * B.ak_k + bits16];
    if (over) st2 |= 0x08;               /* HOFL */
    if (reg == A_ST1) {
        if (B.dor) B.dor_reported += 1;
        return (B.drdy ? 0x01 : 0) | (B.dor ? 0x02 : 0);
    }
    if (reg >= A_HXL && reg < A_ST2) {
        B.reading = 1;
        if (B.ak_k < 0) return 0;
        uint16_t c = (uint16_t)R.mag.counts[6 * B.ak_k + 3 * bits16 + (reg - A_HXL) / 2];
        return (reg - A_HXL) % 2 ? (uint8_t)(c >> 8) : (uint8_t)c;   /* little-endian */
    }
    if (reg == A_ST2) {                  /* data read end */
        if (B.drdy && over) B.hofl += 1;
        B.drdy = B.dor = B.reading = 0;
        return st2;
    }
    if (reg >= A_ASAX && reg <= A_ASAX + 2) {
        if (ak_mode() == MODE_FUSE_ROM) return R.asa[reg - A_ASAX];
        B.violations += 1;
        fprintf(stderr, "simavr_harness: AK8963 fuse ROM read outside fuse-ROM mode\n");
        return B.ak[reg];
    }
    return reg < AK_SIZE ? B.ak[reg] : 0;
}

static void mpu_latch_burst(void) {       /* one sampling instant for the whole burst */
    memset(B.burst, 0, sizeof B.burst);
    if (B.mpu[R_PWR_MGMT_1] & 0x40) return;    /* SLEEP: data registers read 0 */
    int64_t now = now_cycle();
    int afs = (B.mpu[R_ACCEL_CONFIG] >> 3) & 3, gfs = (B.mpu[R_GYRO_CONFIG] >> 3) & 3;
    int16_t v[7] = {0};
    int64_t k = (int64_t)rows_until(&R.acc, now) - 1;
    if (k >= 0) for (int i = 0; i < 3; ++i) v[i] = R.acc.counts[12 * k + 3 * afs + i];
    k = (int64_t)rows_until(&R.tmp, now) - 1;
    if (k >= 0) v[3] = R.tmp.counts[k];
    k = (int64_t)rows_until(&R.gyr, now) - 1;
    if (k >= 0) for (int i = 0; i < 3; ++i) v[4 + i] = R.gyr.counts[12 * k + 3 * gfs + i];
    for (int i = 0; i < 7; ++i) {         /* big-endian */
        B.burst[2 * i] = (uint8_t)((uint16_t)v[i] >> 8);
        B.burst[2 * i + 1] = (uint8_t)v[i];
    }
}

static void mpu_write(uint8_t reg, uint8_t v) {
    if (reg == R_PWR_MGMT_1 && (v & 0x80)) { mpu_power_on(); return; }   /* H_RESET self-clears */
    if (reg == R_WHO_AM_I || reg == R_INT_STATUS ||
        (reg >= R_ACCEL_XOUT_H && reg < R_ACCEL_XOUT_H + IMU_BURST)) return;  /* read-only */
    B.mpu[reg] = v;
}

static uint8_t mpu_read(uint8_t reg) {
    if (reg >= R_ACCEL_XOUT_H && reg < R_ACCEL_XOUT_H + IMU_BURST) return B.burst[reg - R_ACCEL_XOUT_H];
    if (reg == R_INT_STATUS) {
        const channel_t *clk = R.acc.n ? &R.acc : &R.gyr;
        int64_t k = (int64_t)rows_until(clk, now_cycle()) - 1;
        int ready = k > B.imu_seen && (B.mpu[R_INT_ENABLE] & 0x01);
        B.imu_seen = k;                   /* cleared by this read */
        return ready ? 0x01 : 0x00;
    }
    return B.mpu[reg & 0x7F];
}

/* Messages from the AVR's TWI master (avr_twi.c): START carries the 8-bit address, each data
 * byte a WRITE or READ; the slave answers at once by raising ACK (or READ with the data). */
static void twi_hook(struct avr_irq_t *irq, uint32_t value, void *param) {
    (void)irq; (void)param;
    avr_twi_msg_irq_t m;
    m.u.v = value;
    if (m.u.twi.msg & TWI_COND_STOP) B.selected = 0;
    if (m.u.twi.msg & TWI_COND_START) {
        uint8_t addr7 = m.u.twi.addr >> 1, is_read = m.u.twi.addr & 1;
        B.selected = 0;
        B.index = 0;
        B.transactions += 1;
        ak_sync();                        /* every transaction moves the chips to "now" */
        if (!present(addr7)) {            /* no ACK: the master sees a NACK */
            if (addr7 == MPU_ADDR || addr7 == AK_ADDR) B.refused_absent += 1;
            return;
        }
        B.selected = addr7;
        if (is_read && addr7 == MPU_ADDR) mpu_latch_burst();
        avr_raise_irq(B.irq + TWI_IRQ_INPUT, avr_twi_irq_msg(TWI_COND_ACK, m.u.twi.addr, 1));
        return;
    }
    if (!B.selected) return;
    if (m.u.twi.msg & TWI_COND_WRITE) {
        avr_raise_irq(B.irq + TWI_IRQ_INPUT, avr_twi_irq_msg(TWI_COND_ACK, m.u.twi.addr, 1));
        uint8_t d = m.u.twi.data;
        if (B.selected == MPU_ADDR) {
            if (B.index++ == 0) B.mpu_ptr = d & 0x7F;
            else { mpu_write(B.mpu_ptr, d); B.mpu_ptr = (B.mpu_ptr + 1) & 0x7F; }
        } else {
            if (B.index++ == 0) B.ak_ptr = d % AK_SIZE;
            else { ak_write(B.ak_ptr, d); B.ak_ptr = ak_wrap(B.ak_ptr); }
        }
    }
    if (m.u.twi.msg & TWI_COND_READ) {
        uint8_t d;
        if (B.selected == MPU_ADDR) { d = mpu_read(B.mpu_ptr); B.mpu_ptr = (B.mpu_ptr + 1) & 0x7F; }
        else { d = ak_read(B.ak_ptr); B.ak_ptr = ak_wrap(B.ak_ptr); }
        avr_raise_irq(B.irq + TWI_IRQ_INPUT, avr_twi_irq_msg(TWI_COND_READ, m.u.twi.addr, d));
    }
}

static const char *twi_irq_names[2] = {"8>mpu9250.out", "32<mpu9250.in"};

static void chips_attach(avr_t *avr) {
    B.avr = avr;
    B.irq = avr_alloc_irq(&avr->irq_pool, 0, 2, twi_irq_names);
    avr_irq_register_notify(B.irq + TWI_IRQ_OUTPUT, twi_hook, NULL);
    avr_connect_irq(B.irq + TWI_IRQ_INPUT, avr_io_getirq(avr, AVR_IOCTL_TWI_GETIRQ(0), TWI_IRQ_INPUT));
    avr_connect_irq(avr_io_getirq(avr, AVR_IOCTL_TWI_GETIRQ(0), TWI_IRQ_OUTPUT), B.irq + TWI_IRQ_OUTPUT);
    mpu_power_on();
    ak_power_on();
}

/* ---- UART0 <-> pty ------------------------------------------------------------------------------ */
static struct {
    int master, slave;
    uint8_t out[OUT_CAP];
    uint32_t out_len;
    uint8_t in[IN_CAP];
    uint32_t in_head, in_len;
    avr_irq_t *uart_in;
    int xoff;
    uint64_t tx_bytes, tx_delimiters, rx_bytes, out_overflow;
} U;

static void uart_out_hook(struct avr_irq_t *irq, uint32_t value, void *param) {
    (void)irq; (void)param;
    U.tx_bytes += 1;
    if ((uint8_t)value == 0) U.tx_delimiters += 1;   /* one per frame: COBS leaves no zero inside */
    if (U.out_len < OUT_CAP) U.out[U.out_len++] = (uint8_t)value;
    else U.out_overflow += 1;             /* cannot happen: the simulation stalls well before */
}
static void uart_xon_hook(struct avr_irq_t *irq, uint32_t value, void *param) {
    (void)irq; (void)value; (void)param; U.xoff = 0;
}
static void uart_xoff_hook(struct avr_irq_t *irq, uint32_t value, void *param) {
    (void)irq; (void)value; (void)param; U.xoff = 1;
}

/* Host bytes enter the AVR at most one per byte time of the line, as on a real 115200 link. */
static avr_cycle_count_t uart_feed_timer(avr_t *avr, avr_cycle_count_t when, void *param) {
    (void)avr; (void)param;
    if (U.in_len && !U.xoff) {
        uint8_t b = U.in[U.in_head];
        U.in_head = (U.in_head + 1) % IN_CAP;
        U.in_len -= 1;
        U.rx_bytes += 1;
        avr_raise_irq(U.uart_in, b);
    }
    return when + UART_BYTE_CYCLES;
}

static void pty_open(void) {
    struct termios tio;
    char name[256];
    memset(&tio, 0, sizeof tio);
    cfmakeraw(&tio);
    cfsetispeed(&tio, B115200);
    cfsetospeed(&tio, B115200);
    if (openpty(&U.master, &U.slave, name, &tio, NULL) != 0) die("openpty: %s", strerror(errno));
    int fl = fcntl(U.master, F_GETFL);
    fcntl(U.master, F_SETFL, fl | O_NONBLOCK);
    /* The slave stays open here too, so the master never sees a hang-up between host opens. */
    printf("%s\n", name);
    fflush(stdout);
}

static void pty_read(void) {
    while (U.in_len < IN_CAP) {
        uint8_t buf[512];
        size_t room = IN_CAP - U.in_len;
        ssize_t n = read(U.master, buf, room < sizeof buf ? room : sizeof buf);
        if (n <= 0) return;
        for (ssize_t i = 0; i < n; ++i) U.in[(U.in_head + U.in_len + i) % IN_CAP] = buf[i];
        U.in_len += (uint32_t)n;
    }
}

static void pty_write(void) {
    if (!U.out_len) return;
    ssize_t n = write(U.master, U.out, U.out_len);
    if (n > 0) {
        memmove(U.out, U.out + n, U.out_len - (uint32_t)n);
        U.out_len -= (uint32_t)n;
    }
}

static void uart_attach(avr_t *avr) {
    uint32_t flags = 0;
    avr_ioctl(avr, AVR_IOCTL_UART_GET_FLAGS('0'), &flags);
    flags &= ~(uint32_t)(AVR_UART_FLAG_POLL_SLEEP | AVR_UART_FLAG_STDIO);   /* no sleeps, no stdout */
    avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &flags);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUTPUT), uart_out_hook, NULL);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XON), uart_xon_hook, NULL);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XOFF), uart_xoff_hook, NULL);
    U.uart_in = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_INPUT);
    /* Start feeding after 1 ms: the sketch enables its receiver first thing in setup(). */
    avr_cycle_timer_register(avr, F_CPU_HZ / 1000, uart_feed_timer, NULL);
}

/* ---- EEPROM writes ------------------------------------------------------------------------------ */
#define EECR_DATA_ADDR 0x3F                /* ATmega328P EECR: I/O 0x1F */
#define EECR_EEPE 0x02
static uint64_t g_ee_writes, g_ee_reset_at, g_resets_done;
static int g_reset_pending;

static void eecr_write_hook(avr_t *avr, avr_io_addr_t addr, uint8_t v, void *param) {
    (void)avr; (void)addr; (void)param;
    if (!(v & EECR_EEPE)) return;
    g_ee_writes += 1;
    if (g_ee_reset_at && g_ee_writes == g_ee_reset_at) g_reset_pending = 1;
}

/* ---- EEPROM file, stats, logging ---------------------------------------------------------------- */
static void eeprom_load(avr_t *avr, const char *path) {
    uint8_t buf[EEPROM_SIZE];
    FILE *f = fopen(path, "rb");
    if (!f) return;                       /* first run: erased EEPROM (0xFF) */
    size_t n = fread(buf, 1, sizeof buf, f);
    fclose(f);
    if (n != sizeof buf) die("%s: EEPROM image must be %d bytes, got %zu", path, EEPROM_SIZE, n);
    avr_eeprom_desc_t d = {.ee = buf, .offset = 0, .size = sizeof buf};
    avr_ioctl(avr, AVR_IOCTL_EEPROM_SET, &d);
}

static int write_atomic(const char *path, const void *data, size_t n) {
    char tmp[4096];
    snprintf(tmp, sizeof tmp, "%s.tmp.%d", path, (int)getpid());
    FILE *f = fopen(tmp, "wb");
    if (!f) return -1;
    int ok = fwrite(data, 1, n, f) == n;
    ok = (fflush(f) == 0) && ok && fsync(fileno(f)) == 0;
    ok = (fclose(f) == 0) && ok;
    if (!ok || rename(tmp, path) != 0) { unlink(tmp); return -1; }
    return 0;
}

static void eeprom_save(avr_t *avr, const char *path) {
    uint8_t buf[EEPROM_SIZE];
    avr_eeprom_desc_t d = {.ee = buf, .offset = 0, .size = sizeof buf};
    avr_ioctl(avr, AVR_IOCTL_EEPROM_GET, &d);
    if (write_atomic(path, buf, sizeof buf) != 0)
        fprintf(stderr, "simavr_harness: %s: cannot save EEPROM (%s)\n", path, strerror(errno));
}

static double wall_now(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec + ts.tv_nsec * 1e-9;
}

static void stats_write(avr_t *avr, const char *path, double wall_s, const char *state) {
    char js[2048];
    double sim_s = avr ? (double)avr->cycle / F_CPU_HZ : 0.0;
    snprintf(js, sizeof js,
             "{\"state\": \"%s\", \"cycles\": %" PRIu64 ", \"sim_s\": %.6f, \"wall_s\": %.3f, "
             "\"transactions\": %" PRIu64 ", \"refused_absent\": %" PRIu64 ", "
             "\"samples_latched\": %" PRIu64 ", \"skipped\": %" PRIu64 ", \"dor_reported\": %" PRIu64 ", "
             "\"hofl\": %" PRIu64 ", \"violations\": %" PRIu64 ", \"mag_rows\": %u, \"mag_next\": %u, "
             "\"uart_tx_bytes\": %" PRIu64 ", \"uart_tx_frames\": %" PRIu64 ", \"uart_rx_bytes\": %" PRIu64 ", \"out_overflow\": %" PRIu64 ", "
             "\"eeprom_writes\": %" PRIu64 ", \"resets\": %" PRIu64 "}\n",
             state, avr ? (uint64_t)avr->cycle : 0, sim_s, wall_s, B.transactions, B.refused_absent,
             B.samples_latched, B.skipped, B.dor_reported, B.hofl, B.violations, R.mag.n, B.ak_next,
             U.tx_bytes, U.tx_delimiters, U.rx_bytes, U.out_overflow, g_ee_writes, g_resets_done);
    fprintf(stderr, "simavr_harness: stats %s", js);
    if (path && write_atomic(path, js, strlen(js)) != 0)
        fprintf(stderr, "simavr_harness: %s: cannot write stats (%s)\n", path, strerror(errno));
}

static void log_to_stderr(avr_t *avr, const int level, const char *fmt, va_list ap) {
    (void)avr;
    if (level <= LOG_WARNING) vfprintf(stderr, fmt, ap);
}

static volatile sig_atomic_t g_stop;
static void on_signal(int sig) { (void)sig; g_stop = 1; }

/* ---- main ---------------------------------------------------------------------------------------- */
int main(int argc, char **argv) {
    const char *elf = NULL, *replay = NULL, *eeprom = NULL, *stats = NULL;
    double tail_s = 1.0;
    for (int i = 1; i < argc; ++i) {
        if (!strcmp(argv[i], "--eeprom") && i + 1 < argc) eeprom = argv[++i];
        else if (!strcmp(argv[i], "--stats") && i + 1 < argc) stats = argv[++i];
        else if (!strcmp(argv[i], "--tail") && i + 1 < argc) tail_s = atof(argv[++i]);
        else if (!strcmp(argv[i], "--reset-at-eeprom-write") && i + 1 < argc)
            g_ee_reset_at = strtoull(argv[++i], NULL, 10);
        else if (argv[i][0] == '-') die("unknown option %s", argv[i]);
        else if (!elf) elf = argv[i];
        else if (!replay) replay = argv[i];
        else die("unexpected argument %s", argv[i]);
    }
    if (!elf || !replay)
        die("usage: simavr_harness FIRMWARE.elf REPLAY.bin [--eeprom FILE] [--stats FILE] [--tail S]");

    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigaction(SIGTERM, &sa, NULL);
    sigaction(SIGINT, &sa, NULL);
    sigaction(SIGHUP, &sa, NULL);
    signal(SIGPIPE, SIG_IGN);
    avr_global_logger_set(log_to_stderr);

    load_replay(replay);
    elf_firmware_t fw;
    memset(&fw, 0, sizeof fw);
    if (elf_read_firmware(elf, &fw) != 0) die("%s: cannot read firmware", elf);
    snprintf(fw.mmcu, sizeof fw.mmcu, "%s", MCU_NAME);   /* Arduino ELFs carry no mcu section */
    fw.frequency = F_CPU_HZ;
    avr_t *avr = avr_make_mcu_by_name(fw.mmcu);
    if (!avr) die("simavr does not know %s", fw.mmcu);
    avr_init(avr);
    avr_load_firmware(avr, &fw);
    avr->frequency = F_CPU_HZ;
    if (eeprom) eeprom_load(avr, eeprom);
    chips_attach(avr);
    uart_attach(avr);
    avr_register_io_write(avr, EECR_DATA_ADDR, eecr_write_hook, NULL);
    pty_open();

    /* Held in reset until the host's first byte (as an Uno resets when its port opens). */
    while (!g_stop && U.in_len == 0) {
        struct pollfd p = {.fd = U.master, .events = POLLIN};
        if (poll(&p, 1, 100) > 0) pty_read();
    }

    const int64_t realtime_from = R.last_cycle + (int64_t)(tail_s * F_CPU_HZ);
    double t0 = wall_now(), rt_wall0 = 0.0;
    int64_t rt_cycle0 = -1;
    const char *state = "stopped";
    while (!g_stop) {
        pty_read();
        pty_write();
        if (U.out_len > OUT_HIGH_WATER) {      /* the host is behind: wait for it, keep time still */
            struct pollfd p = {.fd = U.master, .events = POLLOUT};
            poll(&p, 1, 50);
            continue;
        }
        if ((int64_t)avr->cycle >= realtime_from) {   /* after the replay: real time */
            if (rt_cycle0 < 0) {
                rt_cycle0 = (int64_t)avr->cycle;
                rt_wall0 = wall_now();
                printf("replay-end\n");   /* the host may stop reading once it has caught up */
                fflush(stdout);
            }
            double ahead = ((int64_t)avr->cycle - rt_cycle0) / (double)F_CPU_HZ - (wall_now() - rt_wall0);
            if (ahead > 0) {
                struct pollfd p = {.fd = U.master, .events = POLLIN};
                poll(&p, 1, (int)(ahead * 1000) + 1);
                continue;
            }
        }
        avr_cycle_count_t target = avr->cycle + BATCH_CYCLES;
        int st = cpu_Running;
        while (avr->cycle < target) {
            st = avr_run(avr);
            if (st == cpu_Done || st == cpu_Crashed) break;
            if (g_reset_pending) {
                g_reset_pending = 0;
                g_resets_done += 1;
                fprintf(stderr, "simavr_harness: reset after EEPROM write %" PRIu64 "\n", g_ee_writes);
                avr_reset(avr);
                /* avr_reset clears the cycle timers: start feeding host bytes again */
                U.xoff = 0;
                avr_cycle_timer_register(avr, F_CPU_HZ / 1000, uart_feed_timer, NULL);
            }
        }
        if (st == cpu_Done || st == cpu_Crashed) {
            state = st == cpu_Done ? "done" : "crashed";
            fprintf(stderr, "simavr_harness: AVR %s at cycle %" PRIu64 "\n", state, (uint64_t)avr->cycle);
            pty_write();
            break;
        }
    }
    if (eeprom) eeprom_save(avr, eeprom);
    stats_write(avr, stats, wall_now() - t0, state);
    close(U.master);
    close(U.slave);
    avr_terminate(avr);
    return strcmp(state, "crashed") == 0 ? 1 : 0;
}

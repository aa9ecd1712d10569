"""The AK8963 die of the fake (:mod:`firmware_bridge.fake_mpu9250`): its registers and the
measurement sequence.

Mode changes (CNTL1) must pass through power-down (else recorded as a violation and ignored);
CNTL2.SRST restores the power-on values; a continuous mode latches magnetometer rows into
HXL..HZH, setting ST1.DRDY, and ST1.DOR when a row was lost (skipped, or overwritten unread);
reading a data register protects them until ST2 is read, which clears DRDY/DOR; ST2.HOFL marks an
overflow, ST2.BITM the 16-bit output; the fuse ROM (ASAX..ASAZ) reads back only in fuse-ROM mode.
In step mode (no clock) an ST1 poll advances the bus to the next magnetometer row.
"""
from __future__ import annotations

import numpy as np

from . import registers as R

SIZE = 0x13
DEFAULT_INFO = 0x9A   # INFO content is undocumented; any constant will do


def wrap(register: int, i: int) -> int:
    """Address of the ``i``-th byte of a burst from ``register`` (bursts wrap inside a block)."""
    for lo, hi in R.AK_REGISTER_BLOCKS:
        if lo <= register <= hi:
            return lo + (register - lo + i) % (hi - lo + 1)
    return (register + i) % SIZE


class Ak8963Die:
    """Register logic of the AK8963 die of ``bus`` (its clock, replay, faults and counters)."""

    def __init__(self, bus):
        self.bus = bus
        self.power_on()

    def power_on(self) -> None:
        self.regs = bytearray(SIZE)
        self.regs[R.AkReg.WIA] = self.bus.ak_wia
        self.regs[R.AkReg.INFO] = DEFAULT_INFO
        self.next = len(self.bus.replay.mag_t)   # nothing is measured until a continuous mode
        self.k = -1                              # magnetometer row held in the data registers
        self.drdy = self.dor = self.reading = False

    def mode(self) -> int:
        return R.AK_MODE.get(self.regs[R.AkReg.CNTL1])

    def continuous(self) -> bool:
        return self.mode() in R.AK_CONTINUOUS_RATE_HZ

    def bits(self) -> int:
        return 16 if R.AK_BIT_16.get(self.regs[R.AkReg.CNTL1]) else 14

    def write(self, reg: int, value: int) -> None:
        if reg == R.AkReg.CNTL2:
            if R.AK_SRST.get(value):
                self.power_on()
            return
        if reg in (R.AkReg.CNTL1, R.AkReg.ASTC, R.AkReg.I2CDIS):
            if reg == R.AkReg.CNTL1:
                old, new = self.mode(), R.AK_MODE.get(value)
                if old != R.AkMode.POWER_DOWN and new not in (R.AkMode.POWER_DOWN, old):
                    self.bus.violations.append(f"AK8963 mode 0x{old:X} → 0x{new:X} without power-down")
                    return
                self.regs[reg] = value
                if new in R.AK_CONTINUOUS_RATE_HZ and old != new:
                    self.next = int(np.searchsorted(self.bus.replay.mag_t, self.bus.now(),
                                                    side="right"))
                return
            self.regs[reg] = value
        # WIA, INFO, ST1, data, ST2, ASA are read-only

    def latch(self, k: int, skipped: int) -> None:
        """Put magnetometer row k in the data registers; ``skipped`` rows were lost before it."""
        if self.drdy:
            skipped += 1               # the unread sample is overwritten
        if skipped:
            self.dor = True
            self.bus.counters.skipped += skipped
        self.k, self.drdy = k, True
        self.bus.counters.samples_latched += 1

    def latch_until(self, tau: float) -> None:
        if self.reading:
            return                     # registers are protected until ST2 is read
        end = int(np.searchsorted(self.bus.replay.mag_t, tau, side="right"))
        if end > self.next:
            self.latch(end - 1, end - 1 - self.next)
            self.next = end

    def step(self) -> None:
        """Step mode: an ST1 poll advances to the next magnetometer sample when measuring,
        else by one magnetometer period."""
        bus = self.bus
        mag_t = bus.replay.mag_t
        k = self.next
        if not self.continuous() or k >= len(mag_t) or self.reading:
            bus.advance_to(bus.now() + bus.step_dt)
            return
        if bus.faults.dor_rate and bus.rng.random() < bus.faults.dor_rate and k + 1 < len(mag_t):
            k += 1
        bus.advance_to(mag_t[k])
        if not self.continuous():      # a reset event at this instant stopped the AK8963
            return
        self.latch(k, k - self.next)
        self.next = k + 1

    def sample_bytes(self) -> tuple[bytes, int]:
        bits = self.bits()
        st2 = R.ST2_BITM if bits == 16 else 0
        if self.k < 0:
            return bytes(6), st2
        counts, over = self.bus.replay.mag_counts(bits)
        if over[self.k]:
            st2 |= R.ST2_HOFL
        return counts[self.k].tobytes(), st2

    def read(self, reg: int, length: int) -> list[int]:
        bus = self.bus
        regs = [wrap(reg, i) for i in range(length)]
        if regs[0] == R.AkReg.ST1 and not bus.clocked:
            self.step()
        view = bytearray(self.regs)
        view[R.AkReg.ST1] = (R.ST1_DRDY if self.drdy else 0) | (R.ST1_DOR if self.dor else 0)
        data, st2 = self.sample_bytes()
        view[R.AkReg.HXL:R.AkReg.HXL + 6] = data
        view[R.AkReg.ST2] = st2
        if self.mode() == R.AkMode.FUSE_ROM:
            view[R.AkReg.ASAX:R.AkReg.ASAX + 3] = bytes(bus.asa)
        elif any(r >= R.AkReg.ASAX for r in regs):
            bus.violations.append("AK8963 fuse ROM read outside fuse-ROM mode")
        out = [view[r] for r in regs]
        if R.AkReg.ST1 in regs and self.dor:
            bus.counters.dor_reported += 1
        if R.AkReg.ST2 in regs:
            if self.drdy and st2 & R.ST2_HOFL:
                bus.counters.hofl += 1
                bus.hofl_indices.append(self.k)
            self.drdy = self.dor = self.reading = False
        elif any(R.AkReg.HXL <= r < R.AkReg.ST2 for r in regs):
            self.reading = True
        return out

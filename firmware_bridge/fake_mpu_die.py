"""The MPU-9250 die of the fake (:mod:`firmware_bridge.fake_mpu9250`): its 128 registers.

H_RESET (PWR_MGMT_1) restores the power-on values; WHO_AM_I, the data registers and INT_STATUS
are read-only; INT_STATUS.RAW_DATA_RDY_INT is set when a new IMU row is due (and RAW_RDY_EN is
set) and cleared by reading it; the data registers hold the IMU row at the current track time,
big-endian, zeros while asleep (PWR_MGMT_1.SLEEP).
"""
from __future__ import annotations

import numpy as np

from . import registers as R

DATA = range(R.MpuReg.ACCEL_XOUT_H, R.MpuReg.ACCEL_XOUT_H + R.IMU_BURST_LEN)


class MpuDie:
    """Register logic of the MPU-9250 die of ``bus`` (its clock, replay and identity)."""

    def __init__(self, bus):
        self.bus = bus
        self.power_on()

    def power_on(self) -> None:
        self.regs = bytearray(128)
        for reg, value in R.MPU_RESET_VALUES.items():
            self.regs[reg] = value
        self.regs[R.MpuReg.WHO_AM_I] = self.bus.who_am_i
        self.regs[R.MpuReg.PWR_MGMT_1] = self.bus.power_on_pwr_mgmt_1
        self.seen = -1          # IMU row last reported by INT_STATUS

    def field(self, reg: int, bits: R.Field) -> int:
        """The bit field ``bits`` of register ``reg``."""
        return bits.get(self.regs[reg])

    def write(self, reg: int, value: int) -> None:
        if reg == R.MpuReg.PWR_MGMT_1 and R.H_RESET.get(value):
            self.power_on()            # H_RESET self-clears
            return
        if reg == R.MpuReg.WHO_AM_I or reg in DATA or reg == R.MpuReg.INT_STATUS:
            return                     # read-only
        self.regs[reg] = value

    def read(self, reg: int, length: int) -> list[int]:
        bus = self.bus
        regs = [(reg + i) & 0x7F for i in range(length)]
        view = bytearray(self.regs)
        data = any(r in DATA for r in regs)
        if data:
            bus.imu_step()             # step mode without magnetometer
        if R.MpuReg.INT_STATUS in regs:
            k = int(np.searchsorted(bus.imu_clock_t, bus.now(), side="right")) - 1
            ready = k > self.seen and R.RAW_RDY_EN.get(self.regs[R.MpuReg.INT_ENABLE])
            view[R.MpuReg.INT_STATUS] = R.RAW_DATA_RDY_INT.set(0, int(bool(ready)))
            self.seen = k                                    # cleared by this read
        if data:
            view[DATA.start:DATA.stop] = self.imu_bytes()
        return [view[r] for r in regs]

    def imu_bytes(self) -> bytes:
        if R.SLEEP.get(self.regs[R.MpuReg.PWR_MGMT_1]):
            return bytes(R.IMU_BURST_LEN)
        replay = self.bus.replay
        tau = self.bus.now()
        afs = R.ACCEL_FS_SEL.get(self.regs[R.MpuReg.ACCEL_CONFIG])
        gfs = R.GYRO_FS_SEL.get(self.regs[R.MpuReg.GYRO_CONFIG])
        out = np.zeros(7, dtype=np.int16)
        for (times, key, fs), cols in zip(
                ((replay.acc_t, "acc", afs), (replay.tmp_t, "tmp", 0), (replay.gyr_t, "gyr", gfs)),
                (slice(0, 3), slice(3, 4), slice(4, 7))):
            k = int(np.searchsorted(times, tau, side="right")) - 1
            if k >= 0:
                out[cols] = replay.imu_counts(key, fs)[k]
        return out.astype(R.IMU_DTYPE).tobytes()

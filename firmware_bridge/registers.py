"""The MPU-9250 / AK8963 register map as data.

Every constant cites the section of ``/work/shared/HARDWARE.md`` it comes from and, in brackets,
that page's datasheet code ([PS pN] product specification, [RM pN] register map, [AKM pN] AK8963
datasheet, [LNX-*] Linux inv_mpu6050 / ak8975 drivers). Nothing here does I/O: the driver
(:mod:`firmware_bridge.mpu9250`) and the fake chip (:mod:`firmware_bridge.fake_mpu9250`) both
read this table, so the encoding of one is the decoding of the other.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from streamcal.constants import GRAVITY

# --- Bus addresses (HARDWARE.md §1) -------------------------------------------------------------
MPU_ADDRESS_AD0_LOW = 0x68    # AD0 pin tied low [PS p12]
MPU_ADDRESS_AD0_HIGH = 0x69   # AD0 pin tied high [PS p12]
MPU_ADDRESSES = (MPU_ADDRESS_AD0_LOW, MPU_ADDRESS_AD0_HIGH)
AK8963_ADDRESS = 0x0C         # visible to the host only with INT_PIN_CFG.BYPASS_EN [PS p24]
SMBUS_BLOCK_MAX = 32          # bytes per SMBus I2C-block transfer [SMBUS2] (§3)


class MpuReg(IntEnum):
    """MPU-9250 register addresses (HARDWARE.md §2, §3) [RM p9], [LNX-H]."""

    SMPLRT_DIV = 0x19
    CONFIG = 0x1A
    GYRO_CONFIG = 0x1B
    ACCEL_CONFIG = 0x1C
    ACCEL_CONFIG2 = 0x1D
    INT_PIN_CFG = 0x37
    INT_ENABLE = 0x38
    INT_STATUS = 0x3A
    ACCEL_XOUT_H = 0x3B       # start of the 14-byte accel/temp/gyro burst (§3)
    TEMP_OUT_H = 0x41
    GYRO_XOUT_H = 0x43
    USER_CTRL = 0x6A
    PWR_MGMT_1 = 0x6B
    PWR_MGMT_2 = 0x6C
    WHO_AM_I = 0x75


class AkReg(IntEnum):
    """AK8963 register addresses (HARDWARE.md §4) [RM p47], [LNX-MAGN]."""

    WIA = 0x00
    INFO = 0x01
    ST1 = 0x02
    HXL = 0x03                # HXL..HZH little-endian, then ST2 (§4)
    ST2 = 0x09
    CNTL1 = 0x0A
    CNTL2 = 0x0B
    ASTC = 0x0C
    I2CDIS = 0x0F
    ASAX = 0x10               # ASAX..ASAZ: fuse ROM, readable in fuse-ROM mode only


REGISTER_NAMES = {
    MPU_ADDRESS_AD0_LOW: {int(r): r.name for r in MpuReg},
    MPU_ADDRESS_AD0_HIGH: {int(r): r.name for r in MpuReg},
    AK8963_ADDRESS: {int(r): r.name for r in AkReg},
}


def register_name(address: int, register: int) -> str:
    """Human name of a register, e.g. ``"PWR_MGMT_1 (0x6B) at 0x68"``."""
    name = REGISTER_NAMES.get(address, {}).get(register)
    label = f"{name} (0x{register:02X})" if name else f"register 0x{register:02X}"
    return f"{label} at 0x{address:02X}"


@dataclass(frozen=True)
class Field:
    """A bit field ``width`` bits wide starting at bit ``shift`` of register ``reg``."""

    reg: int
    shift: int
    width: int = 1

    @property
    def mask(self) -> int:
        return ((1 << self.width) - 1) << self.shift

    def get(self, byte: int) -> int:
        return (byte & self.mask) >> self.shift

    def set(self, byte: int, value: int) -> int:
        if not 0 <= value < (1 << self.width):
            raise ValueError(f"value {value} does not fit a {self.width}-bit field")
        return (byte & ~self.mask & 0xFF) | (value << self.shift)


# --- MPU-9250 fields (HARDWARE.md §2) -----------------------------------------------------------
DLPF_CFG = Field(MpuReg.CONFIG, 0, 3)                 # gyro/temp low-pass code [RM p43]
GYRO_FS_SEL = Field(MpuReg.GYRO_CONFIG, 3, 2)         # [LNX-H] FSR_SHIFT 3
GYRO_FCHOICE_B = Field(MpuReg.GYRO_CONFIG, 0, 2)      # 0 for normal DLPF operation
ACCEL_FS_SEL = Field(MpuReg.ACCEL_CONFIG, 3, 2)
A_DLPFCFG = Field(MpuReg.ACCEL_CONFIG2, 0, 3)
ACCEL_FCHOICE_B = Field(MpuReg.ACCEL_CONFIG2, 3, 1)
BYPASS_EN = Field(MpuReg.INT_PIN_CFG, 1)              # 0x02 [LNX-H] BIT_BYPASS_EN
RAW_RDY_EN = Field(MpuReg.INT_ENABLE, 0)              # [LNX-H], [KW]
RAW_DATA_RDY_INT = Field(MpuReg.INT_STATUS, 0)        # new accel/gyro data; cleared by reading
I2C_MST_EN = Field(MpuReg.USER_CTRL, 5)               # must be 0 for bypass [LNX-H]
H_RESET = Field(MpuReg.PWR_MGMT_1, 7)                 # 0x80, self-clearing [LNX-H]
SLEEP = Field(MpuReg.PWR_MGMT_1, 6)                   # 0x40
CLKSEL = Field(MpuReg.PWR_MGMT_1, 0, 3)

CLKSEL_INTERNAL = 0
CLKSEL_AUTO_PLL = 1            # PLL from the gyro when ready, else internal (recommended) [RM p9]

# Reset values: all registers are 0x00 except these [RM p9] (HARDWARE.md §1 notes).
MPU_RESET_VALUES = {MpuReg.PWR_MGMT_1: 0x01, MpuReg.WHO_AM_I: 0x71}

# DLPF_CFG / A_DLPFCFG code → approximate bandwidth, Hz; codes 0 and 7 bypass the 1 kHz path
# (HARDWARE.md §2) [IMUS], [KW].
DLPF_BANDWIDTH_HZ = {1: 184, 2: 92, 3: 41, 4: 20, 5: 10, 6: 5}
INTERNAL_RATE_HZ = 1000.0      # with the DLPF on [LNX-H] INV_MPU6050_INTERNAL_FREQ_HZ


def output_rate_hz(smplrt_div: int) -> float:
    """Accel/gyro output rate for a SMPLRT_DIV value with the DLPF on (HARDWARE.md §2)."""
    return INTERNAL_RATE_HZ / (1 + smplrt_div)


# --- Identity (HARDWARE.md §1) [LNX-H] ----------------------------------------------------------
@dataclass(frozen=True)
class ChipInfo:
    """What a WHO_AM_I value means for this driver."""

    name: str
    has_magnetometer: bool
    supported: bool = True


WHO_AM_I_TABLE = {
    0x71: ChipInfo("MPU-9250", True),
    0x73: ChipInfo("MPU-9255", True),
    0x70: ChipInfo("MPU-6500", False),                  # same accel/gyro, no AK8963
    0x68: ChipInfo("MPU-6050/6000/9150", False, supported=False),
    0x74: ChipInfo("MPU-6515", False, supported=False),
}
AK8963_WIA = 0x48              # [LNX-MAGN], [KW]

# --- Scales (HARDWARE.md §2 "Full-scale ranges") [PS p8], [PS p9] -------------------------------
STANDARD_GRAVITY = GRAVITY     # m/s² per g (CGPM 1901 definition)
GYRO_LSB_PER_DPS = (131.0, 65.5, 32.8, 16.4)          # index = GYRO_FS_SEL
GYRO_RANGE_DPS = (250, 500, 1000, 2000)
ACCEL_LSB_PER_G = (16384.0, 8192.0, 4096.0, 2048.0)   # index = ACCEL_FS_SEL
ACCEL_RANGE_G = (2, 4, 8, 16)


def accel_scale(fs_sel: int) -> float:
    """m/s² per LSB for ACCEL_FS_SEL ``fs_sel`` (0..3)."""
    return STANDARD_GRAVITY / ACCEL_LSB_PER_G[fs_sel]


def gyro_scale(fs_sel: int) -> float:
    """rad/s per LSB for GYRO_FS_SEL ``fs_sel`` (0..3)."""
    return math.radians(1.0) / GYRO_LSB_PER_DPS[fs_sel]


# Temperature (HARDWARE.md §3): °C = (raw − offset) / sensitivity + 21 [PS p12], [FORUM-RM p33].
TEMP_SENSITIVITY_LSB_PER_C = 333.87
TEMP_ROOM_OFFSET_LSB = 0.0
TEMP_ROOM_C = 21.0

# --- AK8963 (HARDWARE.md §4) --------------------------------------------------------------------
class AkMode(IntEnum):
    """CNTL1 MODE[3:0] [AKM p15], [LNX-AK]."""

    POWER_DOWN = 0x0
    SINGLE = 0x1
    CONTINUOUS_8HZ = 0x2       # continuous mode 1
    EXTERNAL_TRIGGER = 0x4
    CONTINUOUS_100HZ = 0x6     # continuous mode 2
    SELF_TEST = 0x8
    FUSE_ROM = 0xF


AK_MODE = Field(AkReg.CNTL1, 0, 4)
AK_BIT_16 = Field(AkReg.CNTL1, 4)                     # 1 = 16-bit output [LNX-MAGN] 0x10
AK_SRST = Field(AkReg.CNTL2, 0)                       # soft reset
ST1_DRDY = 0x01                # data ready [AKM p15]
ST1_DOR = 0x02                 # data overrun: at least one sample skipped
ST2_HOFL = 0x08                # magnetic sensor overflow: discard the sample [LNX-AK]
ST2_BITM = 0x10                # mirrors CNTL1.BIT
AK_CONTINUOUS_RATE_HZ = {AkMode.CONTINUOUS_8HZ: 8.0, AkMode.CONTINUOUS_100HZ: 100.0}
AK_REGISTER_BLOCKS = ((0x00, 0x0C), (0x10, 0x12))     # auto-increment wraps inside each [AKM p25]

MAG_FULL_SCALE_UT = 4912.0
MAG_FULL_SCALE_COUNTS = {16: 32760, 14: 8190}         # [RM p50], [LNX-AK]


def mag_scale(bits: int) -> float:
    """µT per LSB before sensitivity adjustment: 0.14994 (16-bit) or 0.59976 (14-bit) [RM p50]."""
    return MAG_FULL_SCALE_UT / MAG_FULL_SCALE_COUNTS[bits]


def asa_factor(asa) -> np.ndarray:
    """Sensitivity adjustment factor(s) from fuse-ROM ASA byte(s): Hadj = H·(ASA+128)/256 [LNX-AK]."""
    return (np.asarray(asa, dtype=float) + 128.0) / 256.0


# Fixed AK8963 → accel/gyro (body) axis remap: m_x = H_y, m_y = H_x, m_z = −H_z (HARDWARE.md §4
# "Axis orientation") [LNX-MAGN], [IMUS]. It is its own inverse.
AK_TO_BODY = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])

# --- Burst layouts (HARDWARE.md §3, §4) ---------------------------------------------------------
IMU_BURST_LEN = 14             # ax ay az temp gx gy gz, big-endian int16 from ACCEL_XOUT_H
IMU_DTYPE = np.dtype(">i2")
MAG_BURST_LEN = 8              # ST1, HXL..HZH little-endian int16, ST2, from ST1
MAG_DTYPE = np.dtype("<i2")

# --- Timing (HARDWARE.md §2, §4, §5) ------------------------------------------------------------
RESET_WAIT_S = 0.100           # after H_RESET / power-up [LNX-H] INV_MPU6050_POWER_UP_TIME
GYRO_STARTUP_S = 0.035         # from sleep [PS p8]
ACCEL_STARTUP_S = 0.020        # from sleep [PS p9]
AK_MODE_WAIT_S = 0.010         # between AK8963 mode changes [FABO], [KW]

"""Everything that touches a wire: the MPU-9250/AK8963 driver, fake buses, serial frames,
and sample sources that all yield :class:`SampleBlock`. Nothing here knows about fitting.

Heavier pieces (smbus2, pyserial) load on first use.
"""
from streamcal.samples import SampleBlock

_LAZY = {
    "MPU9250": "mpu9250", "DeviceError": "mpu9250", "DeviceIOError": "mpu9250",
    "WrongDeviceError": "mpu9250",
    "open_bus": "ports", "open_link": "ports", "open_i2c_source": "i2c_source", "I2CSource": "i2c_source",
    "FakeMPU9250Bus": "fake_mpu9250", "Faults": "fake_mpu9250",
    "SerialLink": "serial_link", "LinkError": "serial_link",
}

__all__ = ["SampleBlock", *_LAZY]


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    raise AttributeError(f"module 'firmware_bridge' has no attribute {name!r}")

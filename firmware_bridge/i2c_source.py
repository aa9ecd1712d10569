"""I²C sample source: an MPU-9250 driver polled at a rate, yielding :class:`SampleBlock`.

``open_bus("1")`` gives ``smbus2.SMBus(1)`` (``/dev/i2c-1``); ``open_bus("fake:TRACK.csv")`` gives
a :class:`~firmware_bridge.fake_mpu9250.FakeMPU9250Bus` replaying the track, so the same code path
runs on a Raspberry Pi and in a demo or test. ``open_i2c_source`` ties bus, driver and source.

Example::

    src = open_i2c_source("fake:log.csv")
    for block in src:              # SampleBlock: t s, mag µT, accel m/s², gyro rad/s, temp °C
        ...
"""
from __future__ import annotations

import logging
from typing import Callable, Iterator

from streamcal.errors import InputError

from . import registers as R
from .mpu9250 import MPU9250, DeviceIOError
from .ports import FAKE_PREFIX, open_bus
from streamcal.samples import SampleBlock

log = logging.getLogger(__name__)

class I2CSource:
    """Iterate :class:`SampleBlock` from an :class:`MPU9250` driver.

    Args:
        driver: an initialised driver.
        block_size: samples per block (a block may be shorter: timeout, outage, end of a fake).
        rate_hz: poll rate while no new sample is ready; default twice the sensor's rate
            (a rate below the magnetometer's 100 Hz loses samples, counted as overruns).
        block_timeout: seconds to wait for a full block before yielding what there is.
        max_outage_s: give up (re-raise the :class:`DeviceIOError`) when the sensor has not
            answered for this long; None = keep trying forever (a service).
        retry_interval_s: pause between attempts while the sensor is absent.
        source: label stored in each block (``"i2c:1:0x68"``).
        sleep, clock: injected; default the driver's.
    """

    def __init__(self, driver: MPU9250, *, block_size: int = 50, rate_hz: float | None = None,
                 block_timeout: float = 1.0,
                 max_outage_s: float | None = 30.0, retry_interval_s: float = 0.5,
                 source: str = "", sleep: Callable[[float], None] | None = None,
                 clock: Callable[[], float] | None = None):
        self.driver, self.block_size, self.block_timeout = driver, block_size, block_timeout
        if rate_hz is not None and not rate_hz > 0:
            raise InputError(f"--rate must be a positive number of Hz, got {rate_hz}")
        self.poll_s = None if rate_hz is None else 1.0 / rate_hz
        self.max_outage_s, self.retry_interval_s, self.source = max_outage_s, retry_interval_s, source
        self._sleep = sleep or driver._sleep
        self._clock = clock or driver.clock
        self.outages = 0

    def _finished(self) -> bool:
        return bool(getattr(self.driver.bus, "finished", False))

    def __iter__(self) -> Iterator[SampleBlock]:
        outage_since = None
        while True:
            try:
                block = self.driver.read_block(self.block_size, timeout=self.block_timeout,
                                               source=self.source, poll_s=self.poll_s)
            except DeviceIOError as e:
                now = self._clock()
                if outage_since is None:
                    outage_since = now
                    self.outages += 1
                    log.warning("sensor not answering (%s); retrying every %.1f s", e,
                                self.retry_interval_s)
                if self.max_outage_s is not None and now - outage_since > self.max_outage_s:
                    raise
                if self._finished():
                    return
                self._sleep(self.retry_interval_s)
                continue
            outage_since = None
            if len(block):
                yield block
            if len(block) < self.block_size and self._finished():
                return


def open_i2c_source(spec, address: int = R.MPU_ADDRESS_AD0_LOW, *, block_size: int = 50,
                    rate_hz: float | None = None, fake_kwargs: dict | None = None,
                    read_track=None, **driver_kwargs) -> I2CSource:
    """Bus from ``spec`` (see :func:`open_bus`), driver brought up, source ready to iterate.

    With a fake bus the driver's clock is the track's clock, so block times are track times;
    ``read_track`` reads its file (see :func:`firmware_bridge.ports.open_bus`).
    """
    bus = open_bus(spec, read_track=read_track, **(fake_kwargs or {}))
    fake = isinstance(spec, str) and spec.startswith(FAKE_PREFIX)
    if fake:
        driver_kwargs.setdefault("clock", bus.now)
        if (fake_kwargs or {}).get("clock") is None:
            driver_kwargs.setdefault("sleep", lambda s: None)   # step mode: time is the track's
    driver = MPU9250(bus, address, **driver_kwargs)
    label = spec if fake else f"i2c:{int(spec)}:0x{address:02X}"
    return I2CSource(driver, block_size=block_size, rate_hz=rate_hz, source=label)

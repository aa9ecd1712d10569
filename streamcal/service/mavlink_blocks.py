"""A flight controller over MAVLink as a service source (``--port mavlink:CONNECTION``).

The adapter of :class:`firmware_bridge.mavlink_link.MavlinkLink` to the source interface of
:mod:`streamcal.service.sources`: a silent or failed link raises :class:`SourceUnavailable`
(the service says so in its status and keeps calling ``read()``, which listens again or
reconnects); the counters give heartbeats, messages, lost messages (MAVLink sequence numbers),
garbage and link drops.
"""
from __future__ import annotations

import time

from .sources import SourceUnavailable

MAVLINK_PREFIX = "mavlink:"


def is_mavlink(spec) -> bool:
    return isinstance(spec, str) and spec.startswith(MAVLINK_PREFIX)


class MavlinkBlocks:
    """``spec``: ``mavlink:CONNECTION``; ``compass``: 0 RAW_IMU, 1 SCALED_IMU2, 2 SCALED_IMU3;
    ``baud``: a serial device's rate unless the connection ends in ``,BAUD``; ``silence_s``:
    how long the compass may be silent before the link counts as down."""

    def __init__(self, spec: str, *, compass: int = 0, baud: int = 115200,
                 block_size: int = 50, timeout: float = 0.2, silence_s: float = 3.0, link=None):
        from firmware_bridge.mavlink_link import COMPASS_MESSAGES, MavlinkLink

        self.link = link or MavlinkLink(spec, compass=compass, baud=baud, silence_s=silence_s)
        self.block_size, self.timeout = int(block_size), float(timeout)
        self.finished = False
        self.sensor = "mavlink magnetometer"
        self._pending = None
        self.description = (f"MAVLink {self.link.connection} ({COMPASS_MESSAGES[compass]} "
                            "magnetometer, mgauss x0.1 = uT)")

    def sleep(self, seconds: float) -> None:
        """Wait by listening: what arrives while the service backs off is kept for ``read()``
        (a UDP socket left unread would overflow and lose it)."""
        from firmware_bridge.mavlink_link import MavlinkSilent

        if self._pending is not None:
            time.sleep(seconds)
            return
        try:
            self._pending = self.link.read_block(self.block_size, timeout=seconds)
        except MavlinkSilent:
            pass

    def read(self):
        from firmware_bridge.mavlink_link import MavlinkSilent

        if self._pending is not None:
            block, self._pending = self._pending, None
            return block
        try:
            return self.link.read_block(self.block_size, timeout=self.timeout)
        except MavlinkSilent as exc:
            raise SourceUnavailable(str(exc)) from exc

    def counters(self) -> dict:
        out = self.link.stats.as_dict()
        out["autopilot"] = self.link.autopilot
        return out

    def close(self) -> None:
        self.link.close()

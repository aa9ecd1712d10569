"""The long-running side of streamcal: the Raspberry Pi daemon and the serial host.

- :mod:`.daemon` — :class:`Service`, the run loop (source → streaming calibrator → store and
  outputs; signals; systemd notifications).
- :mod:`.sources` — I²C and serial device adapters with bring-up and reconnection.
- :mod:`.mavlink_blocks` — a flight controller over MAVLink (``--port mavlink:…``).
- :mod:`.output` — calibrated samples as JSON lines on stdout and/or a local UNIX socket.
- :mod:`.notify` — the ``sd_notify`` protocol (READY, STATUS, WATCHDOG…).
- :mod:`.live_state`, :mod:`.http_page` — the ``--http`` live page (docs/live_page.md).

    from streamcal.service import Service, I2CBlocks, Outputs
"""
from __future__ import annotations

from .daemon import Service
from .notify import Notifier
from .output import Outputs, SocketOutput, StreamOutput, format_lines
from .sources import I2CBlocks, SerialBlocks, SourceUnavailable

__all__ = ["I2CBlocks", "Notifier", "Outputs", "SerialBlocks", "Service", "SocketOutput",
           "SourceUnavailable", "StreamOutput", "format_lines"]

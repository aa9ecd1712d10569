"""systemd notification protocol (``sd_notify``): READY, STATUS, WATCHDOG, RELOADING, STOPPING.

The protocol is one datagram of ``KEY=VALUE`` lines sent to the ``AF_UNIX`` socket named by
``$NOTIFY_SOCKET`` (a path, or ``@name`` for the abstract namespace). ``$WATCHDOG_USEC`` asks for
``WATCHDOG=1`` at least that often (we ping at half of it, as ``sd_watchdog_enabled(3)``
advises), and ``$WATCHDOG_PID``, when set, names the only process that should ping.

Standard library on purpose: the protocol is these few lines; ``sdnotify`` on PyPI has had no
release since 2017 and ``systemd-python`` needs libsystemd headers to build on the Pi. Outside
systemd (no ``$NOTIFY_SOCKET``) every call does nothing.

    notifier = Notifier()
    notifier.ready("calibration v3 in use")
    while running:
        notifier.tick()                   # WATCHDOG=1 when half the watchdog interval has passed
"""
from __future__ import annotations

import os
import socket
import time
from typing import Callable, Mapping


class Notifier:
    """Sends ``sd_notify`` messages; a no-op when not started by systemd with ``Type=notify``.

    Args:
        environ: where ``NOTIFY_SOCKET``/``WATCHDOG_USEC``/``WATCHDOG_PID`` are read (default
            ``os.environ``).
        clock: monotonic seconds (injected for tests).
    """

    def __init__(self, environ: Mapping[str, str] | None = None,
                 clock: Callable[[], float] = time.monotonic):
        env = os.environ if environ is None else environ
        self.address = _address(env.get("NOTIFY_SOCKET", ""))
        self.watchdog_interval = _watchdog_interval(env)
        self.clock = clock
        self.sent = 0
        self.errors = 0
        self._sock: socket.socket | None = None
        self._last_ping = -float("inf")

    @property
    def enabled(self) -> bool:
        return self.address is not None

    def send(self, **fields) -> bool:
        """Send ``KEY=value`` lines in one datagram (``send(READY=1, STATUS="…")``); True if sent."""
        if self.address is None:
            return False
        text = "\n".join(f"{k}={str(v).replace(chr(10), ' ')}" for k, v in fields.items())
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
                self._sock.setblocking(False)   # a full receiver queue must not stall the service
            self._sock.sendto(text.encode("utf-8", "replace"), self.address)
        except OSError:          # EAGAIN, systemd gone or restarting: never fatal for the service
            self.errors += 1
            return False
        self.sent += 1
        return True

    def ready(self, status: str | None = None) -> bool:
        return self.send(READY=1, **({"STATUS": status} if status else {}))

    def status(self, text: str) -> bool:
        return self.send(STATUS=text)

    def reloading(self) -> bool:
        return self.send(RELOADING=1, MONOTONIC_USEC=int(time.clock_gettime(time.CLOCK_MONOTONIC) * 1e6))

    def stopping(self, status: str | None = None) -> bool:
        return self.send(STOPPING=1, **({"STATUS": status} if status else {}))

    def tick(self) -> bool:
        """Ping the watchdog if half its interval has passed since the last ping."""
        if self.watchdog_interval is None:
            return False
        now = self.clock()
        if now - self._last_ping < self.watchdog_interval:
            return False
        self._last_ping = now
        return self.send(WATCHDOG=1)

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


def _address(value: str):
    if not value or value[0] not in "/@":
        return None          # unset, or a transport we do not speak (vsock:…)
    return "\0" + value[1:] if value[0] == "@" else value


def _watchdog_interval(env) -> float | None:
    """Half of ``WATCHDOG_USEC`` in seconds, or None when no watchdog is asked of this process."""
    try:
        usec = int(env.get("WATCHDOG_USEC", ""))
    except ValueError:
        return None
    pid = env.get("WATCHDOG_PID")
    if usec <= 0 or (pid and pid.strip() != str(os.getpid())):
        return None
    return usec / 2e6

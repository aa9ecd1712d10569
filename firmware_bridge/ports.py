"""Buses and serial ports by name, in the manner of pyserial's ``serial_for_url``.

``open_bus("1")`` is ``smbus2.SMBus(1)``; ``open_bus("fake:TRACK.csv", read_track=…)`` a
register-level fake MPU-9250 replaying the track. ``open_link("/dev/ttyACM0")`` is the host
side of the sketch on a real port; ``open_link("fake:TRACK.csv", read_track=…)`` the same
against a simulated board on a pseudo-terminal, ``simavr:TRACK.csv`` against the compiled
sketch in simavr. This package does not read track files: whoever names one passes the
``read_track`` callable that turns a path into a recording (``t``, ``columns``, ``metadata``).
"""
from __future__ import annotations

from typing import Callable

from streamcal.errors import InputError

from .fake_board import FakeBoard
from .fake_mpu9250 import FakeMPU9250Bus
from .serial_link import DEFAULT_BAUD, SerialLink
from .simavr_board import SimavrBoard

FAKE_PREFIX = "fake:"
SIMAVR_PREFIX = "simavr:"


def _read(read_track, path: str):
    if read_track is None:
        raise InputError(f"{path}: a simulated device replays a track; pass read_track "
                         "(e.g. streamcal.inputs.track.Track.read) to read it")
    return read_track(path)


def open_bus(spec, *, read_track: Callable[[str], object] | None = None, **fake_kwargs):
    """Open an I²C bus from a CLI-style spec.

    Args:
        spec: an int or digit string (``1`` → ``/dev/i2c-1`` via ``smbus2.SMBus``), or
            ``"fake:PATH.csv"`` for a register-level fake MPU-9250 replaying that track (a µT
            track, or a raw-count MPU-9250/AK8963 log: see :meth:`FakeMPU9250Bus.from_track`).
        read_track: reads the fake's track file into a recording (``t``, ``columns``,
            ``metadata``), e.g. ``streamcal.inputs.track.Track.read``; required for ``fake:``.
        fake_kwargs: passed to :meth:`FakeMPU9250Bus.from_track` (faults, clock, who_am_i…).

    Raises:
        InputError: a bad spec, a missing or inaccessible ``/dev/i2c-N``, or a fake track that
            cannot be read or replayed (the message names the file and what is wrong).
    """
    if isinstance(spec, str) and spec.startswith(FAKE_PREFIX):
        path = spec[len(FAKE_PREFIX):]
        if not path:
            raise InputError("--bus fake: needs a track file, e.g. fake:log.csv")
        return FakeMPU9250Bus.from_track(_read(read_track, path), **fake_kwargs)
    if isinstance(spec, int) or (isinstance(spec, str) and spec.strip().isdigit()):
        number = int(spec)
        from smbus2 import SMBus
        try:
            return SMBus(number)
        except FileNotFoundError as e:
            raise InputError(f"/dev/i2c-{number} does not exist: enable I2C (raspi-config → "
                             f"Interface Options → I2C, or dtparam=i2c_arm=on) and check the bus "
                             f"number with `ls /dev/i2c-*`") from e
        except PermissionError as e:
            raise InputError(f"no permission to open /dev/i2c-{number}: add the user to the "
                             f"'i2c' group (sudo adduser $USER i2c) and log in again") from e
    raise InputError(f"bus must be a bus number (e.g. 1 for /dev/i2c-1) or fake:TRACK.csv, "
                     f"got {spec!r}")


def _fake_board(path, read_track, *, speed=None, faults=None, **board_options):
    return FakeBoard.from_track(_read(read_track, path), speed=speed, faults=faults, **board_options)


def _simavr_board(path, read_track, *, speed=None, faults=None, **board_options):
    if speed is not None or faults is not None:
        raise InputError(f"simavr:{path}: speed and faults apply to fake: boards only (simavr runs "
                         "as fast as the host reads)")
    return SimavrBoard(_read(read_track, path), **board_options)


#: scheme → board factory ``(path, read_track, **options)``; anything else is a device or URL.
PORT_SCHEMES = {"fake": _fake_board, "simavr": _simavr_board}


def open_link(spec: str, baud: int = DEFAULT_BAUD, *, read_track=None, timeout: float = 0.05,
              mode: str = "auto", **board_options) -> SerialLink:
    """A woken :class:`SerialLink` on ``spec``: ``fake:TRACK``, ``simavr:TRACK``, a pyserial URL
    or a device path. ``board_options`` (``speed``, ``faults``, …) configure a simulated board."""
    scheme, sep, path = spec.partition(":")
    if not (sep and scheme in PORT_SCHEMES):
        if board_options:
            raise InputError(f"{spec}: {', '.join(board_options)} apply to simulated boards only")
        return SerialLink.open(spec, baud, timeout=timeout, mode=mode)
    if not path:
        raise InputError(f"{scheme}: needs a track file, e.g. {scheme}:track.csv")
    board = PORT_SCHEMES[scheme](path, read_track, **board_options).start()
    return SerialLink.open(board.port_name, baud, timeout=timeout, mode=mode, board=board,
                           source=f"serial:{spec}")

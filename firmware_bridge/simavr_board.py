"""The real ``streamcal_bridge`` firmware in the loop: the compiled Uno sketch in simavr.

:class:`SimavrBoard` builds the sketch (``tools/build_sketch.sh``) and the C harness
(``tools/simavr_harness``, a separate GPL-3 program because it links libsimavr), turns a track into
the raw counts the harness's register-level MPU-9250/AK8963 replay (the same conversion as
:class:`~firmware_bridge.fake_mpu9250.FakeMPU9250Bus`, called, not re-derived), starts the
harness and exposes the pseudo-terminal that carries the simulated UART0::

    with SimavrBoard(Track.read("track.csv")) as board:
        link = board.open_link()            # a SerialLink on the board's pty
        for block in link.blocks(idle_timeout=2.0): ...

or, through the host's usual entry point (``streamcal serial --port simavr:track.csv``)::

    link = open_link("simavr:track.csv", read_track=Track.read)   # closing the link stops the board

Time: the AVR starts at cycle 0 when the host sends its first byte; track row ``t`` becomes the
chips' current value at simulated time ``t - t[0] + lead_s`` (16 MHz cycles), so the sketch's
``micros()`` reads about ``(t - t[0] + lead_s)·1e6`` when it samples row ``t``
(:meth:`SimavrBoard.track_time`). The simulation runs as fast as the host reads (the UART is
modelled at 115200 baud in simulated time), then in real time once the track is over.

Builds are cached by content hash under ``$STREAMCAL_SIMAVR_CACHE`` (default
``~/.cache/streamcal/simavr``). Needs Debian's ``arduino-builder arduino-core-avr gcc-avr avr-libc
binutils-avr simavr libsimavr-dev libsimavrparts1 libelf-dev pkg-config make`` and a C compiler
(HARDWARE.md §7); :func:`missing_toolchain` names what is absent.
"""
from __future__ import annotations

import hashlib
import json
import os
import select
import shutil
import signal
import struct
import subprocess
import tempfile
import threading
from pathlib import Path
from typing import Sequence

import numpy as np

from streamcal.errors import InputError, StreamcalError

from . import registers as R
from .fake_mpu9250 import FakeMPU9250Bus

REPO = Path(__file__).resolve().parent.parent
SKETCH_DIR = REPO / "arduino" / "streamcal_bridge"
BUILD_SCRIPT = REPO / "tools" / "build_sketch.sh"
HARNESS_DIR = REPO / "tools" / "simavr_harness"
F_CPU_HZ = 16_000_000
REPLAY_MAGIC = b"SCSIMRP1"
DEFAULT_LEAD_S = 0.3      # simulated seconds before the first track row (sensor setup takes ~0.13 s)
_TOOLS = ("arduino-builder", "avr-size", "avr-gcc", "make", "cc", "pkg-config")
_SIMAVR_HEADER = Path("/usr/include/simavr/sim_avr.h")


class SimavrError(StreamcalError):
    """The simulated board could not be built, started or stopped; says which step and why."""

    exit_code = 2


def missing_toolchain() -> list[str]:
    """Names of the tools/headers needed here that are not installed (empty when all are)."""
    missing = [tool for tool in _TOOLS if shutil.which(tool) is None]
    if not _SIMAVR_HEADER.exists():
        missing.append(f"{_SIMAVR_HEADER} (libsimavr-dev)")
    return missing


def _cache_dir(cache_dir) -> Path:
    base = Path(cache_dir) if cache_dir is not None else Path(
        os.environ.get("STREAMCAL_SIMAVR_CACHE", Path.home() / ".cache" / "streamcal" / "simavr"))
    base.mkdir(parents=True, exist_ok=True)
    return base


def _digest(paths: Sequence[Path]) -> str:
    h = hashlib.sha256()
    for p in sorted(paths):
        h.update(p.name.encode() + b"\0" + p.read_bytes() + b"\0")
    return h.hexdigest()[:16]


def _run(cmd, what: str, **kw) -> None:
    res = subprocess.run(cmd, capture_output=True, text=True, **kw)
    if res.returncode != 0:
        raise SimavrError(f"{what} failed (exit {res.returncode}): {(res.stderr or res.stdout).strip()[-2000:]}")


def _cached_build(name: str, sources: Sequence[Path], build, cache_dir) -> Path:
    """Return ``cache/name-<hash>``; ``build(tmpdir) -> Path`` makes it if absent (atomic rename)."""
    cache = _cache_dir(cache_dir)
    target = cache / f"{name}-{_digest(sources)}"
    if target.exists():
        return target
    with tempfile.TemporaryDirectory(dir=cache) as tmp:
        product = build(Path(tmp))
        os.replace(product, target)
    return target


def build_firmware(cache_dir=None) -> Path:
    """Compile the sketch for an Uno (``tools/build_sketch.sh``); return the ``.elf`` path."""
    sources = [p for p in SKETCH_DIR.iterdir() if p.is_file()] + [BUILD_SCRIPT]

    def build(tmp: Path) -> Path:
        _run(["sh", str(BUILD_SCRIPT), str(tmp / "build")], "building the sketch (tools/build_sketch.sh)")
        return tmp / "build" / "streamcal_bridge.ino.elf"
    return _cached_build("streamcal_bridge.elf", sources, build, cache_dir)


def build_harness(cache_dir=None) -> Path:
    """Compile ``tools/simavr_harness`` with make; return the executable's path."""
    sources = [HARNESS_DIR / "simavr_harness.c", HARNESS_DIR / "Makefile"]

    def build(tmp: Path) -> Path:
        _run(["make", "-s", "-C", str(HARNESS_DIR), f"OUT={tmp}"], "building tools/simavr_harness")
        return tmp / "simavr_harness"
    return _cached_build("simavr_harness", sources, build, cache_dir)


#: The fuse-ROM bytes the simulated AK8963 holds for a µT track: typical, unequal values, so the
#: sketch's sensitivity adjustment is exercised.
DEFAULT_ASA = (0xB0, 0xB2, 0xA5)


def replay_bytes(track, *, lead_s: float = DEFAULT_LEAD_S, asa=None, who_am_i: int = 0x71,
                 ak_wia: int = R.AK8963_WIA, magnetometer: bool | None = None, hofl_rate: float = 0.0,
                 seed: int = 0) -> bytes:
    """The harness's replay file for ``track`` (a :class:`~streamcal.inputs.track.Track`, mag in µT).

    Raw counts come from :class:`FakeMPU9250Bus` (every ACCEL_FS_SEL/GYRO_FS_SEL setting, 14- and
    16-bit magnetometer output, ASA and axis remap inverted); row times become 16 MHz cycles
    ``round((t - t[0] + lead_s)·F_CPU)``. Layout: ``tools/simavr_harness/simavr_harness.c``.
    ``asa`` (3 bytes): the fuse ROM; by default a raw AK8963 counts log keeps the ASA its metadata
    records (its counts are served unchanged, so only that ASA turns them into the right µT) and a
    µT track gets :data:`DEFAULT_ASA`.
    """
    from .fake_mpu9250 import Faults

    if lead_s < 0:
        raise InputError(f"lead_s must be >= 0, got {lead_s}")
    if asa is None and getattr(track, "mag_unit", "uT") != "counts":
        asa = DEFAULT_ASA
    asa_option = {} if asa is None else {"asa": asa}
    bus = FakeMPU9250Bus.from_track(track, who_am_i=who_am_i, ak_wia=ak_wia, magnetometer=magnetometer,
                                    faults=Faults(hofl_rate=hofl_rate), seed=seed, **asa_option)
    t0 = float(bus.t[0])
    cyc = lambda t: np.rint((np.asarray(t, float) - t0 + lead_s) * F_CPU_HZ).astype("<i8")  # noqa: E731
    per_fs = [bus.encoded_rows(accel_fs=fs, gyro_fs=fs, mag_bits=16) for fs in range(4)]
    rows14, rows = bus.encoded_rows(mag_bits=14), per_fs[0]
    acc = np.stack([r.accel for r in per_fs], axis=1).reshape(-1, 4, 3)     # (Na, fs, xyz)
    gyr = np.stack([r.gyro for r in per_fs], axis=1).reshape(-1, 4, 3)
    mag = np.stack([rows14.mag, rows.mag], axis=1).reshape(-1, 2, 3)       # (Nm, [14, 16], xyz)
    hofl = np.stack([rows14.mag_overflow, rows.mag_overflow], axis=1).astype("u1")
    asa_b = bytes(np.asarray(bus.asa, dtype=np.uint8))
    header = REPLAY_MAGIC + struct.pack("<4I", len(rows.accel_t), len(rows.gyro_t), len(rows.temp_t),
                                        len(rows.mag_t)) \
        + bytes([who_am_i & 0xFF, ak_wia & 0xFF, int(bus.has_mag)]) + asa_b + b"\0\0"
    parts = [header,
             cyc(rows.accel_t).tobytes(), acc.astype("<i2").tobytes(),
             cyc(rows.gyro_t).tobytes(), gyr.astype("<i2").tobytes(),
             cyc(rows.temp_t).tobytes(), rows.temp.astype("<i2").tobytes(),
             cyc(rows.mag_t).tobytes(), mag.astype("<i2").tobytes(), hofl.tobytes()]
    return b"".join(parts)


class SimavrBoard:
    """The compiled sketch running in simavr on a pty, replaying ``track``.

    ``track``: a recording (``t``, ``columns``, ``metadata``: a Track). ``eeprom``: a 1024-byte
    EEPROM image file, loaded at start if it exists and saved at close (a calibration survives a
    "reboot"). ``tail_s``: simulated seconds after the last row before the AVR drops to real time.
    ``reset_at_eeprom_write``: reset the AVR right after it starts its N-th EEPROM byte write
    (``stats["eeprom_writes"]`` counts them).
    Other keywords go to :func:`replay_bytes`. After :meth:`close`, :attr:`stats` holds the
    harness's counters (``sim_s``, ``wall_s``, ``samples_latched``, ``skipped``, ``dor_reported``,
    ``violations``, ``uart_tx_bytes``…).
    """

    #: The sketch keeps sampling after the replay (a sensor whose values stopped changing), so a
    #: host reading until the line is quiet never stops: it stops at :attr:`finished` instead.
    streams_after_replay = True

    def __init__(self, track, *, lead_s: float = DEFAULT_LEAD_S, eeprom=None, tail_s: float = 1.0,
                 cache_dir=None, start_timeout: float = 120.0, reset_at_eeprom_write: int = 0,
                 **replay_options):
        self.track = track
        self.lead_s = float(lead_s)
        self.t0 = float(self.track.t[0])
        self.eeprom = None if eeprom is None else Path(eeprom)
        self.tail_s = float(tail_s)
        self.cache_dir = cache_dir
        self.start_timeout = start_timeout
        self.reset_at_eeprom_write = int(reset_at_eeprom_write)
        self.replay_options = replay_options
        self.port_name: str | None = None
        self.stats: dict | None = None
        self.proc: subprocess.Popen | None = None
        self._tmp: tempfile.TemporaryDirectory | None = None
        self._finished = threading.Event()

    @classmethod
    def from_track(cls, track, **options) -> "SimavrBoard":
        return cls(track, **options).start()

    def track_time(self, t_board_s):
        """Board clock (s since reset, as ``SampleBlock.t``) → track time, s."""
        return np.asarray(t_board_s, dtype=float) + self.t0 - self.lead_s

    def start(self) -> "SimavrBoard":
        """Build what is missing, write the replay file, start the harness, learn its pty."""
        missing = missing_toolchain()
        if missing:
            raise SimavrError(f"simavr board: missing {', '.join(missing)} (see HARDWARE.md §7)")
        elf, harness = build_firmware(self.cache_dir), build_harness(self.cache_dir)
        self._tmp = tempfile.TemporaryDirectory(prefix="streamcal-simavr-")
        work = Path(self._tmp.name)
        replay = work / "replay.bin"
        replay.write_bytes(replay_bytes(self.track, lead_s=self.lead_s, **self.replay_options))
        self._stats_path = work / "stats.json"
        self._log_path = work / "harness.log"
        cmd = [str(harness), str(elf), str(replay), "--stats", str(self._stats_path), "--tail", str(self.tail_s)]
        if self.eeprom is not None:
            cmd += ["--eeprom", str(self.eeprom)]
        if self.reset_at_eeprom_write:
            cmd += ["--reset-at-eeprom-write", str(self.reset_at_eeprom_write)]
        self._log = open(self._log_path, "wb")
        try:
            self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=self._log, stdin=subprocess.DEVNULL)
        except OSError as exc:
            self._log.close()
            self.close()
            raise SimavrError(f"simavr harness {harness}: cannot start ({exc})") from None
        ready, _, _ = select.select([self.proc.stdout], [], [], self.start_timeout)
        line = self.proc.stdout.readline().decode(errors="replace").strip() if ready else ""
        if not line.startswith("/dev/"):
            self.close()
            raise SimavrError(f"simavr harness did not report its pty within {self.start_timeout:g} s "
                              f"(got {line!r}); log: {self.log()[-1000:]}")
        self.port_name = line
        return self

    @property
    def finished(self) -> threading.Event:
        """Set once the simulation has passed the track's last row plus ``tail_s`` (the harness
        says so on its stdout) or the harness has ended: the interface of
        :attr:`FakeBoard.finished <firmware_bridge.fake_board.FakeBoard.finished>`."""
        proc = self.proc
        if not self._finished.is_set() and proc is not None:
            if proc.poll() is not None:
                self._finished.set()
            elif select.select([proc.stdout], [], [], 0)[0]:
                line = proc.stdout.readline()
                if not line or line.strip() == b"replay-end":
                    self._finished.set()
        return self._finished

    def open_link(self, baud: int = 115200, timeout: float = 0.05, **link_options):
        """A :class:`~firmware_bridge.serial_link.SerialLink` on this board's pty, woken up;
        closing the link closes the board."""
        import serial

        from .serial_link import SerialLink

        port = serial.Serial(self.port_name, baud, timeout=timeout)
        link = SerialLink(port, source=f"simavr:{self.port_name}", board=self, **link_options)
        link.wake()
        return link

    def log(self) -> str:
        """What the harness wrote on stderr so far."""
        try:
            return self._log_path.read_text(errors="replace")
        except (AttributeError, OSError):
            return ""

    def close(self, timeout: float = 10.0) -> dict | None:
        """SIGTERM the harness, wait for it, collect :attr:`stats`; idempotent."""
        if self.proc is not None:
            if self.proc.poll() is None:
                self.proc.send_signal(signal.SIGTERM)
                try:
                    self.proc.wait(timeout)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
                    self.proc.wait()
                    raise SimavrError(f"simavr harness (pid {self.proc.pid}) ignored SIGTERM for {timeout:g} s")
            self.proc.stdout.close()
            self._log.close()
            try:
                self.stats = json.loads(self._stats_path.read_text())
            except (OSError, ValueError):
                self.stats = None
            self.returncode = self.proc.returncode
            self.proc = None
            self._finished.set()
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None
        return self.stats

    def __enter__(self) -> "SimavrBoard":
        return self if self.proc is not None else self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self):
        try:
            if self.proc is not None and self.proc.poll() is None:
                self.proc.kill()
        except Exception:
            pass


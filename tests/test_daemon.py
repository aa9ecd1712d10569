"""The I²C daemon: convergence against the batch fit, faults, signals, sd_notify, outputs.

The convergence bound: the streaming fits see the bounded coverage buffer (a few hundred samples
spread over the sphere), not the whole track, so they match ``streamcal fit`` on the track only up
to the sampling error of that subset. We require the normalized model error (paper eq. 40,
``Calibration.model_error``) to stay below 1 % — about 0.9 µT on ‖[K, b]‖ ≈ 85 µT, i.e. within two
noise rms of the sensor — and measured 0.56 % (demo track) and 0.33 % (sunsided full sphere).
"""
from __future__ import annotations

import io
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import streamcal
from firmware_bridge.fake_mpu9250 import Faults
from streamcal.calibration import Calibration
from streamcal.service import I2CBlocks, Notifier, Outputs, Service, SocketOutput, StreamOutput
from streamcal.service.output import format_lines
from streamcal.stream import CalibrationStore, StreamingCalibrator
from streamcal.inputs.track import Track

REPO = Path(__file__).resolve().parent.parent
DEMO = REPO / "streamcal" / "data" / "demo_track.csv.gz"
MODEL_ERROR_BOUND = 0.01
#: Waits on a condition give up after this long (s): generous, so that a loaded or slow machine
#: only makes the test slower, never makes it fail; no test compares a wall-clock time.
WAIT_S = 120.0


@pytest.fixture(scope="module")
def demo_batch() -> Calibration:
    return streamcal.fit(Track.read(DEMO))


def service_for(track, state_dir, *, faults=None, outputs=None, notifier=None, log=None,
                sync=True, **kw) -> Service:
    store = CalibrationStore(state_dir)
    source = I2CBlocks(f"fake:{track}", fake_kwargs={"faults": faults} if faults else None)

    def make(buffer=None):
        return StreamingCalibrator(store=store, synchronous=sync,
                                   **({"buffer": buffer} if buffer is not None else {}))

    lines = []
    return Service(make, source, outputs=outputs, notifier=notifier or Notifier(environ={}),
                   log=log or lines.append, **kw)


def short_dir() -> Path:
    """AF_UNIX paths are limited to 108 bytes: keep sockets under a short temp dir."""
    return Path(tempfile.mkdtemp(prefix="scd", dir="/tmp"))


# -- convergence ------------------------------------------------------------------------------

def test_daemon_over_fake_bus_converges_to_batch_fit(tmp_path, demo_batch):
    service = service_for(DEMO, tmp_path)
    assert service.run() == 0
    stored = Calibration.load(tmp_path / "calibration.json")
    err = stored.model_error(demo_batch)
    assert err < MODEL_ERROR_BOUND, f"daemon vs streamcal fit: model error {err:.4f}"
    assert service.calibrator.calibration.model_error(stored) == 0.0
    assert service.summary()["samples"] == int(Track.read(DEMO).mag_rows.sum())


def test_daemon_on_real_fullsphere_track(tmp_path, real_tracks_dir):
    track = real_tracks_dir / "sunsided_set2_fullsphere.csv.gz"
    batch = streamcal.fit(Track.read(track))
    service = service_for(track, tmp_path)
    assert service.run() == 0
    err = Calibration.load(tmp_path / "calibration.json").model_error(batch)
    assert err < MODEL_ERROR_BOUND, f"daemon vs streamcal fit: model error {err:.4f}"


def test_daemon_survives_bus_faults_with_calibration_unaffected(tmp_path, demo_batch):
    faults = Faults(nack_rate=0.05, hofl_rate=0.01, dor_rate=0.01, vanish=[(60.0, 64.0)],
                    self_resets=[(100.0, "both"), (130.0, "mpu"), (150.0, "ak")])
    log: list[str] = []
    service = service_for(DEMO, tmp_path, faults=faults, log=log.append)
    assert service.run() == 0
    counters = service.source.counters()
    assert counters["nacks"] > 0 and counters["overflows"] > 0
    assert counters["reinits"] >= 2          # the vanish (returns at power-on) and the resets
    assert service.stats.outages >= 1 and any("device answers again" in line for line in log)
    assert service.stats.ingest_errors == 0
    err = Calibration.load(tmp_path / "calibration.json").model_error(demo_batch)
    assert err < MODEL_ERROR_BOUND, f"with faults: model error {err:.4f}"


def test_device_absent_at_start_is_retried_not_fatal(tmp_path):
    # the sensor is missing for the first 2 s of the track: bring-up fails, is retried, succeeds
    service = service_for(DEMO, tmp_path, faults=Faults(vanish=[(0.0, 2.0)]), max_seconds=1.5)
    assert service.run() == 0
    assert service.stats.outages == 1 and service.source.bringups == 1
    assert service.stats.samples > 0


def test_garbage_block_is_counted_not_fatal(tmp_path):
    from streamcal.samples import SampleBlock

    class Hostile:
        description, finished, sleep = "hostile", False, staticmethod(lambda s: None)

        def __init__(self):
            self.n = 0

        def read(self):
            self.n += 1
            if self.n == 1:      # wrong shapes: the calibrator raises on it
                return SampleBlock(t=np.zeros(3), mag=np.zeros((2, 5)))
            self.finished = self.n > 3
            return None

        def counters(self):
            return {}

        def close(self):
            pass

    store = CalibrationStore(tmp_path)
    service = Service(lambda buffer=None: StreamingCalibrator(store=store), Hostile(),
                      notifier=Notifier(environ={}), log=lambda line: None)
    assert service.run() == 1            # end of replay without a calibration: exit 1
    assert service.stats.ingest_errors == 1


# -- outputs ----------------------------------------------------------------------------------

@pytest.mark.slow
def test_json_lines_and_socket_output_are_unit_directions(tmp_path):
    d = short_dir()
    stream = io.StringIO()
    sock = SocketOutput(d / "s.sock")
    client = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    client.connect(os.fspath(d / "s.sock"))
    received = bytearray()

    def reader():
        while chunk := client.recv(65536):
            received.extend(chunk)
    thread = threading.Thread(target=reader, daemon=True)
    thread.start()
    service = service_for(DEMO, tmp_path, outputs=Outputs([StreamOutput(stream), sock]))
    assert service.run() == 0
    thread.join(timeout=10)
    lines = stream.getvalue().splitlines()
    assert len(lines) == service.outputs.lines > 10000
    rows = [json.loads(line) for line in lines]
    assert set(rows[0]) == {"t", "field_uT", "direction", "cal_version", "disturbed"}
    x = np.array([r["direction"] for r in rows])
    f = np.array([r["field_uT"] for r in rows])
    np.testing.assert_allclose(np.linalg.norm(x, axis=1), 1.0, atol=2e-6)
    np.testing.assert_allclose(f / np.linalg.norm(f, axis=1)[:, None], x, atol=2e-6)
    versions = np.array([r["cal_version"] for r in rows])
    assert versions[0] == 0 and np.all(np.diff(versions) >= 0) and versions[-1] == service.cal_version
    assert np.all(np.diff([r["t"] for r in rows]) >= 0)
    # after the last calibration: the field is that calibration applied, |B| = K's radius
    cal = service.calibrator.calibration
    last = versions == versions[-1]
    assert np.median(np.abs(np.linalg.norm(f[last], axis=1) / cal.radius - 1)) < 0.05
    # the socket client got the same lines, byte for byte
    assert sock.clients_served == 1 and sock.dropped_lines == 0
    assert received.decode() == stream.getvalue()
    assert not (d / "s.sock").exists()       # removed on close


def test_slow_socket_client_loses_whole_lines_and_memory_stays_bounded():
    d = short_dir()
    out = SocketOutput(d / "s.sock", max_pending=4096)
    client = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    client.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    client.connect(os.fspath(d / "s.sock"))
    t = np.arange(200) * 0.01
    field = np.tile([30.0, -10.0, 40.0], (200, 1))
    for k in range(100):                      # nobody reads
        out.publish(format_lines(t + 2 * k, field, 1))
    assert out.dropped_lines > 0
    assert all(len(p) <= 4096 for p in out._clients.values())
    client.setblocking(False)
    data = bytearray()
    while True:
        try:
            chunk = client.recv(65536)
        except BlockingIOError:
            out.publish("")                   # flush what is queued
            try:
                chunk = client.recv(65536)
            except BlockingIOError:
                break
        if not chunk:
            break
        data.extend(chunk)
    lines = data.decode().splitlines()
    assert lines and all(json.loads(line)["cal_version"] == 1 for line in lines)
    out.close()


def test_format_lines_skips_rows_without_estimate():
    text = format_lines([0.0, 0.1, 0.2], [[1.0, 0, 0], [np.nan] * 3, [0.0, 3.0, 4.0]], 2)
    rows = [json.loads(line) for line in text.splitlines()]
    assert [r["t"] for r in rows] == [0.0, 0.2]
    assert rows[1]["direction"] == [0.0, 0.6, 0.8] and rows[1]["cal_version"] == 2


# -- reload and start-up --------------------------------------------------------------------------

def test_start_uses_stored_calibration_and_sighup_rereads_it(tmp_path, demo_batch):
    store = CalibrationStore(tmp_path)
    store.save(demo_batch)
    stream = io.StringIO()
    service = service_for(DEMO, tmp_path, outputs=Outputs([StreamOutput(stream)]), max_seconds=60)
    service.calibrator = None
    edited = demo_batch.replace(b=demo_batch.b + [3.0, 0.0, 0.0])

    reads = {"n": 0}
    read = service.source.read

    def read_and_edit():
        reads["n"] += 1
        if reads["n"] == 3:                  # an operator replaces the file, then sends SIGHUP
            store.save(edited)
            service.request_reload()
        if reads["n"] == 6:
            service.request_stop("test done")
        return read()
    service.source.read = read_and_edit
    assert service.run() == 0
    rows = [json.loads(line) for line in stream.getvalue().splitlines()]
    # the first samples already use the stored calibration (version 1), then the edited one
    assert rows[0]["cal_version"] == 1 and rows[-1]["cal_version"] == 2
    assert service.stats.reloads == 1
    in_use = service.calibrator.calibration
    np.testing.assert_allclose(in_use.b, edited.b)
    first = np.array(rows[0]["field_uT"])
    block_m = Track.read(DEMO).mag[0]
    expect = demo_batch.apply(block_m)
    # the driver path quantizes to one AK8963 LSB (0.15 µT × fuse-ROM factor ≤ 1.5)
    lsb = 0.15 * 1.5 / np.prod(np.diag(demo_batch.K)) ** (1 / 3)
    np.testing.assert_allclose(first / np.linalg.norm(first), expect / np.linalg.norm(expect),
                               atol=lsb)


def test_sighup_with_damaged_file_keeps_calibration_in_use(tmp_path, demo_batch):
    CalibrationStore(tmp_path).save(demo_batch)
    log: list[str] = []
    service = service_for(DEMO, tmp_path, log=log.append, max_seconds=60)
    read = service.source.read
    calls = {"n": 0}

    def damage_then_reload():
        calls["n"] += 1
        if calls["n"] == 2:
            for f in [tmp_path / "calibration.json", *(tmp_path / "history").iterdir()]:
                f.write_text("{ not json")
            service.request_reload()
        if calls["n"] == 4:
            service.request_stop("test done")
        return read()
    service.source.read = damage_then_reload
    assert service.run() == 0
    assert any("nothing to reload" in line for line in log)
    assert service.calibrator.calibration.model_error(demo_batch) == 0.0


# -- the real process: signals and sd_notify --------------------------------------------------------

class NotifySocket:
    """A datagram socket standing in for systemd's NOTIFY_SOCKET; a thread collects messages."""

    def __init__(self, path: Path):
        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(os.fspath(path))
        self.sock.settimeout(0.2)
        self.messages: list[dict] = []
        self.closed = False
        threading.Thread(target=self._collect, daemon=True).start()

    def _collect(self):
        while not self.closed:
            try:
                data = self.sock.recv(4096)
            except socket.timeout:
                continue
            except OSError:
                return
            self.messages.append(dict(line.split("=", 1) for line in data.decode().splitlines()))

    def wait_for(self, key: str, value: str | None = None, timeout: float = 60.0, start: int = 0) -> dict:
        end = time.monotonic() + timeout
        while True:
            for msg in self.messages[start:]:
                if key in msg and (value is None or msg[key] == value):
                    return msg
            if time.monotonic() > end:
                raise AssertionError(f"no {key}={value} within {timeout} s; got {self.messages}")
            time.sleep(0.05)


class Daemon:
    """``python -m streamcal daemon`` in a subprocess; stdout and stderr drained by threads (a
    full pipe would stall the daemon)."""

    def __init__(self, state: Path, notify: Path, *extra):
        self.proc = start_daemon(state, notify, *extra)
        self.out, self.err = [], []
        self.threads = [threading.Thread(target=lambda f=f, acc=acc: acc.extend(f), daemon=True)
                        for f, acc in ((self.proc.stdout, self.out), (self.proc.stderr, self.err))]
        for th in self.threads:
            th.start()

    def stop(self, sig, timeout: float = 30.0) -> tuple[str, str]:
        self.proc.send_signal(sig)
        self.proc.wait(timeout=timeout)
        for th in self.threads:
            th.join(timeout=10)
        return "".join(self.out), "".join(self.err)

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


def start_daemon(state: Path, notify: Path, *extra) -> subprocess.Popen:
    env = dict(os.environ, NOTIFY_SOCKET=os.fspath(notify), WATCHDOG_USEC="400000",
               PYTHONPATH=os.fspath(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("WATCHDOG_PID", None)
    return subprocess.Popen([sys.executable, "-m", "streamcal", "daemon", "--bus", f"fake:{DEMO}",
                             "--state-dir", os.fspath(state), "--speed", "8", *extra],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.mark.slow
def test_process_notifies_systemd_and_stops_cleanly_on_sigterm():
    d = short_dir()
    notify = NotifySocket(d / "notify")
    daemon = Daemon(d / "state", d / "notify", "--json-lines")
    proc = daemon.proc
    try:
        notify.wait_for("READY", "1", timeout=WAIT_S)
        notify.wait_for("WATCHDOG", "1", timeout=WAIT_S)
        status = notify.wait_for("STATUS", timeout=WAIT_S)["STATUS"]
        assert "coverage" in status and "device" in status
        # wait until a calibration was accepted and stored, then stop in the middle of the run
        end = time.monotonic() + WAIT_S
        while not (d / "state" / "calibration.json").exists() and time.monotonic() < end:
            time.sleep(0.2)
        assert (d / "state" / "calibration.json").exists()
        seen = len(notify.messages)
        assert "rms" in notify.wait_for("STATUS", timeout=WAIT_S, start=seen)["STATUS"]
        out, err = daemon.stop(signal.SIGTERM, timeout=WAIT_S)
    finally:
        daemon.kill()
    assert proc.returncode == 0, err
    assert "stopped (SIGTERM)" in err
    notify.wait_for("STOPPING", "1", timeout=WAIT_S)
    cal = Calibration.load(d / "state" / "calibration.json")
    assert cal.sensor == "mag" and np.all(np.diag(cal.K) > 0)
    rows = [json.loads(line) for line in out.splitlines()]
    assert rows and all(abs(np.linalg.norm(r["direction"]) - 1) < 2e-6 for r in rows)
    # Stopped by the signal (not by the end of the track), whatever the machine's speed.
    assert json.loads(err.strip().splitlines()[-1])["stop_reason"] == "SIGTERM"


def test_process_reloads_on_sighup():
    d = short_dir()
    notify = NotifySocket(d / "notify")
    state = d / "state"
    daemon = Daemon(state, d / "notify", "--no-socket")
    proc = daemon.proc
    try:
        notify.wait_for("READY", "1", timeout=WAIT_S)
        seen = len(notify.messages)
        proc.send_signal(signal.SIGHUP)
        notify.wait_for("RELOADING", "1", timeout=WAIT_S, start=seen)
        notify.wait_for("READY", "1", timeout=WAIT_S, start=seen)   # ready again after the reload
        out, err = daemon.stop(signal.SIGINT, timeout=WAIT_S)
    finally:
        daemon.kill()
    assert proc.returncode == 0, err
    assert "SIGHUP" in err and "stopped (SIGINT)" in err
    assert json.loads(out.strip().splitlines()[-1])["reloads"] == 1


def test_notifier_speaks_the_protocol():
    d = short_dir()
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(os.fspath(d / "n"))
    now = [0.0]
    n = Notifier(environ={"NOTIFY_SOCKET": os.fspath(d / "n"), "WATCHDOG_USEC": "2000000"},
                 clock=lambda: now[0])
    assert n.watchdog_interval == 1.0
    assert n.ready("up")
    assert sock.recv(100).decode() == "READY=1\nSTATUS=up"
    assert n.tick() and sock.recv(100) == b"WATCHDOG=1"
    now[0] = 0.5
    assert not n.tick()
    now[0] = 1.0
    assert n.tick()
    other = Notifier(environ={"NOTIFY_SOCKET": os.fspath(d / "n"), "WATCHDOG_USEC": "2000000",
                              "WATCHDOG_PID": str(os.getpid() + 1)})
    assert other.watchdog_interval is None and not other.tick()
    assert not Notifier(environ={}).ready()


# -- the systemd unit ---------------------------------------------------------------------------

def test_systemd_unit_is_notify_with_watchdog_and_a_valid_command_line():
    import shlex

    from streamcal.cli import build_parser

    text = (REPO / "tools" / "streamcal-daemon.service").read_text().replace("\\\n", " ")
    keys: dict[str, list[str]] = {}
    for line in text.splitlines():
        if "=" in line and not line.lstrip().startswith(("#", "[")):
            k, v = line.split("=", 1)
            keys.setdefault(k.strip(), []).append(v.strip())
    assert keys["Type"] == ["notify"] and float(keys["WatchdogSec"][0]) > 0
    assert keys["ExecReload"] == ["/bin/kill -HUP $MAINPID"]
    assert keys["Restart"] == ["on-failure"] and keys["NoNewPrivileges"] == ["yes"]
    assert keys["ProtectSystem"] == ["strict"] and keys["StateDirectory"] == ["streamcal"]
    assert "i2c" in keys["SupplementaryGroups"][0]
    argv = shlex.split(keys["ExecStart"][0])
    bus = argv[argv.index("--bus") + 1]
    assert keys["DeviceAllow"] == [f"/dev/i2c-{bus} rw"] and keys["DevicePolicy"] == ["closed"]
    args = build_parser().parse_args(argv[1:])
    assert args.command == "daemon" and args.func.__module__ == "streamcal.cli.daemon"
    assert args.grace < float(keys["TimeoutStopSec"][0])


def run_cli_in_process(argv, capsys) -> tuple[int, str, str]:
    """``streamcal.cli.main(argv)``, restoring the signal handlers the service installs."""
    from streamcal.cli import main

    saved = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)}
    try:
        code = main(argv)
    finally:
        for sig, handler in saved.items():
            signal.signal(sig, handler)
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize("json_lines", [False, True])
def test_cli_draws_the_coverage_map_on_stderr_at_milestones(tmp_path, capsys, json_lines):
    from streamcal.sim import simulate

    path = tmp_path / "track.csv"
    simulate(duration_s=30.0, seed=3, motor=False).track.write(path)
    code, out, err = run_cli_in_process(
        ["daemon", "--bus", f"fake:{path}", "--state-dir", str(tmp_path / "state"), "--no-socket",
         "--sync-fits"] + (["--json-lines"] if json_lines else []), capsys)
    assert code in (0, 1), err
    milestones = err.count(" coverage: coverage ")            # the event lines
    assert milestones >= 2
    maps = err.count("% of the sphere (")                       # coverage_view's heading
    assert maps == err.count("█ seen  · not yet") == (0 if json_lines else milestones)
    assert "█ seen" not in out                                  # stdout: samples or the summary
    summary = json.loads((err if json_lines else out).strip().splitlines()[-1])
    assert summary["events"]["coverage"] == milestones


def test_daemon_buffer_columns_follow_the_effect_declarations():
    """The columns the daemon keeps beside the field come from each effect's declared needs
    (the first of ``needs_any`` the sensor has): the built-ins as before, an effect registered
    later without touching the daemon, and a refusal for needs the MPU-9250 lacks."""
    from streamcal.cli.daemon import _covariates
    from streamcal.errors import UnknownEffectError
    from streamcal.model import registered

    from .test_effect_registration import TOY, WARM

    assert _covariates(("hard_iron", "soft_iron")) == ()
    assert _covariates(("hard_iron", "temperature_scale")) == ("temp",)
    assert _covariates(("hard_iron", "time_lag", "mag_accel_misalignment",
                        "temperature_offset")) == ("temp", "ax", "ay", "az", "gx", "gy", "gz")
    with pytest.raises(UnknownEffectError, match="aux_interference needs an auxiliary channel"):
        _covariates(("hard_iron", "aux_interference"))
    with registered(WARM):
        assert _covariates(("hard_iron", "warm_offset")) == ("temp",)
    with registered(TOY), pytest.raises(UnknownEffectError, match="coil_square needs coil_drive"):
        _covariates(("hard_iron", "coil_square"))
    with pytest.raises(UnknownEffectError, match="unknown effect"):
        _covariates(("hard_iron", "warm_offset"))

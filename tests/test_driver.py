"""MPU-9250 driver against the register-level fake: decoding, identity, faults, recovery."""
import errno
import os

import numpy as np
import pytest

from firmware_bridge import registers as R
from firmware_bridge.fake_mpu9250 import FakeMPU9250Bus, Faults
from firmware_bridge.i2c_source import I2CSource, open_i2c_source
from firmware_bridge.ports import open_bus
from streamcal.inputs.track import Track
from firmware_bridge.mpu9250 import MPU9250, DeviceIOError, WrongDeviceError
from streamcal.errors import InputError

ASA = np.array([0xB0, 0xB2, 0xA5])


def make_track(n=400, seed=0):
    """IMU at 200 Hz; magnetometer at 100 Hz (NaN on odd rows): a rotating 48 µT field plus
    hard iron, gravity in varying directions, ±3 rad/s rates, a temperature ramp."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.005
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    mag = 48.0 * u + np.array([12.0, -30.0, 7.0])
    mag[1::2] = np.nan
    g = rng.normal(size=(n, 3))
    accel = 9.81 * g / np.linalg.norm(g, axis=1, keepdims=True) + rng.normal(0, 0.5, (n, 3))
    return dict(t=t, mag=mag, accel=accel, gyro=rng.uniform(-3, 3, (n, 3)),
                temp=np.linspace(15.0, 40.0, n))


def driver(bus, **kw):
    kw.setdefault("clock", bus.now)
    return MPU9250(bus, sleep=lambda s: None, **kw)


def bounds(d):
    """Half an LSB per channel: the quantization bound of a round trip (mag (3,), accel, gyro, temp)."""
    return (0.5 * R.mag_scale(16) * R.asa_factor(d.asa)[[1, 0, 2]] + 1e-9,
            0.5 * R.accel_scale(d.accel_fs) + 1e-9, 0.5 * R.gyro_scale(d.gyro_fs) + 1e-9,
            0.5 / R.TEMP_SENSITIVITY_LSB_PER_C + 1e-9)


def check_replay_through_the_driver(path) -> None:
    """A mixed-rate track file through fake bus + driver + source: every magnetometer sample
    comes back, each channel within half an LSB of the track value the chip would hold at that
    instant, with no bus-protocol violation and no retry."""
    track = Track.read(path)
    src = open_i2c_source(f"fake:{path}", block_size=500, read_track=Track.read)
    blocks = list(src)
    d = src.driver
    t = np.concatenate([b.t for b in blocks])
    np.testing.assert_array_equal(t, track.t_mag)
    bm, ba, bg, bt = bounds(d)
    mag = np.concatenate([b.mag for b in blocks])
    assert np.all(np.abs(mag - track.mag) <= bm)
    for name, rows, values, bound in (("accel", track.accel_rows, track.accel, ba),
                                      ("gyro", track.gyro_rows, track.gyro, bg)):
        k = np.searchsorted(track.t[rows], t, side="right") - 1
        got = np.concatenate([getattr(b, name) for b in blocks])
        assert np.all(np.abs(got[k >= 0] - values[k[k >= 0]]) <= bound)
    temp_rows = np.isfinite(track.columns["temp"])
    k = np.searchsorted(track.t[temp_rows], t, side="right") - 1
    got = np.concatenate([b.temp for b in blocks])
    assert np.all(np.abs(got[k >= 0] - track.columns["temp"][temp_rows][k[k >= 0]]) <= bt)
    assert d.bus.violations == [] and d.stats["retries"] == 0


def assert_round_trip(block, tr, d):
    """Each returned sample equals the track at its time stamp within half an LSB."""
    k = np.searchsorted(tr["t"], block.t)
    np.testing.assert_array_equal(tr["t"][k], block.t)
    bm, ba, bg, bt = bounds(d)
    assert np.all(np.abs(block.mag - tr["mag"][k]) <= bm)
    assert np.all(np.abs(block.accel - tr["accel"][k]) <= ba)
    assert np.all(np.abs(block.gyro - tr["gyro"][k]) <= bg)
    assert np.all(np.abs(block.temp - tr["temp"][k]) <= bt)


def mag_times(tr):
    return tr["t"][np.all(np.isfinite(tr["mag"]), axis=1)]


@pytest.mark.parametrize("accel_fs,gyro_fs", [(0, 0), (1, 1), (3, 2)])
def test_round_trip_within_quantization(accel_fs, gyro_fs):
    tr = make_track()
    tr["accel"] = np.clip(tr["accel"], -19.0, 19.0)    # inside ±2 g
    tr["gyro"] = np.clip(tr["gyro"], -4.3, 4.3)        # inside ±250 °/s
    bus = FakeMPU9250Bus(**tr, asa=ASA)
    d = driver(bus, accel_fs=accel_fs, gyro_fs=gyro_fs)
    block = d.read_block(1000)
    assert d.chip.name == "MPU-9250" and list(d.asa) == list(ASA)
    np.testing.assert_array_equal(block.t, mag_times(tr))     # every magnetometer sample, once
    assert_round_trip(block, tr, d)
    assert bus.violations == [] and d.stats["retries"] == 0


def test_i2c_rdwr_transport_gives_the_same_samples():
    tr = make_track(100)
    a = driver(FakeMPU9250Bus(**tr)).read_block(50)
    b = driver(FakeMPU9250Bus(**tr), use_i2c_rdwr=True).read_block(50)
    for name in ("t", "mag", "accel", "gyro", "temp"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


@pytest.mark.parametrize("asa", [(0, 0, 0), (255, 255, 255), (40, 128, 230)])
def test_fuse_rom_adjustment_applied(asa):
    tr = make_track(100)
    d = driver(FakeMPU9250Bus(**tr, asa=asa))
    block = d.read_block(50)
    assert list(d.asa) == list(asa)
    assert_round_trip(block, tr, d)
    # without the adjustment the error would be far above the quantization bound
    factor = R.asa_factor(np.asarray(asa)[[1, 0, 2]])
    if np.any(factor != 1.0):
        k = np.searchsorted(tr["t"], block.t)
        assert np.max(np.abs(block.mag / factor - tr["mag"][k])) > 10 * bounds(d)[0].max()


@pytest.mark.parametrize("axis", range(3))
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_body_axis_field_appears_on_that_axis(axis, sign):
    n = 10
    mag = np.zeros((n, 3))
    mag[:, axis] = sign * 50.0
    bus = FakeMPU9250Bus(np.arange(n) * 0.01, mag=mag, accel=np.zeros((n, 3)),
                         gyro=np.zeros((n, 3)), temp=np.full(n, 21.0))
    r = driver(bus).read_sample()
    assert np.argmax(np.abs(r.mag)) == axis and np.sign(r.mag[axis]) == sign
    assert abs(r.mag[axis]) == pytest.approx(50.0, abs=0.1)


@pytest.mark.parametrize("who,name", [(0x71, "MPU-9250"), (0x73, "MPU-9255")])
def test_who_am_i_accepted(who, name):
    d = driver(FakeMPU9250Bus(**make_track(50), who_am_i=who))
    assert d.chip.name == name and d.has_magnetometer
    assert np.all(np.isfinite(d.read_sample().mag))


def test_mpu6500_has_no_magnetometer_and_says_so():
    tr = make_track(50)
    with pytest.raises(WrongDeviceError, match=r"0x70.*MPU-6500.*NO magnetometer"):
        driver(FakeMPU9250Bus(**tr, who_am_i=0x70))
    bus = FakeMPU9250Bus(**tr, who_am_i=0x70)
    d = driver(bus, require_magnetometer=False)
    assert not d.has_magnetometer
    block = d.read_block(20)
    assert len(block) == 20 and np.all(np.isnan(block.mag))
    np.testing.assert_array_equal(block.t, tr["t"][:20])     # paced by RAW_DATA_RDY: no repeats
    k = np.searchsorted(tr["t"], block.t)
    assert np.all(np.abs(block.accel - tr["accel"][k]) <= bounds_accel(d))
    with pytest.raises(OSError):              # nothing at 0x0C, as on the real part
        bus.read_byte_data(R.AK8963_ADDRESS, 0)


def test_mpu6500_reset_detected_too():
    tr = make_track(800)
    bus = FakeMPU9250Bus(**tr, who_am_i=0x70, faults=Faults(self_resets=[(1.0, "mpu")]))
    d = driver(bus, require_magnetometer=False, accel_fs=3)
    blocks = list(I2CSource(d, block_size=100))             # ends with the track: no repeats
    t = np.concatenate([b.t for b in blocks])
    assert d.stats["reinits"] == 1 and np.all(np.diff(t) > 0) and t[-1] == tr["t"][-1]
    for b in blocks:
        k = np.searchsorted(tr["t"], b.t)
        assert np.all(np.abs(b.accel - tr["accel"][k]) <= bounds_accel(d))


def bounds_accel(d):
    return 0.5 * R.accel_scale(d.accel_fs) + 1e-9


def test_unknown_who_am_i_tells_what_to_check():
    with pytest.raises(WrongDeviceError) as e:
        driver(FakeMPU9250Bus(**make_track(50), who_am_i=0x12))
    msg = str(e.value)
    for needle in ("0x12", "WHO_AM_I", "0x68", "0x69", "AD0", "pull-up", "wiring"):
        assert needle in msg
    assert e.value.address == 0x68 and e.value.register == R.MpuReg.WHO_AM_I


def test_other_family_member_refused():
    with pytest.raises(WrongDeviceError, match="MPU-6050"):
        driver(FakeMPU9250Bus(**make_track(50), who_am_i=0x68))


def test_absent_device_error_names_address_and_register():
    bus = FakeMPU9250Bus(**make_track(50), address=0x69)
    with pytest.raises(DeviceIOError) as e:
        driver(bus, address=0x68)
    assert "0x68" in str(e.value) and "WHO_AM_I" in str(e.value) and "AD0" in str(e.value)
    assert e.value.errno == errno.EREMOTEIO
    d = driver(FakeMPU9250Bus(**make_track(50), address=0x69), address=0x69)
    assert d.read_sample() is not None


def test_wrong_ak8963_wia():
    with pytest.raises(WrongDeviceError, match=r"0x0C.*0x47.*0x48"):
        driver(FakeMPU9250Bus(**make_track(50), ak_wia=0x47))


def test_long_reads_split_at_the_32_byte_limit():
    bus = FakeMPU9250Bus(**make_track(50))
    d = driver(bus)
    reads = d.stats["reads"]
    dump = d.read_registers(0x68, 0x00, 0x3A)        # 58 bytes: two SMBus blocks
    assert d.stats["reads"] - reads == 2
    assert list(dump) == [bus.read_byte_data(0x68, r) for r in range(0x3A)]
    with pytest.raises(ValueError):
        bus.read_i2c_block_data(0x68, 0x00, 0x3A)


def test_nacks_retried_until_every_sample_arrives():
    tr = make_track()
    bus = FakeMPU9250Bus(**tr, seed=3, faults=Faults(
        nack_rate=0.05, nack_errnos=(errno.EREMOTEIO, errno.EIO, errno.ETIMEDOUT)))
    d = driver(bus)
    block = d.read_block(1000)
    np.testing.assert_array_equal(block.t, mag_times(tr))
    assert_round_trip(block, tr, d)
    s = d.stats
    assert bus.counters.nacks > 20
    assert s["failures"] == 0 and s["retries"] == bus.counters.nacks
    assert s["nacks"] + s["io_errors"] + s["timeouts"] == bus.counters.nacks
    assert min(s["nacks"], s["io_errors"], s["timeouts"]) > 0


def test_overflow_samples_dropped_and_counted_exactly():
    tr = make_track()
    bus = FakeMPU9250Bus(**tr, seed=5, faults=Faults(hofl_rate=0.1))
    d = driver(bus)
    block = d.read_block(1000)
    t_mag = mag_times(tr)
    dropped = t_mag[bus.hofl_indices]
    assert 5 < len(dropped) == d.stats["overflows"] == bus.counters.hofl
    np.testing.assert_array_equal(block.t, np.setdiff1d(t_mag, dropped))
    assert_round_trip(block, tr, d)


def test_overflow_from_a_field_beyond_full_scale():
    n = 6
    mag = np.tile([10.0, 20.0, 30.0], (n, 1))
    mag[2] = [6000.0, 0.0, 0.0]               # beyond ±4912 µT
    bus = FakeMPU9250Bus(np.arange(n) * 0.01, mag=mag, accel=np.zeros((n, 3)),
                         gyro=np.zeros((n, 3)), temp=np.full(n, 21.0))
    d = driver(bus)
    block = d.read_block(n)
    assert len(block) == n - 1 and d.stats["overflows"] == 1
    assert 0.02 not in block.t


def test_overruns_counted_and_skipped_samples_absent():
    tr = make_track()
    bus = FakeMPU9250Bus(**tr, seed=2, faults=Faults(dor_rate=0.1))
    d = driver(bus)
    block = d.read_block(1000)
    assert 5 < d.stats["overruns"] == bus.counters.dor_reported
    assert len(mag_times(tr)) - len(block) == bus.counters.skipped
    assert_round_trip(block, tr, d)


def read_all(d, bus, limit=2000):
    """Read until the fake has served its track, collecting blocks and the errors raised."""
    blocks, errors = [], []
    for _ in range(limit):
        try:
            b = d.read_block(50)
        except DeviceIOError as e:
            errors.append(e)
            continue
        blocks.append(b)
        if bus.finished and len(b) < 50:
            break
    t = np.concatenate([b.t for b in blocks])
    return t, blocks, errors


@pytest.mark.parametrize("pwr_mgmt_1", [0x01, 0x41])     # datasheet reset value; wakes asleep
def test_vanished_device_is_reinitialised_when_it_returns(pwr_mgmt_1):
    tr = make_track(800)
    bus = FakeMPU9250Bus(**tr, faults=Faults(vanish=[(1.0, 1.6)]), power_on_pwr_mgmt_1=pwr_mgmt_1)
    d = driver(bus, accel_fs=3, gyro_fs=3)
    t, blocks, errors = read_all(d, bus)
    assert errors and all(e.address == 0x68 and "WHO_AM_I" in str(e) for e in errors)
    assert d.stats["reinits"] == 1
    assert t.min() < 1.0 and t.max() > 1.9 and not np.any((t >= 1.0) & (t < 1.6))
    for b in blocks:
        assert_round_trip(b, tr, d)        # nothing read at the default ranges slips through
    assert bus.violations == []


@pytest.mark.parametrize("which", ["mpu", "ak", "both"])
def test_self_reset_detected_and_reinitialised(which):
    tr = make_track(800)
    bus = FakeMPU9250Bus(**tr, faults=Faults(self_resets=[(1.0, which)]))
    d = driver(bus, accel_fs=3, gyro_fs=3)
    t, blocks, errors = read_all(d, bus)
    assert errors == [] and d.stats["reinits"] == 1 and bus.counters.resets == 1
    assert t.max() > 1.9 and np.sum(t >= 1.0) > 0.8 * np.sum(mag_times(tr) >= 1.0)
    for b in blocks:
        assert_round_trip(b, tr, d)
    assert bus.violations == []


def test_clock_mode_polling_at_twice_the_rate_keeps_up():
    tr = make_track(400)
    now = [0.0]

    def sleep(s):
        now[0] += s
    bus = FakeMPU9250Bus(**tr, clock=lambda: now[0])
    d = MPU9250(bus, clock=bus.now, sleep=sleep)
    block = d.read_block(1000, timeout=3.0)
    # time stamps are the driver's clock at read time: each names the newest sample due by then
    t_mag = mag_times(tr)
    k = np.searchsorted(t_mag, block.t, side="right") - 1
    m = tr["mag"][np.all(np.isfinite(tr["mag"]), axis=1)]
    assert np.all(np.abs(block.mag - m[k]) <= bounds(d)[0])
    started = bus.t[0] + R.RESET_WAIT_S + R.GYRO_STARTUP_S     # bring-up time has passed
    due = np.flatnonzero((t_mag > started + 0.05) & (t_mag <= block.t[-1]))
    assert set(due) <= set(k) and len(set(k)) == len(k)        # none missed, none twice
    assert d.stats["overruns"] == 0 and d.stats["empty_polls"] > 0


def test_slow_polling_in_clock_mode_counts_overruns():
    now = [0.0]

    def sleep(s):
        now[0] += s
    bus = FakeMPU9250Bus(**make_track(400), clock=lambda: now[0])
    src = I2CSource(MPU9250(bus, clock=bus.now, sleep=sleep), rate_hz=40.0, block_size=10)
    block = next(iter(src))
    assert len(block) == 10
    assert src.driver.stats["overruns"] == bus.counters.dor_reported > 0
    assert bus.counters.skipped >= 10


def test_8hz_mode_selectable():
    bus = FakeMPU9250Bus(**make_track(50))
    d = driver(bus, mag_mode=R.AkMode.CONTINUOUS_8HZ)
    assert bus.read_byte_data(R.AK8963_ADDRESS, R.AkReg.CNTL1) == 0x12
    assert d.mag_rate_hz == 8.0 and d.read_sample() is not None
    with pytest.raises(InputError, match="mag_mode"):
        driver(FakeMPU9250Bus(**make_track(50)), mag_mode=R.AkMode.SINGLE)


def test_periodic_health_check():
    d = driver(FakeMPU9250Bus(**make_track()), health_every=50)
    d.read_block(150)
    assert d.stats["health_checks"] >= 2 and d.stats["reinits"] == 0


def test_read_sample_none_when_no_new_data():
    now = [0.0]
    bus = FakeMPU9250Bus(**make_track(), clock=lambda: now[0])
    d = MPU9250(bus, clock=bus.now, sleep=lambda s: None)
    now[0] += 0.5
    assert d.read_sample() is not None
    assert d.read_sample() is None             # same instant: DRDY cleared by the previous read


# --- the sample source ----------------------------------------------------------------------
def test_open_bus_specs():
    with pytest.raises(InputError, match="fake:TRACK.csv"):
        open_bus("bogus")
    with pytest.raises(InputError, match="/dev/i2c-97"):
        open_bus(97)


def test_source_over_a_fake_track_file(tmp_path):
    tr = make_track(600)
    path = tmp_path / "log.csv"
    Track.from_arrays(tr["t"], mag=tr["mag"], accel=tr["accel"], gyro=tr["gyro"],
                                temp=tr["temp"]).write(path)
    src = open_i2c_source(f"fake:{path}", block_size=64, read_track=Track.read,
                          fake_kwargs={"faults": Faults(nack_rate=0.02)})
    blocks = list(src)
    assert all(b.source == f"fake:{path}" for b in blocks) and len(blocks) >= 4
    t = np.concatenate([b.t for b in blocks])
    np.testing.assert_array_equal(t, mag_times(tr))
    for b in blocks:
        assert_round_trip(b, tr, src.driver)


def test_source_rides_out_an_outage():
    tr = make_track(800)
    bus = FakeMPU9250Bus(**tr, faults=Faults(vanish=[(1.0, 1.5)]))
    src = I2CSource(driver(bus), block_size=32, retry_interval_s=0.1)
    t = np.concatenate([b.t for b in src])
    assert src.outages == 1 and src.driver.stats["reinits"] == 1 and t.max() > 1.9


def test_source_gives_up_after_max_outage():
    bus = FakeMPU9250Bus(**make_track(800), faults=Faults(vanish=[(1.0, 1.9)]))
    src = I2CSource(driver(bus), block_size=32, max_outage_s=0.3)
    with pytest.raises(DeviceIOError):
        list(src)


def test_real_track_replayed_through_the_driver(real_tracks_dir):
    """A recorded mixed-rate track (75 Hz mag, 100 Hz IMU) through fake bus + driver + source:
    every magnetometer sample comes back, each channel within half an LSB of the track value
    the chip would hold at that instant."""
    check_replay_through_the_driver(real_tracks_dir / "sunsided_set2_fullsphere.csv.gz")


# -- the same checks on a real bus (opt-in: STREAMCAL_I2C_BUS=N; never in CI) ------------------

@pytest.fixture(params=["fake", "real"])
def any_driver(request):
    """A brought-up driver on the fake bus, or on ``/dev/i2c-$STREAMCAL_I2C_BUS`` when set
    (address ``$STREAMCAL_I2C_ADDRESS``, default 0x68)."""
    if request.param == "fake":
        bus = FakeMPU9250Bus(**make_track(), asa=ASA)
        d = driver(bus)
    else:
        spec = os.environ.get("STREAMCAL_I2C_BUS")
        if not spec:
            pytest.skip("real-hardware check: set STREAMCAL_I2C_BUS=1 (and STREAMCAL_I2C_ADDRESS if "
                        "AD0 is high) to run it against an MPU-9250 on /dev/i2c-1")
        bus = open_bus(spec)
        d = MPU9250(bus, int(os.environ.get("STREAMCAL_I2C_ADDRESS", "0x68"), 0))
    yield d
    d.close()
    bus.close()


def test_any_bus_identifies_the_chip_and_reads_plausible_samples(any_driver):
    d = any_driver
    assert d.chip is R.WHO_AM_I_TABLE[d.read_registers(d.address, R.MpuReg.WHO_AM_I, 1)[0]]
    assert d.chip.supported and d.has_magnetometer
    assert d.read_registers(R.AK8963_ADDRESS, R.AkReg.WIA, 1)[0] == R.AK8963_WIA
    assert np.all((R.asa_factor(d.asa) >= 0.5) & (R.asa_factor(d.asa) < 1.5))
    block = d.read_block(100, timeout=5.0)
    assert len(block) == 100 and np.all(np.diff(block.t) > 0)
    assert np.all(np.isfinite(block.mag)) and np.all(np.isfinite(block.accel))
    assert np.all(np.abs(block.mag) <= R.MAG_FULL_SCALE_UT * 1.5)          # within full scale × ASA
    assert np.all(np.abs(block.accel) <= R.ACCEL_RANGE_G[d.accel_fs] * R.STANDARD_GRAVITY)
    assert np.all(np.abs(block.gyro) <= np.radians(R.GYRO_RANGE_DPS[d.gyro_fs]))
    assert np.all((block.temp > -40.0) & (block.temp < 85.0))               # operating range [PS]
    assert d.check() is False and d.stats["failures"] == d.stats["reinits"] == 0   # config intact
    d.close()                                                               # AK8963 powered down
    mode = d.read_registers(R.AK8963_ADDRESS, R.AkReg.CNTL1, 1)[0]
    assert R.AK_MODE.get(mode) == R.AkMode.POWER_DOWN

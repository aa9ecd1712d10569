"""The register-level fake MPU-9250/AK8963 bus: smbus2 method set and chip protocol."""
import errno

import numpy as np
import pytest
from smbus2 import i2c_msg

from firmware_bridge import registers as R
from firmware_bridge.fake_mpu9250 import FakeMPU9250Bus, Faults
from streamcal.inputs.track import Track

MPU, AK = 0x68, R.AK8963_ADDRESS


def make_track(n=100, seed=0):
    """IMU at 200 Hz, magnetometer at 100 Hz (NaN on odd rows)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.005
    mag = rng.normal(0.0, 40.0, (n, 3))
    mag[1::2] = np.nan
    return dict(t=t, mag=mag, accel=rng.normal(0.0, 6.0, (n, 3)),
                gyro=rng.normal(0.0, 2.0, (n, 3)), temp=24.0 + rng.normal(0.0, 2.0, n))


def enable_bypass(bus):
    bus.write_byte_data(MPU, R.MpuReg.INT_PIN_CFG, 0x02)


def start_mag(bus, mode=R.AkMode.CONTINUOUS_100HZ):
    enable_bypass(bus)
    bus.write_byte_data(AK, R.AkReg.CNTL1, 0x10 | mode)


def test_absent_address_is_remote_io_error():
    bus = FakeMPU9250Bus(**make_track())
    for addr in (0x69, 0x0D, AK):   # AK8963 hidden until bypass is enabled
        with pytest.raises(OSError) as e:
            bus.read_byte_data(addr, 0x00)
        assert e.value.errno == errno.EREMOTEIO
    enable_bypass(bus)
    assert bus.read_byte_data(AK, R.AkReg.WIA) == 0x48
    bus.write_byte_data(MPU, R.MpuReg.USER_CTRL, 0x20)   # I2C master on: bypass no longer works
    with pytest.raises(OSError):
        bus.read_byte_data(AK, R.AkReg.WIA)


def test_ad0_high_address_option():
    bus = FakeMPU9250Bus(**make_track(), address=0x69)
    assert bus.read_byte_data(0x69, R.MpuReg.WHO_AM_I) == 0x71
    with pytest.raises(OSError):
        bus.read_byte_data(0x68, R.MpuReg.WHO_AM_I)


def test_block_limit_is_32_bytes_like_smbus2():
    bus = FakeMPU9250Bus(**make_track())
    assert len(bus.read_i2c_block_data(MPU, 0x00, 32)) == 32
    with pytest.raises(ValueError):
        bus.read_i2c_block_data(MPU, 0x00, 33)
    with pytest.raises(ValueError):
        bus.write_i2c_block_data(MPU, 0x00, [0] * 33)


def test_i2c_rdwr_with_real_messages_matches_smbus_calls():
    bus = FakeMPU9250Bus(**make_track())
    bus.i2c_rdwr(i2c_msg.write(MPU, [R.MpuReg.ACCEL_CONFIG, 0x18]))     # register write
    assert bus.read_byte_data(MPU, R.MpuReg.ACCEL_CONFIG) == 0x18
    w, r = i2c_msg.write(MPU, [R.MpuReg.SMPLRT_DIV]), i2c_msg.read(MPU, 40)  # > 32 is fine here
    bus.i2c_rdwr(w, r)
    expect = [bus.read_byte_data(MPU, R.MpuReg.SMPLRT_DIV + i) for i in range(34)]
    assert list(r)[:34] == expect
    with pytest.raises(OSError):
        bus.i2c_rdwr(i2c_msg.write(0x50, [0]), i2c_msg.read(0x50, 1))


def test_block_write_and_auto_increment():
    bus = FakeMPU9250Bus(**make_track())
    bus.write_i2c_block_data(MPU, R.MpuReg.SMPLRT_DIV, [4, 3, 0x08, 0x10, 3])
    assert bus.read_i2c_block_data(MPU, R.MpuReg.SMPLRT_DIV, 5) == [4, 3, 0x08, 0x10, 3]


def test_reset_restores_defaults_and_hides_magnetometer():
    bus = FakeMPU9250Bus(**make_track())
    start_mag(bus)
    bus.write_byte_data(MPU, R.MpuReg.ACCEL_CONFIG, 0x18)
    bus.write_byte_data(MPU, R.MpuReg.PWR_MGMT_1, 0x80)
    assert bus.read_byte_data(MPU, R.MpuReg.ACCEL_CONFIG) == 0
    assert bus.read_byte_data(MPU, R.MpuReg.PWR_MGMT_1) == R.MPU_RESET_VALUES[R.MpuReg.PWR_MGMT_1]
    assert bus.read_byte_data(MPU, R.MpuReg.WHO_AM_I) == 0x71
    with pytest.raises(OSError):
        bus.read_byte_data(AK, R.AkReg.WIA)


def test_fuse_rom_readable_only_in_fuse_mode():
    bus = FakeMPU9250Bus(**make_track(), asa=(0x90, 0xA0, 0xB0))
    enable_bypass(bus)
    assert bus.read_i2c_block_data(AK, R.AkReg.ASAX, 3) == [0, 0, 0]
    assert bus.violations
    bus.write_byte_data(AK, R.AkReg.CNTL1, R.AkMode.FUSE_ROM)
    assert bus.read_i2c_block_data(AK, R.AkReg.ASAX, 3) == [0x90, 0xA0, 0xB0]


def test_mode_change_must_pass_through_power_down():
    bus = FakeMPU9250Bus(**make_track())
    bus.write_byte_data(MPU, R.MpuReg.INT_PIN_CFG, 0x02)
    bus.write_byte_data(AK, R.AkReg.CNTL1, R.AkMode.FUSE_ROM)
    bus.write_byte_data(AK, R.AkReg.CNTL1, 0x16)
    assert bus.read_byte_data(AK, R.AkReg.CNTL1) == R.AkMode.FUSE_ROM
    assert "without power-down" in bus.violations[-1]


def test_drdy_only_in_continuous_mode_and_cleared_by_st2():
    bus = FakeMPU9250Bus(**make_track())
    enable_bypass(bus)
    assert bus.read_byte_data(AK, R.AkReg.ST1) & R.ST1_DRDY == 0
    bus.write_byte_data(AK, R.AkReg.CNTL1, 0x16)
    assert bus.read_byte_data(AK, R.AkReg.ST1) & R.ST1_DRDY
    bus.read_byte_data(AK, R.AkReg.ST2)
    # ST1 polled without reading the data: the next poll brings a sample that overwrote it
    st1 = bus.read_i2c_block_data(AK, R.AkReg.ST1, 1)[0]
    st1 = bus.read_i2c_block_data(AK, R.AkReg.ST1, 1)[0]
    assert st1 & R.ST1_DRDY and st1 & R.ST1_DOR
    assert bus.counters.skipped == 1


def test_raw_counts_big_endian_imu_little_endian_remapped_mag():
    tr = make_track()
    asa = np.array([0x99, 0xAA, 0xBB])
    bus = FakeMPU9250Bus(**tr, asa=asa)
    start_mag(bus)
    bus.write_byte_data(MPU, R.MpuReg.ACCEL_CONFIG, R.ACCEL_FS_SEL.set(0, 2))
    bus.write_byte_data(MPU, R.MpuReg.GYRO_CONFIG, R.GYRO_FS_SEL.set(0, 3))
    raw_m = bytes(bus.read_i2c_block_data(AK, R.AkReg.ST1, 8))       # first sample: row 0
    raw_i = bytes(bus.read_i2c_block_data(MPU, R.MpuReg.ACCEL_XOUT_H, 14))
    h = np.frombuffer(raw_m[1:7], "<i2")
    m = tr["mag"][0]
    # m_x = H_y, m_y = H_x, m_z = -H_z (HARDWARE.md §4); counts·0.15·(ASA+128)/256 = µT
    lsb = R.mag_scale(16) * (asa + 128) / 256
    np.testing.assert_array_equal(h, np.rint(np.array([m[1], m[0], -m[2]]) / lsb))
    c = np.frombuffer(raw_i, ">i2")
    np.testing.assert_array_equal(c[:3], np.rint(tr["accel"][0] / (9.80665 / 4096)))
    np.testing.assert_array_equal(c[4:], np.rint(tr["gyro"][0] / np.radians(1 / 16.4)))
    assert c[3] == np.rint((tr["temp"][0] - 21.0) * 333.87)
    assert raw_m[7] == R.ST2_BITM


def test_clock_mode_follows_injected_clock_and_reports_overrun():
    now = [100.0]
    tr = make_track()
    bus = FakeMPU9250Bus(**tr, clock=lambda: now[0])
    start_mag(bus)
    now[0] += 0.0401          # four magnetometer samples (10 ms apart) come due; three are lost
    st1 = bus.read_i2c_block_data(AK, R.AkReg.ST1, 8)
    assert st1[0] == R.ST1_DRDY | R.ST1_DOR
    assert bus.counters.skipped == 3
    assert bus.now() == pytest.approx(tr["t"][0] + 0.0401)


def test_nack_injection_is_seeded_and_uses_given_errnos():
    def run():
        bus = FakeMPU9250Bus(**make_track(), seed=7,
                             faults=Faults(nack_rate=0.2, nack_errnos=(errno.EIO, errno.ETIMEDOUT)))
        seen = []
        for _ in range(200):
            try:
                bus.read_byte_data(MPU, R.MpuReg.WHO_AM_I)
            except OSError as e:
                seen.append(e.errno)
        return bus, seen
    bus, seen = run()
    assert len(seen) == bus.counters.nacks and 10 < len(seen) < 80
    assert set(seen) == {errno.EIO, errno.ETIMEDOUT}
    assert run()[1] == seen


def test_vanish_window_returns_at_defaults():
    bus = FakeMPU9250Bus(**make_track(), faults=Faults(vanish=[(0.1, 0.2)]))
    start_mag(bus)
    while bus.now() < 0.1:
        bus.read_i2c_block_data(AK, R.AkReg.ST1, 8)
    refused = 0
    while True:
        try:
            bus.read_byte_data(MPU, R.MpuReg.WHO_AM_I)
            break
        except OSError as e:
            assert e.errno == errno.EREMOTEIO
            refused += 1
    assert refused >= 5 and bus.now() >= 0.2
    assert bus.read_byte_data(MPU, R.MpuReg.INT_PIN_CFG) == 0


def test_context_manager_closes():
    with FakeMPU9250Bus(**make_track()) as bus:
        bus.read_byte_data(MPU, R.MpuReg.WHO_AM_I)
    with pytest.raises(ValueError):
        bus.read_byte_data(MPU, R.MpuReg.WHO_AM_I)


def test_from_track():
    tr = make_track()
    track = Track.from_arrays(tr["t"], mag=tr["mag"], accel=tr["accel"],
                                        gyro=tr["gyro"], temp=tr["temp"])
    bus = FakeMPU9250Bus.from_track(track)
    direct = FakeMPU9250Bus(**tr)
    for b in (bus, direct):
        start_mag(b)
    assert bus.read_i2c_block_data(AK, 2, 8) == direct.read_i2c_block_data(AK, 2, 8)


def test_raw_data_ready_flag_follows_new_imu_rows():
    now = [0.0]
    bus = FakeMPU9250Bus(**make_track(), clock=lambda: now[0])
    status = lambda: bus.read_byte_data(MPU, R.MpuReg.INT_STATUS) & 1   # noqa: E731
    assert status() == 0                                   # RAW_RDY_EN not set
    bus.write_byte_data(MPU, R.MpuReg.INT_ENABLE, 0x01)
    now[0] += 0.0051                                       # one 200 Hz row later
    assert status() == 1 and status() == 0                 # cleared by reading


def test_encoded_rows_are_the_counts_the_chips_serve():
    tr = make_track()
    tr["mag"][4] = [6000.0, 0.0, 0.0]                      # beyond the AK8963's 4912 µT
    bus = FakeMPU9250Bus(**tr)
    start_mag(bus)                                          # 16-bit output
    bus.write_byte_data(MPU, R.MpuReg.ACCEL_CONFIG, R.ACCEL_FS_SEL.set(0, 2))
    bus.write_byte_data(MPU, R.MpuReg.GYRO_CONFIG, R.GYRO_FS_SEL.set(0, 1))
    rows = bus.encoded_rows()                               # settings from the registers
    assert (rows.accel_fs, rows.gyro_fs, rows.mag_bits) == (2, 1, 16)
    np.testing.assert_array_equal(rows.accel_t, tr["t"])
    np.testing.assert_array_equal(rows.mag_t, tr["t"][::2])
    assert rows.accel.shape == rows.gyro.shape == (100, 3) and rows.temp.shape == (100,)
    np.testing.assert_allclose(rows.accel * R.accel_scale(2), tr["accel"], atol=0.5 * R.accel_scale(2))
    np.testing.assert_allclose(rows.gyro * R.gyro_scale(1), tr["gyro"], atol=0.5 * R.gyro_scale(1))
    assert rows.mag_overflow.tolist() == [k == 2 for k in range(50)]
    for k in range(4):    # step mode: each ST1 read serves the next magnetometer row
        st1, *data, st2 = bus.read_i2c_block_data(AK, R.AkReg.ST1, R.MAG_BURST_LEN)
        assert np.frombuffer(bytes(data), "<i2").tolist() == rows.mag[k].tolist()
        assert bool(st2 & R.ST2_HOFL) == rows.mag_overflow[k]
        imu = np.frombuffer(bytes(bus.read_i2c_block_data(MPU, R.MpuReg.ACCEL_XOUT_H, 14)), ">i2")
        j = np.searchsorted(rows.accel_t, bus.now(), side="right") - 1
        assert imu[:3].tolist() == rows.accel[j].tolist() and imu[4:].tolist() == rows.gyro[j].tolist()
        assert imu[3] == rows.temp[j]
    other = bus.encoded_rows(accel_fs=0, mag_bits=14)      # another setting, registers untouched
    assert (other.accel_fs, other.gyro_fs, other.mag_bits) == (0, 1, 14)
    np.testing.assert_allclose(other.mag, np.rint(rows.mag * R.mag_scale(16) / R.mag_scale(14)), atol=1)
    assert bus.encoded_rows().accel_fs == 2
    with pytest.raises(ValueError):
        bus.encoded_rows(mag_bits=12)


# -- raw AK8963 count logs (MPU-9250 recordings in counts) -----------------------------------

AK_COUNTS_META = {"sensor": "mpu9250 (AK8963 16-bit, 100 Hz)",
                  "mag_unit": "counts (nominal 0.15 uT/LSB; ASA not applied)",
                  "mag_axes": "AK8963 chip axes (no accelerometer in this log)"}


def counts_track(meta=AK_COUNTS_META, n=40, seed=3, **channels):
    from streamcal.inputs.track import Track

    rng = np.random.default_rng(seed)
    counts = rng.integers(-300, 300, (n, 3)).astype(float)
    return Track.from_arrays(np.arange(n) * 0.0097, mag=counts, metadata=meta, **channels), counts


def read_mag_bursts(bus, n):
    start_mag(bus)
    return np.array([np.frombuffer(bytes(bus.read_i2c_block_data(AK, R.AkReg.ST1, 8)[1:7]), "<i2")
                     for _ in range(n)])


def test_counts_log_is_served_unchanged_with_neutral_asa():
    track, counts = counts_track()
    bus = FakeMPU9250Bus.from_track(track)
    np.testing.assert_array_equal(read_mag_bursts(bus, len(counts)), counts)
    bus.write_byte_data(AK, R.AkReg.CNTL1, R.AkMode.POWER_DOWN)
    bus.write_byte_data(AK, R.AkReg.CNTL1, R.AkMode.FUSE_ROM)
    assert bus.read_i2c_block_data(AK, R.AkReg.ASAX, 3) == [128, 128, 128]   # adjustment 1.0
    assert R.asa_factor(128) == 1.0
    rows = bus.encoded_rows(mag_bits=14)                    # the other width: rescaled exactly
    np.testing.assert_array_equal(rows.mag, np.rint(counts / 4))


def test_counts_log_through_the_driver_is_uT_in_body_axes():
    from firmware_bridge.mpu9250 import MPU9250

    track, counts = counts_track()
    bus = FakeMPU9250Bus.from_track(track)
    block = MPU9250(bus, clock=bus.now, sleep=lambda s: None).read_block(len(counts))
    assert len(block) == len(counts)
    # body = P · counts · 4912/32760 with P the fixed AK8963 remap (HARDWARE.md §4)
    expect = counts[:, [1, 0, 2]] * np.array([1, 1, -1]) * (4912 / 32760)
    np.testing.assert_allclose(block.mag, expect, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(block.t, track.t)          # timing from t


def test_counts_log_states_asa_and_body_axes_14_bit():
    meta = {"sensor": "mpu9250 (AK8963 14-bit single-shot)", "mag_unit": "counts",
            "mag_axes": "accelerometer body axes (datasheet AK8963 remap applied)",
            "asa": "0xB0, 178 165"}
    track, counts = counts_track(meta)
    bus = FakeMPU9250Bus.from_track(track)
    assert bus.asa.tolist() == [0xB0, 178, 165]
    chip16 = counts[:, [1, 0, 2]] * np.array([1, 1, -1]) * 4      # remap undone, 14 → 16 bit
    np.testing.assert_array_equal(read_mag_bursts(bus, len(counts)), chip16)
    assert any("14-bit" in note and "remap undone" in note for note in bus.notes)


def test_log_without_imu_is_served_at_rest_and_says_so(caplog):
    from firmware_bridge.mpu9250 import MPU9250

    track, counts = counts_track()
    with caplog.at_level("WARNING", logger="firmware_bridge.fake_mpu9250"):
        bus = FakeMPU9250Bus.from_track(track)
    assert any("at rest" in r.getMessage() for r in caplog.records)
    assert any("no accel/gyro/temp" in note for note in bus.notes)
    block = MPU9250(bus, clock=bus.now, sleep=lambda s: None).read_block(10)
    lsb = R.accel_scale(1)                                  # the driver's default ±4 g range
    np.testing.assert_allclose(block.accel, np.tile([0, 0, 9.80665], (10, 1)), atol=0.5 * lsb)
    np.testing.assert_allclose(block.gyro, 0.0, atol=0)
    np.testing.assert_allclose(block.temp, 25.0, atol=0.5 / R.TEMP_SENSITIVITY_LSB_PER_C)
    # only the missing channels are substituted
    acc = np.tile([1.0, -2.0, 9.0], (len(counts), 1))
    bus = FakeMPU9250Bus.from_track(counts_track(accel=acc)[0])
    block = MPU9250(bus, clock=bus.now, sleep=lambda s: None).read_block(5)
    np.testing.assert_allclose(block.accel, acc[:5], atol=0.5 * lsb)
    assert any(note.startswith("no gyro/temp") for note in bus.notes)


@pytest.mark.parametrize("meta, why", [
    ({"sensor": "not stated", "mag_unit": "counts (sensor not stated)"}, "MPU-9250/AK8963"),
    ({"sensor": "ICM-20948 (AK09916)", "mag_unit": "counts", "mag_axes": "as read from the chip"},
     "MPU-9250/AK8963"),
    ({"sensor": "mpu9250", "mag_unit": "counts"}, "mag_axes"),
    ({"sensor": "mpu9250", "mag_unit": "counts", "mag_axes": "AK8963 chip axes", "asa": "1,2"},
     "asa"),
    ({"sensor": "mpu9250", "mag_unit": "counts", "mag_axes": "AK8963 chip axes", "mag_bits": "12"},
     "mag_bits"),
    ({"mag_unit": "gauss"}, "gauss"),
])
def test_unreplayable_track_is_an_input_error_naming_the_file(tmp_path, meta, why):
    from streamcal.errors import InputError

    track, _ = counts_track(meta)
    path = tmp_path / "log.csv"
    track.write(path)
    with pytest.raises(InputError) as e:
        FakeMPU9250Bus.from_track(Track.read(path))
    assert str(path) in str(e.value) and why in str(e.value)
    with pytest.raises(InputError) as e:                   # a Track without a file: "track"
        FakeMPU9250Bus.from_track(track)
    assert str(e.value).startswith("track: ")


def test_wrong_accel_unit_and_empty_track_are_input_errors(tmp_path):
    from streamcal.errors import InputError
    from streamcal.inputs.track import Track

    n = 5
    track = Track.from_arrays(np.arange(n) * 0.01, mag=np.ones((n, 3)), accel=np.ones((n, 3)),
                              metadata={"accel_unit": "g"})
    with pytest.raises(InputError, match="accel_unit 'g'"):
        FakeMPU9250Bus.from_track(track)
    path = tmp_path / "empty.csv"
    path.write_text("# streamcal-track: 1\nt,mx,my,mz\n")
    with pytest.raises(InputError, match="empty.csv:2: no data rows"):   # from Track.read
        FakeMPU9250Bus.from_track(Track.read(path))
    with pytest.raises(InputError, match="track: cannot replay.*empty"):
        FakeMPU9250Bus.from_track(Track.from_arrays(np.zeros(0), mag=np.zeros((0, 3))))

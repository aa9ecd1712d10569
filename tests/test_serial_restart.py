"""Board restarts on the serial link (firmware_bridge/serial_link.py).

A board that reboots (brown-out, watchdog, DTR pulled by a reconnect) sends a HELLO numbered 0
and starts its sequence numbers and its µs clock again. The link must count the restart
(``stats.restarts``, in ``stats.as_dict()``), must not count the reboot as lost frames, and
must time the samples after it from the board's new clock (never as a clock wrap).
Frames are fed with ``fr.encode`` as in tests/test_serial_link.py.
"""
from __future__ import annotations

import numpy as np
import serial

from firmware_bridge import frames as fr
from firmware_bridge.serial_link import SerialLink
from streamcal.samples import SampleBlock
from streamcal.stream import StreamingCalibrator
from tests.test_serial_link import HELLO

MAG = int(fr.Status.MAG_VALID)


def link() -> SerialLink:
    return SerialLink(serial.serial_for_url("loop://", timeout=0.01))


def run(t_us, seq0: int = 0, hello: bool = True) -> bytes:
    """Frames of a board run: its HELLO (numbered ``seq0``) then one sample per ``t_us``."""
    out = fr.encode(HELLO, seq0) if hello else b""
    return out + b"".join(fr.encode(fr.Sample(t_us=int(s), mag=(100, 0, 0), status=MAG),
                                    (seq0 + 1 + i) & 0xFFFF) for i, s in enumerate(t_us))


def read_all(ln: SerialLink) -> np.ndarray:
    t = []
    while (block := ln.read_block(timeout=0.05)) is not None:
        t.append(block.t)
    return np.concatenate(t) if t else np.zeros(0)


def test_first_hello_is_no_restart_and_stats_show_the_counter():
    ln = link()
    ln.feed(run(np.arange(20) * 10_000))
    assert len(read_all(ln)) == 20
    stats = ln.stats.as_dict()
    assert stats["restarts"] == 0 and stats["lost"] == 0 and stats["frames"] == 21


def test_reboot_is_counted_not_lost_and_time_restarts_from_the_board_clock():
    ln = link()
    ln.feed(run(1_000_000 + np.arange(50) * 10_000))        # a board up for a second …
    before = read_all(ln)
    ln.feed(run(2_000 + np.arange(30) * 10_000))            # … reboots: HELLO 0, clock from 0
    after = read_all(ln)
    s = ln.stats
    assert s.restarts == 1 and s.lost == 0 and s.frames == 51 + 31
    assert ln.stats.as_dict()["restarts"] == 1
    np.testing.assert_allclose(before[[0, -1]], [1.0, 1.49])
    np.testing.assert_allclose(after, 0.002 + np.arange(30) * 0.01)


def test_reboot_after_the_clock_passed_half_its_range_is_not_taken_for_a_wrap():
    """Up for more than 35.8 min (2**31 µs): the step back to 0 looks like a wrap to unwrapping
    that continues across the reboot; it must not move time 2**32 µs ahead."""
    ln = link()
    up = 3_000_000_000 + np.arange(10) * 10_000              # 50 min of uptime
    ln.feed(run(up))
    read_all(ln)
    ln.feed(run(5_000 + np.arange(10) * 10_000))
    after = read_all(ln)
    np.testing.assert_allclose(after, 0.005 + np.arange(10) * 0.01)
    assert ln.stats.restarts == 1


def test_samples_queued_before_the_reboot_keep_the_old_clock():
    """The HELLO of the reboot may be decoded while samples of the old run still wait: they
    are timed with the old clock (wrapped), the new ones with the new clock."""
    ln = link()
    old = [0xFFFFFF00 - 20_000, 0xFFFFFF00 - 10_000, 0xFFFFFF00]
    ln.feed(run(old))
    np.testing.assert_allclose(ln.read_block(max_samples=1, timeout=0.05).t,
                               [old[0] / 1e6])
    ln.feed(run([0x100 + 0, 0x100 + 10_000, 0x100 + 20_000], seq0=3, hello=False))   # wrapped
    ln.feed(run([1_000, 11_000]))                                                     # reboot
    t = read_all(ln)
    wrapped = (np.array([0x100, 0x100 + 10_000, 0x100 + 20_000]) + (1 << 32)) / 1e6
    np.testing.assert_allclose(t, np.concatenate([np.array(old[1:]) / 1e6, wrapped,
                                                  [0.001, 0.011]]))
    assert ln.stats.restarts == 1 and ln.stats.lost == 0


def test_sequence_wrapping_to_zero_on_a_hello_is_no_restart():
    """A HELLO answering GET_INFO can be numbered 0 when the counter wraps from 65535."""
    ln = link()
    ln.feed(run(np.arange(5) * 10_000, seq0=0xFFFF - 5))       # HELLO 65530, samples … 65535
    ln.feed(fr.encode(HELLO, 0) + fr.encode(fr.Sample(t_us=50_000, status=MAG), 1))
    t = read_all(ln)
    assert ln.stats.restarts == 0 and ln.stats.lost == 0
    np.testing.assert_allclose(t, np.arange(6) * 0.01)


def test_lost_frames_are_still_counted_around_a_reboot():
    ln = link()
    ln.feed(run(np.arange(10) * 10_000))                       # HELLO 0, samples 1 … 10
    frames = [fr.encode(fr.Sample(t_us=100_000 + i * 10_000, status=MAG), 11 + i) for i in range(5)]
    ln.feed(frames[0] + frames[3] + frames[4])                 # seq 12 and 13 lost
    ln.feed(run(np.arange(5) * 10_000))                        # reboot
    read_all(ln)
    assert ln.stats.lost == 2 and ln.stats.restarts == 1


def test_calibrator_keeps_time_monotone_across_the_reboot():
    """Downstream: the streaming calibrator sees the board clock go back and shifts it."""
    ln = link()
    ln.feed(run(1_000_000 + np.arange(300) * 10_000))
    ln.feed(run(np.arange(300) * 10_000))
    sc = StreamingCalibrator(synchronous=True)
    events = []
    while (block := ln.read_block(max_samples=100, timeout=0.05)) is not None:
        events += sc.ingest(SampleBlock(t=block.t, mag=block.mag))
    events += sc.close()
    resets = [e for e in events if e.kind == "clock_reset"]
    assert len(resets) == 1 and ln.stats.restarts == 1
    assert resets[0].data["back_by"] > 3.9

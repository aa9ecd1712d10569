"""The streaming calibrator keeps sample time monotone when the board's clock restarts.

A USB reconnect resets an Uno (DTR) and a brown-out reboots it: its µs counter starts again near
0 and the serial link hands on times that go back by the whole session. The calibrator shifts
those and all later times so that they continue from the last one (``clock_reset`` event);
forgetting by onset, the held samples of a disturbance and its persist test then work as on a
monotone clock. Simulated boards (``streamcal.sim``) as in ``test_stream_disturbance.py``.
"""
import numpy as np
import pytest

from streamcal.samples import SampleBlock
from streamcal.stream import StreamingCalibrator
from tests.test_stream_disturbance import B_TRUE, BOUND, clean, feed, of_kind, truth

T_RESET = 120.0


def restarted(seed, duration=260.0, delta=(0.0, 0.0, 0.0)):
    """(t, m): a clean session whose clock restarts at 0 at ``T_RESET`` s, with a new hard iron
    ``delta`` (µT) from then on."""
    t, m = clean(seed, duration)
    after = t >= T_RESET
    t = np.where(after, t - T_RESET, t)
    m = m + after[:, None] * np.asarray(delta)
    return t, m, after


def test_restart_with_a_magnet_is_one_change_and_forgets_the_old_samples():
    delta = np.array([12.0, -8.0, 6.0])            # a magnet put on the board during the reset
    t, m, after = restarted(2, delta=delta)
    sc = StreamingCalibrator(synchronous=True)
    events = feed(sc, t[~after], m[~after])
    assert sc.calibration is not None and not sc.stale
    events = feed(sc, t[after], m[after])
    (reset,) = of_kind(events, "clock_reset")
    assert reset.data["back_by"] == pytest.approx(T_RESET, abs=0.05)
    assert reset.data["shift"] >= reset.data["back_by"]
    # One change, not a cycle of drift/forgot as with times that restart.
    drift, forgot = of_kind(events, "drift"), of_kind(events, "forgot")
    assert len(drift) == 1 and len(forgot) == 1
    assert T_RESET <= drift[0].data["onset"] <= drift[0].t <= T_RESET + 30.0
    # The old environment's samples are gone: every stored sample is from after the onset.
    snap = sc.buffer.snapshot()
    assert snap.t.min() >= drift[0].data["onset"]
    assert forgot[0].data["dropped"] > 0 and forgot[0].t == drift[0].t
    times = [e.t for e in events if e.t is not None]
    assert times == sorted(times)
    assert sc.calibration.model_error(truth(B_TRUE + delta)) < BOUND and not sc.stale


def test_restart_alone_changes_nothing_but_the_clock():
    t, m, after = restarted(3, duration=200.0)
    sc = StreamingCalibrator(synchronous=True)
    feed(sc, t[~after], m[~after])
    cal = sc.calibration
    assert cal is not None
    events = feed(sc, t[after], m[after])
    assert len(of_kind(events, "clock_reset")) == 1
    kinds = {e.kind for e in events}
    assert not kinds & {"drift", "forgot", "disturbance", "recalled"}
    snap = sc.buffer.snapshot()
    assert snap.t.max() > T_RESET                  # new samples carry the continued time
    assert sc.calibration.model_error(truth()) < BOUND


def test_restart_inside_one_large_block_and_twice():
    """A block larger than the stage carries the restart in its middle; the clock then restarts
    a second time: every time handed on is monotone and each restart is reported once."""
    t, m = clean(4, 90.0)
    t = t.copy()
    t[3000:] -= 30.0        # restart to 0 at 30 s …
    t[6000:] -= 30.0        # … and again at 30 s later
    sc = StreamingCalibrator(synchronous=True)
    events = sc.ingest(SampleBlock(t=t[:4000], mag=m[:4000]))      # one block, restart inside
    events += feed(sc, t[4000:], m[4000:], block=37)
    resets = of_kind(events, "clock_reset")
    assert len(resets) == 2
    assert [r.data["back_by"] for r in resets] == pytest.approx([30.0, 30.0], abs=0.05)
    assert resets[1].data["shift"] == pytest.approx(resets[0].data["shift"] + 30.0, abs=0.05)
    # Stored samples of the third stretch carry times after both earlier stretches.
    snap = sc.buffer.snapshot()
    rows = _rows(snap.m)
    first = np.isin(rows, _rows(m[:3000])) & ~np.isin(rows, _rows(m[3000:]))
    third = np.isin(rows, _rows(m[6000:])) & ~np.isin(rows, _rows(m[:6000]))
    assert first.any() and snap.t[first].max() < 30.0
    assert third.any() and snap.t[third].min() > 60.0
    assert sc.clock.t_last == pytest.approx(t[-1] + resets[1].data["shift"])


def _rows(a):
    """One hashable value per row of ``a`` (n,3)."""
    a = np.ascontiguousarray(a, dtype=float)
    return a.view(np.dtype((np.void, a.dtype.itemsize * 3))).ravel()


def test_a_replacement_calibrator_continues_the_clock_of_the_buffer_it_takes_over():
    """The daemon's reload (SIGHUP) builds a new calibrator on the old one's buffer: with
    ``adopt_clock`` the samples after a restart keep landing after the stored ones, so forgetting
    by onset still drops the old ones; without it they would look older than everything stored."""
    t, m, after = restarted(3, duration=200.0)
    old = StreamingCalibrator(synchronous=True)
    feed(old, t[~after], m[~after])
    first = np.flatnonzero(after)[:1500]
    feed(old, t[first], m[first])                    # the restart happens in the old one
    stored_max = old.buffer.snapshot().t.max()
    new = StreamingCalibrator(synchronous=True, buffer=old.buffer)
    new.adopt_clock(old)
    rest = np.flatnonzero(after)[1500:]
    events = feed(new, t[rest], m[rest])
    assert not of_kind(events, "clock_reset")        # the board clock did not go back again
    assert new.buffer.snapshot().t.max() > stored_max
    newest = new.buffer.snapshot().t.max()           # on the continued clock
    assert t[rest][0] + old.clock.shift < newest <= t[rest][-1] + old.clock.shift + 1e-9

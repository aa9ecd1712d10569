"""Environment changes on real recordings: the change is detected (drift), the buffer forgets, a
worse calibration is never accepted, and the calibration recovers once the field is clean again.

- BROAD 32: a magnet rides on the board for t ∈ [34, 100] s. The device starts with the
  calibration of an undisturbed session of the same sensor (BROAD 02) in its state directory,
  as a daemon would; the recording alone never covers enough of the sphere for a refit.
- sunsided set 1 → set 2: two sessions of one board whose hard iron differs; both are replayed
  through the same calibrator, the second shifted in time after the first.
"""
import numpy as np
import pytest

from streamcal.samples import SampleBlock
from streamcal.fitting import fit
from streamcal.stream import CalibrationStore, CoverageBuffer, StreamingCalibrator
from streamcal.stream.guard import holdout_error
from streamcal.inputs.track import Track


def replay(sc, tracks, shifts, block=100):
    """Feed ``tracks`` one after the other (times shifted); returns the events and, after each
    block, (t_end, calibration in use, stale)."""
    events, in_use = [], []
    for track, shift in zip(tracks, shifts):
        for b in track.blocks(block):
            b = SampleBlock(t=b.t + shift, mag=b.mag, accel=b.accel, gyro=b.gyro, temp=b.temp,
                            aux=b.aux)
            events += sc.ingest(b)
            in_use.append((float(b.t[-1]), sc.calibration, sc.stale))
    events += sc.close()
    return events, in_use


def of_kind(events, kind):
    return [e for e in events if e.kind == kind]


def assert_never_worse(events):
    """Every acceptance beat the calibration in use on held-out samples, by the guard's rule."""
    for e in of_kind(events, "accepted"):
        assert e.data["reason"] in ("first_calibration", "better_on_holdout")
        if e.data["limit"] is not None:
            assert e.data["value"] <= e.data["limit"]


@pytest.fixture(scope="module")
def broad(real_tracks_dir):
    before = fit(Track.read(real_tracks_dir / "broad_02_undisturbed_slow_rotation_B.csv.gz"))
    return before, Track.read(real_tracks_dir / "broad_32_attached_magnet_1cm.csv.gz")


def test_broad32_magnet_detected_forgotten_and_recovered(broad, tmp_path):
    before, track = broad
    CalibrationStore(tmp_path / "state").save(before)
    sc = StreamingCalibrator(store=CalibrationStore(tmp_path / "state"), synchronous=True)
    events, in_use = replay(sc, [track], [0.0])
    assert of_kind(events, "loaded")
    drift = of_kind(events, "drift")
    assert drift, "the magnet was not detected"
    assert 34.0 <= drift[0].t <= 45.0 and drift[0].data["value"] > drift[0].data["limit"]
    forgot = of_kind(events, "forgot")[0]
    assert forgot.t == drift[0].t and forgot.data["dropped"] > 0
    # Before the magnet: no drift, the loaded calibration in use.
    assert all(cal is not None and cal.model_error(before) == 0.0 and not stale
               for t, cal, stale in in_use if t < 34.0)
    # While the magnet rides on the board, the calibration in use is flagged stale.
    assert all(stale for t, _, stale in in_use if 50.0 <= t <= 95.0)
    assert_never_worse(events)
    # After the magnet is gone, the calibration in use is the pre-magnet one again, in force.
    recalled = of_kind(events, "recalled")
    assert recalled and 95.0 <= recalled[-1].t <= 105.0
    after = [(cal, stale) for t, cal, stale in in_use if t >= 105.0]
    assert after and all(not stale and cal.model_error(before) < 0.01 for cal, stale in after)
    m = track.mag[track.t_mag >= 105.0]
    assert holdout_error(sc.calibration, m) <= 1.2 * holdout_error(before, m)
    # The store holds the calibration in use.
    np.testing.assert_allclose(CalibrationStore(tmp_path / "state").load().calibration.K,
                               sc.calibration.K)


@pytest.fixture(scope="module")
def sunsided(real_tracks_dir):
    s1 = Track.read(real_tracks_dir / "sunsided_set1_tiltsphere.csv.gz")
    s2 = Track.read(real_tracks_dir / "sunsided_set2_fullsphere.csv.gz")
    return s1, s2


def test_sunsided_session_change_detected_and_recalibrated(sunsided):
    s1, s2 = sunsided
    shift = float(s1.t[-1]) + 10.0
    sc = StreamingCalibrator(synchronous=True, buffer=CoverageBuffer(covariates=("temp",)))
    events, in_use = replay(sc, [s1, s2], [0.0, shift])
    accepted = of_kind(events, "accepted")
    first = [e for e in accepted if e.t < shift]
    assert first, "no calibration from set 1"
    cal1 = [cal for t, cal, _ in in_use if t < shift][-1]
    # The hard iron differs between the sessions: the change is detected early in set 2.
    drift = of_kind(events, "drift")
    assert len(drift) >= 1 and shift <= drift[0].t <= shift + 10.0
    assert drift[0].data["onset"] >= shift
    forgot = of_kind(events, "forgot")[0]
    assert forgot.data["dropped"] > 0 and forgot.data["onset"] >= shift
    assert_never_worse(events)
    # No set-1 calibration is recalled into set 2, and it recalibrates on set 2's samples.
    assert not of_kind(events, "recalled")
    second = [e for e in accepted if e.t > drift[0].t]
    assert second
    ref = fit(s2)
    assert sc.calibration.model_error(ref) < 0.02 < cal1.model_error(ref)
    assert not sc.stale
    m2 = s2.mag
    assert holdout_error(sc.calibration, m2) < 0.5 * holdout_error(cal1, m2)

"""Coverage is reported only when the buffer's frame is a sphere through the samples: a board
at rest (a cluster of noise) has no directions, so its coverage is "not measured", never a
percentage (it read 93 % with "coverage is good: no action needed" before)."""
import json
import re

import numpy as np

from streamcal.cli import main
from streamcal.inputs.track import Track
from streamcal.stream import StreamingCalibrator
from streamcal.stream.coverage import coverage_words
from streamcal.stream.running_sphere import FRAME_SPREAD
from tests.test_stream_calibrator import feed, kinds, spiral_track


def _at_rest(seconds=30.0, rate=100.0, sigma=0.3, seed=0):
    t = np.arange(0.0, seconds, 1.0 / rate)
    m = np.array([20.0, 5.0, -40.0]) + np.random.default_rng(seed).normal(0, sigma, (len(t), 3))
    return t, m


def test_a_board_at_rest_has_no_coverage():
    sc = StreamingCalibrator(synchronous=True)
    events = feed(sc, *_at_rest())
    report = sc.coverage
    assert not report.measured and sc.buffer.measured_fraction is None
    assert report.to_dict()["coverage"] is None and report.to_dict()["empty_cap_deg"] is None
    assert "no sphere" in report.hint and f"more than {FRAME_SPREAD:.0%}" in report.hint
    assert report.text().startswith("coverage not measured")
    assert "coverage" not in kinds(events)            # no milestone claimed
    assert sc.buffer.fraction > 0.5                   # what the noise would have shown


def test_a_turning_board_has_coverage_before_its_first_calibration():
    sc = StreamingCalibrator(synchronous=True)
    events = feed(sc, *spiral_track(20.0))
    assert sc.calibration is None                     # framed by the running sphere alone
    report = sc.coverage
    assert report.measured and 0.1 < report.fraction < 1.0
    assert "coverage" in kinds(events)
    assert report.to_dict()["coverage"] == round(report.fraction, 4)
    assert sc.buffer.measured_fraction == sc.buffer.fraction


def test_before_the_first_estimate_nothing_is_measured():
    sc = StreamingCalibrator(synchronous=True)
    t, m = spiral_track(0.5)                          # 50 samples: no sphere estimate yet
    feed(sc, t, m)
    assert not sc.coverage.measured and "an estimate comes every" in sc.coverage.hint


def test_one_large_block_is_framed_by_its_own_samples():
    # the frame is judged after the block joins the buffer (it was judged before: a whole
    # recording fed at once stayed "not measured")
    sc = StreamingCalibrator(synchronous=True)
    feed(sc, *spiral_track(20.0), block=2000)
    assert sc.coverage.measured and sc.coverage.fraction > 0.1


def test_replay_of_a_board_at_rest_says_not_measured(tmp_path, capsys):
    path = tmp_path / "rest.csv"
    t, m = _at_rest()
    Track.from_arrays(t, mag=m).write(path)
    assert main(["replay", str(path), "--json"]) == 1         # no calibration
    lines = capsys.readouterr().out.splitlines()
    parsed = [json.loads(line, parse_constant=lambda c: (_ for _ in ()).throw(ValueError(c)))
              for line in lines]                               # strict JSON: no NaN
    summary = parsed[-1]
    assert summary["event"] == "summary" and summary["coverage"] is None
    assert "coverage not measured" in summary["message"]
    # no percentage anywhere: the summary's why, its environments, the fits started
    assert not re.search(r"cover \d+%", summary["why"]) and "not measured" in summary["why"]
    assert all(e["coverage"] is None for e in summary["environments"])
    started = [e for e in parsed if e["event"] == "fit_started"]
    assert started and all(e["coverage"] is None and "coverage not measured" in e["message"]
                           for e in started)
    assert not any(e["event"] == "coverage" for e in parsed)


def test_coverage_words():
    assert coverage_words(None) == "coverage not measured"
    assert coverage_words(0.934) == "coverage 93%"

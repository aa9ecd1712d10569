"""``streamcal replay``: events as JSON lines, summary, state directory left as the daemon's."""
import json

import numpy as np

import streamcal.inputs.track as track_mod
from streamcal.cli import main


def _write_track(path, duration, seed=0, cap=None):
    t = np.arange(0.0, duration, 0.01)
    th = np.pi * ((t / 60.0) % 1.0) if cap is None else np.radians(cap) * np.ones_like(t)
    ph = 2 * np.pi * t / 4.0
    d = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], axis=1)
    rng = np.random.default_rng(seed)
    m = 48.0 * d + [10.0, -20.0, 30.0] + rng.normal(scale=0.3, size=d.shape)
    temp = 25.0 + 0.01 * t
    track_mod.Track.from_arrays(t, mag=m, temp=temp).write(path)
    return path


def test_replay_json_events_and_state_dir(tmp_path, capsys):
    track = _write_track(tmp_path / "spin.csv", 70.0)
    state = tmp_path / "state"
    code = main(["replay", str(track), "--json", "--sync-fits", "--state-dir", str(state),
                 "--block", "100"])
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert code == 0
    kinds = [e["event"] for e in lines]
    assert "coverage" in kinds and "fit_started" in kinds and "accepted" in kinds
    assert kinds[-1] == "summary" and lines[-1]["accepted"] == kinds.count("accepted")
    accepted = [e for e in lines if e["event"] == "accepted"]
    assert all(e["reason"] in ("first_calibration", "better_on_holdout") for e in accepted)
    np.testing.assert_allclose(lines[-1]["b"], [10.0, -20.0, 30.0], atol=0.5)
    from streamcal.stream import CalibrationStore

    loaded = CalibrationStore(state).load()
    assert loaded.path.name == "calibration.json"
    np.testing.assert_allclose(loaded.calibration.b, lines[-1]["b"])


def test_replay_without_enough_coverage_exits_1(tmp_path, capsys):
    track = _write_track(tmp_path / "flat.csv", 20.0, cap=90.0)    # one great circle only
    code = main(["replay", str(track), "--sync-fits"])
    captured = capsys.readouterr()
    assert code == 1
    assert "no calibration" in captured.err and "missing" in captured.err
    assert "replayed" in captured.out

"""One story (SPEC §4): every before/after pair of a diagnosis is on one sample set with its n,
the ladder falls when the missing effect is added, and the command the diagnosis recommends
gives, pasted, the rms it promised — for a fresh tumble and for a flight-like slice against a
held calibration. Simulated data only: a fresh clone runs every case."""
from __future__ import annotations

import json

import numpy as np
import pytest

import streamcal
from streamcal.cli import main
from streamcal.inputs.track import Track
from streamcal.sim import simulate
from streamcal.sim.yaw_slice import yaw_slice

K_TRUE = np.array([[47.0, 0.8, -0.5], [0.0, 49.5, 0.6], [0.0, 0.0, 46.0]])
B_TRUE = np.array([12.0, -7.0, 20.0])
MOTOR_DIRECTION = np.array([0.6, -0.3, 0.74]) / np.linalg.norm([0.6, -0.3, 0.74])
MOTOR_UT = 4.0


def _check_ladder(d) -> None:
    """The contract of the ladder and of the candidates it adds."""
    steps = d.to_dict()["ladder"]
    assert d.rms == steps[0]["rms"]
    assert len({s["n"] for s in steps}) == 1
    for above, step in zip(steps, steps[1:]):
        if step["residual"] == above["residual"]:
            assert step["rms_before"] == above["rms"]
    rows = {c["effect"]: c for c in d.to_dict()["candidates"]}
    for step in steps[1:]:
        row = rows[step["added"]]
        assert (row["rms_before"], row["rms_after"], row["n"]) == \
            (step["rms_before"], step["rms"], step["n"])


def _run_json(argv, capsys) -> dict:
    assert main([*argv, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


@pytest.fixture(scope="module")
def warm_up(tmp_path_factory):
    """A tumble whose only missing effect is a temperature offset, written as a track file."""
    res = simulate(90.0, 7, effects={"temperature_offset": 0.4})
    path = tmp_path_factory.mktemp("story") / "warm_up.csv"
    res.track.write(path)
    return path


@pytest.mark.slow
def test_fresh_tumble_promise_is_what_the_pasted_command_gives(warm_up, capsys):
    d = streamcal.diagnose(Track.read(warm_up))
    assert d.verdict == "effect_missing" and d.candidates[0].effect == "temperature_offset"
    _check_ladder(d)
    assert d.ladder[-1]["rms"] < 0.8 * d.ladder[0]["rms"]
    assert d.next_step[:3] == ("streamcal", "fit", str(warm_up))
    assert "temperature_offset" in d.summary and f"{d.ladder[0]['n']} samples" in d.summary
    got = _run_json(d.next_step[1:], capsys)
    assert got["rms"] == pytest.approx(d.ladder[-1]["rms"], rel=0.01)
    assert got["n"] - got["n_outliers"] == pytest.approx(d.ladder[-1]["n"], rel=0.01)


@pytest.mark.slow
def test_the_loop_closes_once_the_effect_is_in_the_model(warm_up):
    d = streamcal.diagnose(Track.read(warm_up), model=("hard_iron", "soft_iron",
                                                       "temperature_offset"))
    assert d.verdict == "at_noise_floor", d.summary
    assert d.next_step is None and "Nothing to do" in d.summary


def _flight(seed: int = 3) -> tuple[Track, np.ndarray]:
    """A yaw slice (a vehicle turning, tilts of ±10°) with a motor field proportional to a
    throttle channel that steps between hover and climb; returns the track and the throttle."""
    res = yaw_slice(120.0, seed, K=K_TRUE, b=B_TRUE, noise_uT=0.15)
    track = res.track
    t = np.asarray(track.t)
    throttle = np.clip(0.45 + 0.35 * np.sign(np.sin(2 * np.pi * t / 23.0))
                       + 0.05 * np.sin(2 * np.pi * t / 3.1), 0.0, 1.0)
    cols = {k: np.array(v) for k, v in track.columns.items()}
    rows = np.asarray(track.mag_rows)
    for i, k in enumerate(("mx", "my", "mz")):
        cols[k][rows] += MOTOR_UT * throttle[rows] * MOTOR_DIRECTION[i]
    cols["throttle"] = throttle
    return Track(cols, track.metadata), throttle


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    track, _ = _flight()
    where = tmp_path_factory.mktemp("flight")
    path, cal_path = where / "flight.csv", where / "cal.json"
    track.write(path)
    streamcal.Calibration(K=K_TRUE, b=B_TRUE).save(cal_path)
    return path, cal_path


@pytest.mark.slow
def test_motor_field_on_a_slice_is_the_missing_effect_not_outliers(flight, tmp_path, capsys):
    path, cal_path = flight
    track = Track.read(path)
    cal = streamcal.Calibration.load(cal_path)
    d = streamcal.diagnose(track, calibration=cal, recording=[str(path)], cal_arg=str(cal_path))
    assert d.candidates[0].effect == "aux_interference" and d.verdict == "effect_missing"
    _check_ladder(d)
    steps = d.ladder
    assert all(b["rms"] < a["rms"] for a, b in zip(steps, steps[1:]))   # the ladder falls
    # the motor field is explained, not rejected: the last model keeps nearly every sample
    assert steps[-1]["n_outliers"] < 0.02 * d.n
    assert d.next_step[:5] == ("streamcal", "fit", str(path), "--cal", str(cal_path))
    out = tmp_path / "refined.json"
    argv = [*d.next_step[1:-1], str(out)]
    got = _run_json(argv, capsys)
    assert got["rms"] == pytest.approx(steps[-1]["rms"], rel=0.01)
    refined = streamcal.Calibration.load(out)
    assert "aux_interference" in refined.effects and refined.extra.get("held") is not None


def test_fit_and_diagnosis_count_outliers_by_one_rule(warm_up):
    """``fit`` reports its rms over the same samples a diagnosis counts as that model's
    inliers (the fit's widths, widened over a disturbance's ramps)."""
    track = Track.read(warm_up)
    cal = streamcal.fit(track, add=["temperature_offset"])
    d = streamcal.diagnose(track, model=cal.model, candidates=[], ladder=False)
    assert d.n_outliers == cal.n_outliers
    assert d.rms == pytest.approx(cal.rms, rel=1e-9)


def test_a_percentage_is_computed_from_the_two_numbers_shown(warm_up, capsys):
    assert main(["diagnose", str(warm_up)]) == 0
    text = capsys.readouterr().out
    import re

    for line in text.splitlines():
        m = re.match(r"^(\S+)\s+sensor\s+([\d.]+)\s+([\d.]+)\s+([+-]\d+)%", line)
        if m:
            before, after, pct = float(m.group(2)), float(m.group(3)), int(m.group(4))
            assert pct == round(100 * (after / before - 1)), line


@pytest.mark.slow
@pytest.mark.parametrize("effect,size", [("time_lag", 0.02), ("mag_accel_misalignment", 0.06)])
def test_the_loop_closes_on_a_tied_residual(effect, size):
    """A recording whose only missing effect is judged on the gravity-tied residual: named
    first, then, once in the model, at the noise floor — the gravity-tied residual's own
    (streamcal.diagnosis.tied_noise), which its rms is compared with."""
    track = simulate(60.0, 11, effects={effect: size}).track
    before = streamcal.diagnose(track)
    assert before.verdict == "effect_missing" and before.candidates[0].effect == effect
    after = streamcal.diagnose(track, model=("hard_iron", "soft_iron", effect))
    assert after.residual == "gravity_tied"
    assert after.verdict == "at_noise_floor", after.summary
    assert after.rms <= 1.5 * after.floor_for("gravity_tied")


def _ev(norms, inliers, p):
    """A fitted model as the story sees it: residuals (N,3) along x, inliers, parameters."""
    norms = np.asarray(norms, float)
    r = np.column_stack([norms, np.zeros_like(norms), np.zeros_like(norms)])
    from types import SimpleNamespace

    return SimpleNamespace(r=r, rss=norms ** 2, inliers=np.asarray(inliers, bool), p=p)


def test_a_ladder_on_two_residuals_keeps_the_inliers_of_its_last_model_on_each():
    """The tied step's outliers are judged on another residual: a burst the tied model keeps is
    still left out of every step, because the last sensor-residual model rejects it."""
    from streamcal.diagnosis import story
    from streamcal.diagnosis.candidates import Candidate

    rng = np.random.default_rng(0)
    n = 400
    burst = np.zeros(n, bool)
    burst[100:120] = True
    base = _ev(np.where(burst, 30.0, 1.0 + 0.1 * rng.standard_normal(n)), ~burst, 9)
    sensor = _ev(np.where(burst, 30.0, 0.5 + 0.05 * rng.standard_normal(n)), ~burst, 12)
    tied_ref = _ev(np.full(n, 3.0), np.ones(n, bool), 12)
    tied = _ev(np.full(n, 2.0), np.ones(n, bool), 15)
    kinds = {id(base): "sensor", id(sensor): "sensor", id(tied_ref): "gravity_tied",
             id(tied): "gravity_tied"}
    first = Candidate("temperature_offset", 0.0, 0.0, "", 3, True, None,
                      _evaluated=sensor, _reference=base)
    second = Candidate("time_lag", 0.0, 0.0, "", 3, True, None, _evaluated=tied,
                       _reference=tied_ref)
    steps, shown, _ = story.tell(("hard_iron",), base, lambda ev: kinds[id(ev)],
                                 [first, second], [first, second], lambda c: True)
    assert [s["n"] for s in steps] == [n - 20] * 3
    assert steps[0]["rms"] == pytest.approx(np.sqrt(np.mean(base.rss[~burst])))
    assert steps[1]["rms_before"] == steps[0]["rms"]
    # a step its own numbers do not support ends the ladder there
    steps, shown, _ = story.tell(("hard_iron",), base, lambda ev: kinds[id(ev)],
                                 [first, second], [first, second],
                                 lambda c: c.effect != "time_lag")
    assert [s.get("added") for s in steps] == [None, "temperature_offset"]
    assert [c.effect for c in shown] == ["temperature_offset"]


def test_a_step_unsupported_on_the_ladders_samples_is_tried_later_not_dropped_with_the_rest():
    """Effect A (a drift) is ranked first on the samples the model with it keeps; effect B (a
    motor field) makes the last model keep the high-throttle samples, where A's step alone is
    lost in the motor field. Told in the order A, B the first step fails and the whole ladder
    would end at the base; climbed again with A barred from the first step, B then A are each
    supported on the same samples."""
    from streamcal.diagnosis import story
    from streamcal.diagnosis.candidates import Candidate

    n = 400
    motor = np.zeros(n, bool)
    motor[300:] = True
    base = _ev(np.where(motor, 10.0, 1.0), ~motor, 9)
    with_a = _ev(np.where(motor, 10.0, 0.5), ~motor, 12)
    with_b = _ev(np.where(motor, 1.0, 1.0), np.ones(n, bool), 12)
    with_both = _ev(np.full(n, 0.5), np.ones(n, bool), 15)

    def candidate(effect, evaluated, reference):
        return Candidate(effect, 0.0, 0.0, "", 3, True, None, _evaluated=evaluated,
                         _reference=reference)

    ranked = [candidate("A", with_a, base), candidate("B", with_b, base)]

    def rank_after(added, rest):     # the other effect on top of the one added
        return [candidate(name, with_both, added[-1]._evaluated) for name in rest]

    def judge(c):
        return c.rms_after < 0.9 * c.rms_before

    plain = story.climb(ranked, rank_after, max_steps=3)
    assert [c.effect for c in plain] == ["A", "B"]
    steps, _, _ = story.tell(("hard_iron",), base, lambda ev: "sensor", plain, ranked, judge)
    assert len(steps) == 1                      # told as climbed: nothing left
    added = story.climb_supported(ranked, rank_after, max_steps=3, model=("hard_iron",),
                                  base=base, residual_of=lambda ev: "sensor", judge=judge)
    assert [c.effect for c in added] == ["B", "A"]
    steps, shown, _ = story.tell(("hard_iron",), base, lambda ev: "sensor", added, ranked,
                                 judge)
    assert [s.get("added") for s in steps] == [None, "B", "A"]
    assert [s["n"] for s in steps] == [n] * 3 and steps[2]["rms"] == pytest.approx(0.5)

"""Checks that a real-data test and its simulated stand-in both run, each on its own data.

Each function asserts one behaviour on what it is given (a diagnosis, a log's path, a replayed
track); the real-data test (tests/conftest.py fixtures) and the simulated one call the same
function, so the two cannot drift apart."""
from __future__ import annotations

import html
import json
import re

import numpy as np
import pytest

from streamcal.cli.diagnose import _text
from streamcal.diagnosis.verdict import FLOOR_FACTOR
from streamcal.report import render_html
from streamcal.report.html import _SCALES_NOTE


def diagnosis_json(d) -> dict:
    """The diagnosis as its JSON output reads it (NaN as null)."""
    return json.loads(json.dumps(d.to_dict(), allow_nan=False, default=lambda v: None))


def check_unexplained_above_a_measured_floor(track, d) -> tuple[dict, str]:
    """An rms several times a measured floor that no candidate explains is ``unexplained``, and
    the misfit is located: every grouping partitions the inlier energy and the samples.
    Returns the JSON and the text output."""
    js = diagnosis_json(d)
    assert js["noise_floor_reliable"] is True and js["noise_floor"] > 0
    assert js["rms"] / js["noise_floor"] > FLOOR_FACTOR
    assert not any(c["significant"] and c["material"] for c in js["candidates"])
    assert js["verdict"] == "unexplained"
    assert f"{FLOOR_FACTOR:g}×" in js["noise_floor_rule"]
    text = _text(d)
    assert "unexplained" in text and js["noise_floor_rule"] in text
    misfit = js["misfit"]
    groups = [misfit["time"], misfit["directions"], misfit["rotation_rate"]["bins"],
              *misfit["covariates"].values()]
    for bins in groups:
        assert sum(b["share"] for b in bins) == pytest.approx(1.0, abs=1e-9)
        assert sum(b["samples"] for b in bins) == pytest.approx(1.0, abs=1e-9)
        assert all(0 <= b["share"] <= 1 for b in bins)
    # the energy is the one rms is computed from: rms² = energy / n over the same inliers
    assert np.sqrt(misfit["energy"] / misfit["n"]) == pytest.approx(js["rms"], rel=1e-9)
    assert misfit["n"] == js["n"] - js["n_outliers"]
    # time bins cover the recording in order
    starts = [b["t"][0] for b in misfit["time"]]
    assert starts == sorted(starts) and starts[0] == pytest.approx(float(track.t_mag[0]), abs=0.1)
    return js, text


def check_held_verdict_follows_the_same_rules(d) -> None:
    """Diagnosed against a calibration, well above a measured floor with no effect both
    significant and material: ``unexplained``, the misfit located, materiality on the floor
    the verdict uses."""
    js = diagnosis_json(d)
    assert js["held"] is not None and js["noise_floor_reliable"] is True
    assert js["rms"] > FLOOR_FACTOR * js["noise_floor"]
    assert not any(c["significant"] and c["material"] for c in js["candidates"])
    assert js["verdict"] == "unexplained"
    assert js["misfit"]["n"] == js["n"] - js["n_outliers"]
    for c, obj in zip(js["candidates"], d.candidates):
        assert obj.significant == (c["significant"] and c["material"])


def check_unmeasurable_floor_is_null_with_its_reason(track, d) -> tuple[list[str], float]:
    """A floor the recording cannot measure (3.33 Hz, turned by hand) is null with its reason,
    the verdict never ``at_noise_floor``, and no output states a ratio to it. Returns the three
    outputs (JSON, text, page) with the rules taken out, and the rms / measured-noise ratio."""
    js = d.to_dict()
    assert js["noise_floor"] is None and js["noise_floor_reliable"] is False
    reason = js["noise_floor_reason"]
    assert "3.33 Hz" in reason and "correlate" in reason
    assert js["noise"]["measured"] > js["rms"]    # what the estimate gave: above the rms
    assert js["verdict"] == "unexplained"         # never at_noise_floor without a floor
    out = json.dumps(js, allow_nan=False, default=lambda v: None)
    text = _text(d)
    page = render_html(track, d, figures=[])
    ratio = js["rms"] / js["noise"]["measured"]
    outputs = []
    for shown in (out, text, page):
        # the rules and the note on the tied residuals state factors, not ratios to a floor
        for rule in (js["noise_floor_rule"], js["significance_rule"], _SCALES_NOTE):
            shown = shown.replace(rule, "").replace(html.escape(rule), "")
        assert "× floor" not in shown and "× the floor" not in shown
        assert "× the noise floor" not in shown
        assert not re.search(r"\d\.\d\d×", shown), re.search(r".{40}\d\.\d\d×.{20}", shown)
        # the ratio as a number of its own (not the first digits of another one)
        assert not re.search(rf"(?<![\d.]){ratio:.2f}(?!\d)", shown)
        outputs.append(shown)
    assert "not measurable" in text and reason in text
    assert "cannot be measured" in page
    return outputs, ratio


def check_significance_and_materiality_apart(d) -> None:
    """time_drift significant (p < 1e-6) but not material (rms down by less than 10 %): the
    text shows both tests and the rule with its numbers."""
    js = d.to_dict()
    drift = next(c for c in js["candidates"] if c["effect"] == "time_drift")
    assert drift["p_value"] < 1e-6 and drift["significant"] is True
    assert drift["rms_after"] > 0.9 * drift["rms_before"] and drift["material"] is False
    for c in js["candidates"]:
        assert c["residual"] in ("sensor", "gravity_tied", "gyro_tied")
        assert c["significant"] == (c["p_value"] < 1e-6)
    rule = js["significance_rule"]
    assert "1e-06" in rule and "10%" in rule and "effective" in rule
    text = _text(d)
    assert rule in text and "not significant" not in text
    line = next(l for l in text.splitlines() if l.startswith("time_drift"))
    assert re.search(r"\byes\s+no\b", line), line


def check_tied_fit_names_both_residuals(text: str) -> None:
    """``fit --add time_lag`` output: the gravity-tied rms printed with its name beside the same
    calibration's (smaller) sensor-residual rms, and no unlabelled rms."""
    tied = re.search(r"rms\s+([\d.]+) µT on the gravity-tied residual", text)
    sensor = re.search(r"rms\s+([\d.]+) µT on the sensor residual", text)
    assert tied and sensor, text
    assert float(sensor.group(1)) < float(tied.group(1))
    assert not re.search(r"rms\s+[\d.]+ µT over", text)


def check_fit_json_names_the_residual(path, capsys) -> None:
    """``fit --json``: a plain fit is on the sensor residual; with mag_accel_misalignment on
    the gravity-tied one, with the sensor-residual rms beside it."""
    from streamcal.cli import main

    assert main(["fit", str(path), "--json"]) == 0
    plain = json.loads(capsys.readouterr().out)
    assert plain["residual"] == "sensor" and "rms_sensor" not in plain
    assert main(["fit", str(path), "--add", "mag_accel_misalignment", "--json"]) == 0
    tied = json.loads(capsys.readouterr().out)
    assert tied["residual"] == "gravity_tied"
    assert tied["rms_sensor"] > 0 and tied["rms_sensor"] != tied["rms"]


def check_report_heading_names_the_file(path, out) -> int:
    """``report``'s heading names the recording's file, not its folder. Returns the exit code."""
    from streamcal.cli import main

    code = main(["report", str(path), "-o", str(out)])
    heading = re.search(r"<h1>(.*?)</h1>", out.read_text()).group(1)
    assert path.name in heading and str(path.parent) not in heading
    return code


# --- ArduPilot DataFlash: the bulk decoder (streamcal.inputs.dataflash_bulk) -----------------

def assert_same_track(a, b, *, metadata=True) -> None:
    """Every column equal to the bit (time included); the metadata too unless told not."""
    assert list(a.columns) == list(b.columns)
    for name in a.columns:
        np.testing.assert_array_equal(a.columns[name], b.columns[name], err_msg=name)
    if metadata:
        assert a.metadata == b.metadata
    assert len(a) == len(b) and a.skipped_rows == b.skipped_rows


def dataflash_messages(data: bytes):
    """The walk over a log's bytes and its messages as sorted (offset, type) pairs."""
    from streamcal.inputs.dataflash_bulk import walk

    chain = walk(data)
    return chain, sorted((int(o), t) for t, offs in chain.offsets.items() for o in offs)


def mag_format_at(data: bytes) -> int:
    """Where the MAG FMT message's Format string starts in ``data``."""
    from streamcal.inputs.dataflash_bulk import FMT_TYPE

    chain, offsets = dataflash_messages(data)
    mag = next(o for o, t in offsets
               if t == FMT_TYPE and chain.formats[data[o + 3]].name == "MAG")
    return mag + 3 + 1 + 1 + 4   # header, Type, Length, Name → Format


def check_bulk_track_equals_pymavlink_track(path) -> None:
    """The bulk decoder and pymavlink's DFReader give the same Track, metadata included."""
    from streamcal.inputs import dataflash

    bulk = dataflash.read_dataflash(path)
    assert_same_track(bulk, dataflash.read_dataflash_pymavlink(path))
    assert len(bulk.t_mag) > 1000 and "read_warnings" not in bulk.metadata


def check_walk_follows_every_message(path) -> None:
    """On a clean log the walk starts at an FMT, skips nothing and finds the messages back to
    back up to the last byte."""
    from streamcal.inputs.dataflash_bulk import FMT_TYPE

    data = path.read_bytes()
    chain, offsets = dataflash_messages(data)
    assert offsets[0] == (0, FMT_TYPE) and not chain.skipped and chain.cut == 0
    ends = [o + chain.formats[t].length for o, t in offsets]
    assert ends[:-1] == [o for o, _ in offsets[1:]] and ends[-1] == len(data)  # back to back


def check_garbage_run_skipped_and_named(path, tmp_path) -> None:
    """A run of foreign bytes between two messages (one looks like a header of an unknown type):
    every message is still read and read_warnings names the run."""
    from streamcal.inputs import dataflash

    data = path.read_bytes()
    _, offsets = dataflash_messages(data)
    at = offsets[len(offsets) // 2][0]
    junk = b"\x00\x11\xa3\x95\xfe\x22" * 3
    bad = tmp_path / "junk.bin"
    bad.write_bytes(data[:at] + junk + data[at:])
    track = dataflash.read_dataflash(bad)
    assert f"Skipped {len(junk)} bad bytes ({len(junk)} at offset {at})" in \
        track.metadata["read_warnings"]
    assert_same_track(track, dataflash.read_dataflash(path), metadata=False)


def check_damaged_message_resynchronised(path, tmp_path) -> None:
    """5 bytes lost inside message j: j is read over the start of j + 1 (there is no checksum),
    the rest of j + 1 is skipped up to the next header, every other message is read."""
    from streamcal.inputs import dataflash

    data = path.read_bytes()
    chain, offsets = dataflash_messages(data)
    j = len(offsets) // 3
    (start, _), (nxt, ntype) = offsets[j], offsets[j + 1]
    bad = tmp_path / "cut_inside.bin"
    bad.write_bytes(data[:start + 10] + data[start + 15:])
    got_chain, got = dataflash_messages(bad.read_bytes())
    shift = [(o - 5 if o > start else o, t) for o, t in offsets]
    assert got == shift[:j + 1] + shift[j + 2:]
    lost = chain.formats[ntype].length - 5
    assert got_chain.skipped == [(nxt, lost)]
    track = dataflash.read_dataflash(bad)
    assert f"Skipped {lost} bad bytes ({lost} at offset {nxt})" in track.metadata["read_warnings"]


def cut_inside_header_and_body(path, tmp_path) -> list:
    """The log cut 2 bytes into a message's header and 7 into it (past the header): each read
    to its last complete message with what was lost in read_warnings. Returns (cut path,
    track) for each."""
    from streamcal.inputs import dataflash

    data = path.read_bytes()
    _, offsets = dataflash_messages(data)
    last = offsets[len(offsets) // 2][0]
    cuts = []
    for keep, left in ((last + 2, 2), (last + 7, 7)):
        cut = tmp_path / f"cut{keep}.bin"
        cut.write_bytes(data[:keep])
        track = dataflash.read_dataflash(cut)
        assert f"truncated: {left} trailing bytes ignored" in track.metadata["read_warnings"]
        cuts.append((cut, track))
    return cuts


def check_unknown_format_character_named(path, tmp_path) -> None:
    """An FMT whose format has a character pymavlink does not know: unknown layout, named."""
    from streamcal.errors import InputError
    from streamcal.inputs import dataflash

    data = bytearray(path.read_bytes())
    data[mag_format_at(bytes(data)) + 1] = ord("X")
    bad = tmp_path / "odd_fmt.bin"
    bad.write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"odd_fmt\.bin.*'X'.*MAG.*unknown layout"):
        dataflash.read_dataflash(bad)


def check_string_where_a_number_is_needed_named(path, tmp_path, layout: bytes) -> None:
    """MAG's ``layout`` (its first two int16 MagX, MagY) rewritten, same size, with one 4-byte
    string in their place: the reader names the field that is not a number."""
    from streamcal.errors import InputError
    from streamcal.inputs import dataflash

    data = bytearray(path.read_bytes())
    at = mag_format_at(bytes(data))
    assert data[at:at + len(layout)] == layout    # the test is about this layout
    data[at:at + len(layout)] = layout.replace(b"hh", b"n", 1) + b"\0"
    bad = tmp_path / "string_mag.bin"
    bad.write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"string_mag\.bin: MAG\.MagX is not a number.*'n'"):
        dataflash.read_dataflash(bad)


def damaged(blob: bytes, rng, head: int, head_share: float) -> bytes:
    """``blob`` with 1–24 bytes flipped, runs inserted or deleted (a share ``head_share`` of them
    in its first ``head`` bytes)."""
    out = bytearray(blob)
    for _ in range(int(rng.integers(1, 25))):
        at = int(rng.integers(0, head if rng.random() < head_share else len(out)))
        op = rng.random()
        if op < 0.4:
            out[at] ^= int(rng.integers(1, 256))
        elif op < 0.7:
            out[at:at] = rng.integers(0, 256, int(rng.integers(1, 9)), dtype=np.uint8).tobytes()
        else:
            del out[at:at + int(rng.integers(1, 9))]
    return bytes(out)


def check_random_damage(head: bytes, tmp_path, seed: int, fmt_block: int) -> None:
    """Flipped, inserted and deleted bytes (70 % of them in the first ``fmt_block`` bytes, where
    the FMT messages are) in ``head``: the reader returns a Track or raises InputError naming
    the file, never another exception."""
    from streamcal.errors import InputError
    from streamcal.inputs import dataflash

    path = tmp_path / "damaged.bin"
    path.write_bytes(damaged(head, np.random.default_rng(seed), fmt_block, 0.7))
    for skip in (False, True):
        try:
            track = dataflash.read_dataflash(path, skip_bad_rows=skip)
        except InputError as exc:
            assert str(path) in str(exc)
        else:
            assert len(track.t_mag) > 0


# --- autopilot logs (DataFlash and ULog) read as tracks ---------------------------------------

def check_convert_writes_the_track_read_recording_gives(log, flight, tmp_path,
                                                        keys: tuple[str, ...]):
    """``convert`` of a log writes the track ``read_recording`` gives (every magnetometer
    sample of ``flight``, time from 0, µT, accel and gyro) with the metadata ``keys``.
    Returns the written track."""
    from streamcal.cli import main
    from streamcal.inputs import read_recording
    from streamcal.inputs.track import Track

    out = tmp_path / "track.csv"
    assert main(["convert", str(log), "-o", str(out)]) == 0
    track, direct = Track.read(out), read_recording(log)
    assert len(track) == len(direct) and len(track.t_mag) == len(flight.t_mag)
    assert np.all(np.diff(track.t) >= 0) and track.t[0] == 0.0
    np.testing.assert_allclose(track.mag, direct.mag, atol=1e-6)   # the CSV's decimals
    assert track.mag_unit == "uT" and track.has("accel") and track.has("gyro")
    for key in ("input_format", "source", "mag_axes", "units", "time_origin", *keys):
        assert key in track.metadata, key
    return track


def check_detected_from_content_not_name(log, renamed, kind: str, input_format: str) -> None:
    """The log copied to ``renamed`` (another suffix) is still read as ``kind``."""
    import shutil

    from streamcal.inputs import detect, read_recording

    shutil.copy(log, renamed)
    assert detect(renamed) == kind
    assert read_recording(renamed).metadata["input_format"] == input_format


def check_truncated_log_read_to_last_message(whole, cut, fraction: float, tmp_path,
                                             capsys) -> None:
    """``whole`` cut at ``fraction`` of its bytes (a crash, a power cut): ``convert`` exits 0
    without --skip-bad-rows with one stderr line naming the file and what was lost, and keeps
    the complete messages."""
    from streamcal.cli import main
    from streamcal.inputs import read_recording
    from streamcal.inputs.track import Track

    data = whole.read_bytes()
    cut.write_bytes(data[: int(len(data) * fraction)])
    out = tmp_path / "out.csv"
    assert main(["convert", str(cut), "-o", str(out)]) == 0
    err = capsys.readouterr().err
    assert str(cut) in err and "truncated" in err and len(err.strip().splitlines()) == 1
    track = Track.read(out)
    assert "truncated" in track.metadata["read_warnings"]
    n_whole = len(read_recording(whole).t_mag)
    assert 0.3 * n_whole < len(track.t_mag) < n_whole


def check_log_without_magnetometer_named(path, match: str, capsys) -> None:
    """A log with no magnetometer: reading it raises InputError matching ``match``; ``fit``
    exits 2 naming the file."""
    from streamcal.cli import main
    from streamcal.errors import InputError
    from streamcal.inputs import read_recording

    with pytest.raises(InputError, match=match):
        read_recording(path)
    assert main(["fit", str(path)]) == 2
    assert str(path) in capsys.readouterr().err


# --- the fit's path ---------------------------------------------------------------------------

def refine_iterations(monkeypatch) -> list[int]:
    """Counts the LM iterations of each ``autocal.refine`` call from now on: the list it returns
    gets one entry per call (clear it between fits)."""
    from streamcal.fitting import autocal

    iterations: list[int] = []
    original = autocal.refine

    def counted(*args, **kwargs):
        result = original(*args, **kwargs)
        iterations.append(result.iterations)
        return result

    monkeypatch.setattr(autocal, "refine", counted)
    return iterations


def check_px4_calibration_in_force(path, tmp_path, capsys):
    """``--cal log`` on a PX4 ULog: the Calibration built from the CAL_MAG0_* in force maps the
    track's (undone) readings onto the norms of PX4's own correction (export.px4.apply_px4), at
    the strength of the field PX4 logged; diagnose runs against it and names its source; a
    converted track carries the same calibration in its param.* metadata.
    Returns the calibration and the CAL_MAG0_* parameters."""
    from streamcal.cli import main
    from streamcal.export.px4 import apply_px4
    from streamcal.inputs import autopilot_calibration, read_recording

    track = read_recording(path)
    cal = autopilot_calibration(track)
    params = {k[len("param."):]: float(v) for k, v in track.metadata.items()
              if k.startswith("param.CAL_MAG0_")}
    px4 = apply_px4({"CAL_MAG0_XODIAG": 0.0, "CAL_MAG0_YODIAG": 0.0, "CAL_MAG0_ZODIAG": 0.0,
                     **params}, track.mag / 100.0) * 100.0
    np.testing.assert_allclose(np.linalg.norm(cal.apply_field(track.mag), axis=1),
                               np.linalg.norm(px4, axis=1), rtol=1e-9)
    assert cal.field == pytest.approx(np.median(np.linalg.norm(px4, axis=1)), rel=1e-3)
    assert main(["diagnose", str(path), "--cal", "log"]) == 0
    assert "CAL_MAG0_* parameters" in capsys.readouterr().out
    converted = tmp_path / "flight.csv"
    assert main(["convert", str(path), "-o", str(converted)]) == 0
    again = autopilot_calibration(read_recording(converted))     # from the param.* metadata
    np.testing.assert_array_equal(again.K, cal.K)
    np.testing.assert_array_equal(again.b, cal.b)
    return cal, params

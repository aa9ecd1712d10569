"""Errors that say what and where: a column mapping names the file, the line and the mapping
in plain numbers; a file column mapped twice is a mapping error; a calibration file lacking a
key says "missing key"; export's "cannot express" gives names, values and units; a unit a
track does not name in words streamcal knows is said once as unknown and never echoed."""
from __future__ import annotations

import json

import pytest

from streamcal.calibration import REQUIRED_KEYS, Calibration
from streamcal.cli import main
from streamcal.errors import CalibrationFileError
from streamcal.export import export

#: A CSV of another tool: T falls, so mapping it to t puts time backwards at file line 3.
OTHER = "time,Bx,By,Bz,T\n0,30,1,2,10\n1,31,2,3,9\n2,29,3,1,8\n"


def _one_error(capsys, argv) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"streamcal {argv[0]}: error: "), err
    return err[0]


def test_a_mapped_column_out_of_order_names_file_line_and_mapping_in_plain_numbers(tmp_path,
                                                                                    capsys):
    path = tmp_path / "other.csv"
    path.write_text(OTHER)
    line = _one_error(capsys, ["fit", str(path), "--columns", "mx=Bx,my=By,mz=Bz,t=T"])
    assert f"{path}:3 column 't'" in line
    assert "time goes backwards: t=9.0 after t=10.0 (--columns t=T)" in line
    assert "np." not in line


@pytest.mark.parametrize("mapping, said", [
    ("mx=Bx,my=Bx,mz=Bz", "the file's column 'Bx' is mapped twice (mx=Bx, my=Bx)"),
    ("mx=Bx,my=By,mz=Bz,t=By", "the file's column 'By' is mapped twice (my=By, t=By)"),
    ("mx=Bx,my=By,mz=Bz,mx=T", "mx is mapped twice (mx=Bx, mx=T)"),
])
def test_a_column_mapped_twice_is_a_mapping_error_naming_the_file(tmp_path, capsys, mapping,
                                                                  said):
    path = tmp_path / "other.csv"
    path.write_text(OTHER)
    line = _one_error(capsys, ["fit", str(path), "--columns", mapping])
    assert f"{path}: --columns: {said}" in line


@pytest.mark.parametrize("key", REQUIRED_KEYS)
def test_a_calibration_file_without_a_key_says_missing_key(key):
    data = Calibration(K=[[45.0, 0, 0], [0, 46.0, 0], [0, 0, 47.0]], b=[1.0, 2.0, 3.0],
                       n=100).to_dict()
    del data[key]
    with pytest.raises(CalibrationFileError) as info:
        Calibration.from_json(json.dumps(data), "cal.json")
    assert str(info.value).startswith(f"cal.json: missing key '{key}'")


@pytest.mark.parametrize("fmt", ["ardupilot", "px4", "c-header"])
def test_export_cannot_express_gives_names_values_and_units(fmt):
    from streamcal.export.common import ascii_text

    cal = Calibration(K=[[45.0, 0, 0], [0, 46.0, 0], [0, 0, 47.0]], b=[1.0, 2.0, 3.0], n=100,
                      model=("hard_iron", "soft_iron", "temperature_offset"),
                      effects={"temperature_offset": {"T0": 33.975, "c": [0.1, -0.2, 0.3]}},
                      field=48.0)
    text, notes = export(cal, fmt)
    assert notes == ["temperature_offset: T0 33.98 °C, c [0.1, -0.2, 0.3] µT/°C"]
    in_file = notes[0] if fmt == "c-header" else ascii_text(notes[0])   # parameter files: ASCII
    assert "{" not in notes[0] and in_file in text


def _track_in(tmp_path, declared: str):
    from streamcal.sim import simulate

    track = simulate(duration_s=40, seed=5).track
    track.metadata["mag_unit"] = declared
    path = tmp_path / "t.csv"
    track.write(path)
    return path


@pytest.mark.parametrize("declared", ["probably uT", "unknown (normalized?)"])
def test_an_unknown_unit_is_said_once_and_never_echoed(tmp_path, capsys, declared):
    from streamcal.inputs.track import Track

    path = _track_in(tmp_path, declared)
    track = Track.read(path)
    assert track.mag_unit == "unknown" and track.metadata["mag_unit"] == declared
    assert main(["fit", str(path)]) == 0
    out = capsys.readouterr().out
    assert out.count("unit unknown") == 1 and "probably" not in out
    assert "[unknown]" not in out and "K [" not in out and " µT" not in out
    assert main(["replay", str(path)]) in (0, 1)
    out = capsys.readouterr().out
    assert out.count("unit unknown") <= 1 and "probably" not in out and " unknown," not in out
    assert " ," not in out


def test_a_known_unit_is_still_written_after_every_number(tmp_path, capsys):
    path = _track_in(tmp_path, "uT (gauss x 100)")
    assert main(["fit", str(path)]) == 0
    out = capsys.readouterr().out
    assert "K [µT]" in out and "unit unknown" not in out and "µT on the sensor residual" in out


@pytest.mark.slow
def test_the_report_of_an_unknown_unit_says_so_and_leaves_no_empty_unit(tmp_path):
    from streamcal.inputs.track import Track
    from streamcal.report import diagnose_or_reason, render_html

    track = Track.read(_track_in(tmp_path, "probably uT"))
    diagnosis, reason = diagnose_or_reason(track, ("hard_iron", "soft_iron"))
    assert diagnosis is not None, reason
    page = render_html(track, diagnosis)
    assert "unit unknown" in page and "probably" not in page
    text = page.split("<script>", 1)[0]
    assert "()" not in text and " </b>" not in text and "unit unit" not in text

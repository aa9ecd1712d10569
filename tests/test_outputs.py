"""One rule for every command that writes (docs/cli.md, "Output files"): missing parent
directories are created, a directory or an unwritable place is one line naming it with exit 2,
``-o -`` and ``/dev/stdout`` write to stdout, a pipe closed early ends quietly. Every case runs
the real command in a subprocess on a short simulated track, so a fresh clone tests it."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from streamcal.atomic import atomic_write_text, is_stdout, output_dir, prepare_output

ROOT = Path(__file__).resolve().parents[1]
#: A place no process can create anything in (not even root).
UNWRITABLE = Path("/proc/nope")

#: command → (argv with OUT for the output and TRACK/CAL for the inputs, what OUT is, what the
#: text written to stdout by ``-o -`` starts with, or None when the output is a directory).
WRITERS = {
    "fit": (["fit", "TRACK", "-o", "OUT"], "file", '{\n  "format": "streamcal-calibration/1"'),
    "convert": (["convert", "TRACK", "-o", "OUT"], "file", "# streamcal-track: 1"),
    "apply": (["apply", "CAL", "TRACK", "-o", "OUT"], "file", "# streamcal-applied: 1"),
    "export": (["export", "CAL", "--format", "ardupilot", "-o", "OUT"], "file", "# "),
    "batch": (["batch", "fit", "TRACK", "--jobs", "1", "-o", "OUT"], "file", "path,"),
    "report": (["report", "TRACK", "-o", "OUT"], "file", "<!DOCTYPE html>"),
    "record": (["record", "--bus", "fake:TRACK", "-o", "OUT"], "file", "# streamcal-track: 1"),
    "demo -o": (["demo", "--track", "TRACK", "--quiet", "-o", "OUT"], "file", "<!DOCTYPE html>"),
    "demo --out-dir": (["demo", "--track", "TRACK", "--quiet", "--out-dir", "OUT"], "dir", None),
    "diagnose --plots": (["diagnose", "TRACK", "--plots", "OUT"], "dir", None),
    "replay --state-dir": (["replay", "TRACK", "--state-dir", "OUT"], "dir", None),
    "daemon --state-dir": (["daemon", "--bus", "fake:TRACK", "--no-socket", "--state-dir", "OUT"],
                           "dir", None),
    "serial --state-dir": (["serial", "--port", "fake:TRACK", "--no-socket", "--state-dir", "OUT"],
                           "dir", None),
}


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """A 12 s simulated track (every command runs in seconds on it) and a calibration of it."""
    from streamcal.fitting import fit
    from streamcal.sim import simulate

    here = tmp_path_factory.mktemp("inputs")
    track = simulate(duration_s=12, seed=3).track
    track.write(here / "track.csv")
    fit(track, check_coverage=False).save(here / "cal.json")
    return {"TRACK": str(here / "track.csv"), "CAL": str(here / "cal.json")}


def run(name, inputs, out, stdout=subprocess.PIPE):
    argv = [a.replace("TRACK", inputs["TRACK"]).replace("CAL", inputs["CAL"]) if a != "OUT"
            else str(out) for a in WRITERS[name][0]]
    return subprocess.run([sys.executable, "-m", "streamcal", *argv], cwd=ROOT, stdout=stdout,
                          stderr=subprocess.PIPE, timeout=240)


def one_error_line(proc, where) -> str:
    """The stderr of a refused output: exit 2, no traceback, one error line naming ``where``."""
    err = proc.stderr.decode()
    assert proc.returncode == 2, err
    assert "Traceback" not in err
    errors = [line for line in err.splitlines() if ": error: " in line]
    assert len(errors) == 1 and str(where) in errors[0], err
    return errors[0]


@pytest.mark.slow
@pytest.mark.parametrize("name", WRITERS)
def test_missing_parent_directories_are_created(name, inputs, tmp_path):
    out = tmp_path / "a" / "b" / ("out" if WRITERS[name][1] == "dir" else "out.txt")
    proc = run(name, inputs, out)
    assert proc.returncode in (0, 1), proc.stderr.decode()   # 1: the data refused, yet written
    assert "Traceback" not in proc.stderr.decode()
    if WRITERS[name][1] == "dir":
        assert out.is_dir() and any(out.iterdir())
    else:
        assert out.is_file() and out.stat().st_size > 0


@pytest.mark.parametrize("name", WRITERS)
def test_a_directory_where_a_file_goes_or_a_file_where_a_directory_goes_is_one_line(
        name, inputs, tmp_path):
    if WRITERS[name][1] == "dir":
        out = tmp_path / "a-file"
        out.write_text("keep me\n")
    else:
        out = tmp_path
    line = one_error_line(run(name, inputs, out), out)
    assert "directory" in line
    if out.is_file():
        assert out.read_text() == "keep me\n"


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux /proc")
@pytest.mark.parametrize("name", WRITERS)
def test_an_unwritable_place_is_one_line(name, inputs):
    out = UNWRITABLE / ("out" if WRITERS[name][1] == "dir" else "out.txt")
    one_error_line(run(name, inputs, out), out)


@pytest.mark.slow
@pytest.mark.parametrize("name", [n for n, w in WRITERS.items() if w[1] == "file"])
def test_dash_writes_the_output_alone_to_stdout(name, inputs, tmp_path):
    proc = run(name, inputs, "-")
    assert proc.returncode in (0, 1), proc.stderr.decode()
    text = proc.stdout.decode()
    assert text.startswith(WRITERS[name][2]), text[:200]
    assert not Path(ROOT, "-").exists()
    if name == "fit":                       # nothing but the file: the messages went to stderr
        assert json.loads(text)["format"] == "streamcal-calibration/1"
        assert "written: -" in proc.stderr.decode()


@pytest.mark.parametrize("name", ["convert", "fit"])
def test_dev_stdout_into_a_file_and_a_pipe(name, inputs, tmp_path):
    """``/dev/stdout`` is a symbolic link (to a file or a pipe): written in place, not
    replaced, and the messages go to stderr so they cannot interleave with the output."""
    target = tmp_path / "redirected"
    with open(target, "wb") as handle:
        proc = run(name, inputs, "/dev/stdout", stdout=handle)
    assert proc.returncode == 0, proc.stderr.decode()
    assert target.read_text().startswith(WRITERS[name][2])
    piped = run(name, inputs, "/dev/stdout")
    assert piped.returncode == 0
    if name == "fit":                         # the file names the time it was made
        assert json.loads(piped.stdout)["K"] == json.loads(target.read_text())["K"]
    else:
        assert piped.stdout.decode() == target.read_text()


@pytest.mark.parametrize("name", WRITERS)
def test_a_pipe_closed_early_ends_quietly(name, inputs, tmp_path):
    """``streamcal … | head -1`` with the reader already gone: no BrokenPipeError traceback."""
    read_end, write_end = os.pipe()
    os.close(read_end)
    out = "-" if WRITERS[name][1] == "file" else tmp_path / "out"
    try:
        proc = run(name, inputs, out, stdout=write_end)
    finally:
        os.close(write_end)
    err = proc.stderr.decode()
    assert "Traceback" not in err and "BrokenPipe" not in err and "Exception ignored" not in err
    if out == "-":        # the output itself went into the closed pipe
        assert proc.returncode == 141, err
    else:
        assert proc.returncode in (0, 1, 141), err


def test_the_rule_in_the_library(tmp_path, capsysbinary):
    """streamcal.atomic: parents made, a directory refused, ``-`` is stdout, a FIFO is written
    in place."""
    atomic_write_text(tmp_path / "x" / "y" / "f.txt", "a")
    assert (tmp_path / "x" / "y" / "f.txt").read_text() == "a"
    with pytest.raises(IsADirectoryError) as info:
        prepare_output(tmp_path / "x")
    assert info.value.filename == str(tmp_path / "x")
    with pytest.raises(NotADirectoryError):
        output_dir(tmp_path / "x" / "y" / "f.txt")
    atomic_write_text("-", "to stdout")
    assert capsysbinary.readouterr().out == b"to stdout"
    assert is_stdout("-") and not is_stdout(tmp_path / "x")
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    reader = os.open(fifo, os.O_RDONLY | os.O_NONBLOCK)
    try:
        atomic_write_text(fifo, "through")
        assert os.read(reader, 100) == b"through"
    finally:
        os.close(reader)
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


@pytest.mark.slow
def test_report_prints_where_it_wrote_and_the_local_field_only_when_given(inputs, tmp_path):
    """No stray "reference none…" line: without a place the page says why, stdout only where
    the report went; with --lat/--lon the comparison is printed too."""
    out = tmp_path / "r.html"
    proc = run("report", inputs, out)
    assert proc.returncode == 0, proc.stderr.decode()
    assert proc.stdout.decode().splitlines() == [f"report written to {out}"]
    assert "no location given" in out.read_text()
    argv = [sys.executable, "-m", "streamcal", "report", inputs["TRACK"], "-o", str(out),
            "--lat", "52.2", "--lon", "0.1", "--date", "2025-06-01"]
    placed = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=240)
    lines = placed.stdout.splitlines()
    assert lines[0].startswith("reference  WMM") and lines[-1] == f"report written to {out}"

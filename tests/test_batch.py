"""``streamcal.batch`` and ``streamcal batch``: one row per file in input order, a bad file is a
row with its error, any executor (process pool, Dask distributed) gives the serial rows."""
from __future__ import annotations

import concurrent.futures as cf
import csv
import os
import subprocess
import sys
from pathlib import Path

import pytest

import streamcal
from streamcal.batching import COLUMNS, diagnose_task, fit_task, run_one

REPO = Path(__file__).resolve().parents[1]
TRACKS = ("risher_raw_data.csv", "jr_mpu9250_accmag.csv", "tiva_mpu9250_mag_03.csv")


@pytest.fixture()
def paths(real_tracks_dir, tmp_path):
    broken = tmp_path / "broken.csv"
    broken.write_text("t,mx,my,mz\n0.0,1.0,2.0,3.0\n0.01,1.0,oops,3.0\n")
    good = [str(real_tracks_dir / name) for name in TRACKS]
    return good[:2] + [str(broken)] + good[2:]


def _same(row, ref):
    """Every column but the wall time equal (the fit is deterministic)."""
    assert {k: v for k, v in row.items() if k != "seconds"} == \
           {k: v for k, v in ref.items() if k != "seconds"}
    assert row["seconds"] >= 0


def _check_rows(rows, paths, task):
    serial = [run_one(task, p) for p in paths]
    assert [r["path"] for r in rows] == paths
    for row, ref in zip(rows, serial):
        _same(row, ref)
    broken = rows[2]
    assert broken["status"] == "error" and broken["n"] is None
    assert broken["error"].startswith("TrackError: ") and "broken.csv" in broken["error"]
    for row in rows[:2] + rows[3:]:
        assert row["status"] == "ok" and row["error"] is None
        assert row["n"] > 0 and row["rms"] > 0 and row["residual"] == "sensor"


def test_batch_with_a_thread_pool_matches_a_serial_run(paths):
    progress = []
    with cf.ThreadPoolExecutor(2) as pool:
        rows = streamcal.batch(paths, "fit", executor=pool, progress=progress.append)
    assert sorted(r["path"] for r in progress) == sorted(paths)
    _check_rows(rows, paths, fit_task)


def test_batch_diagnose_rows_name_a_verdict_and_a_residual(paths):
    rows = streamcal.batch(paths[:3], "diagnose", jobs=2)
    for row, ref in zip(rows, [run_one(diagnose_task, p) for p in paths[:3]]):
        _same(row, ref)
    for row in rows[:2]:
        assert row["verdict"] in ("at_noise_floor", "effect_missing", "unexplained")
        assert row["residual"] in ("sensor", "gravity_tied", "gyro_tied")
    assert rows[2]["status"] == "error"


def test_unknown_task_is_an_input_error(paths):
    with pytest.raises(streamcal.InputError, match="unknown batch task"):
        streamcal.batch(paths, "fly")


@pytest.mark.slow
def test_dask_distributed_executor_matches_a_serial_run(paths, monkeypatch):
    distributed = pytest.importorskip("distributed")
    # the worker processes must import this checkout, not another installed streamcal
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(
        [str(REPO)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]))
    with distributed.LocalCluster(n_workers=2, processes=True, threads_per_worker=1,
                                  dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:
        rows = streamcal.batch(paths, "fit", executor=client.get_executor())
        where = client.run(lambda: __import__("streamcal").__file__)
    assert all(Path(f).resolve().is_relative_to(REPO) for f in where.values())
    _check_rows(rows, paths, fit_task)


def test_cli_batch_with_jobs_writes_one_row_per_file(paths, tmp_path):
    out = tmp_path / "summary.csv"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.run([sys.executable, "-m", "streamcal", "batch", "fit", *paths,
                           "--jobs", "2", "-o", str(out)],
                          capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 1, proc.stderr          # one file failed
    assert "3 of 4 files ok" in proc.stdout
    assert "broken.csv: TrackError:" in proc.stderr
    assert "4/4" in proc.stderr                        # the progress bar reached the end
    with open(out, newline="") as handle:
        table = list(csv.DictReader(handle))
    assert tuple(table[0]) == COLUMNS
    assert [r["path"] for r in table] == paths
    assert [r["status"] for r in table] == ["ok", "ok", "error", "ok"]
    for r, ref in zip(table, [run_one(fit_task, p) for p in paths]):
        if ref["status"] == "ok":
            assert int(r["n"]) == ref["n"] and float(r["rms"]) == pytest.approx(ref["rms"], rel=1e-5)
            assert r["residual"] == "sensor"
    assert not [p for p in os.listdir(tmp_path) if p.endswith(".tmp")]


def test_cli_batch_rejects_zero_jobs(paths, tmp_path):
    from streamcal.cli import main

    assert main(["batch", "fit", *paths, "--jobs", "0", "-o", str(tmp_path / "s.csv")]) == 2

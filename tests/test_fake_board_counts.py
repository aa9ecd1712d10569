"""``--port fake:`` on a raw-counts AK8963 log serves its counts as the sketch reads the chip
(body axes, the log's ASA), so the host's µT are counts × 4912/32760 µT; counts without
MPU-9250/AK8963 metadata are refused (exit 2) as ``--bus fake:`` refuses them."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

from firmware_bridge import registers as R
from streamcal.inputs.track import Track

from .conftest import REAL_TRACKS, real_path

REPO = Path(__file__).resolve().parent.parent
TIVA_03 = REAL_TRACKS / "tiva_mpu9250_mag_03.csv"


def record(*args):
    return subprocess.run([sys.executable, "-m", "streamcal", "record", *map(str, args)],
                          capture_output=True, text=True, timeout=120, cwd=REPO)


def test_record_from_fake_board_on_a_counts_log_writes_the_field_in_uT(tmp_path):
    real_path(TIVA_03)
    src = Track.read(TIVA_03)
    assert src.mag_unit == "counts" and "chip" in src.metadata["mag_axes"]
    out = tmp_path / "x.csv"
    proc = record("--port", f"fake:{TIVA_03}", "-o", out)
    assert proc.returncode == 0, proc.stderr
    got = Track.read(out)
    assert got.mag_unit == "uT" and len(got) == len(src)
    # chip axes → body axes (x_b = y_c, y_b = x_c, z_b = −z_c), 0.15 µT per count (ASA 128)
    expect = src.mag @ R.AK_TO_BODY.T * (4912.0 / 32760.0)
    np.testing.assert_allclose(got.mag, expect, rtol=1e-6, atol=1e-5)
    radius = np.median(np.linalg.norm(got.mag - got.mag.mean(axis=0), axis=1))
    assert 10.0 < radius < 100.0            # an Earth-size field in µT, not counts read as µT


def test_record_from_fake_board_refuses_foreign_counts(tmp_path):
    src = tmp_path / "foreign.csv"
    src.write_text("# streamcal-track: 1\n# mag_unit: counts\nt,mx,my,mz\n"
                   + "".join(f"{0.01 * i:.2f},{i},{2 * i},{3 * i}\n" for i in range(20)))
    out = tmp_path / "y.csv"
    proc = record("--port", f"fake:{src}", "-o", out)
    assert proc.returncode == 2
    assert str(src) in proc.stderr and "MPU-9250/AK8963" in proc.stderr
    assert not out.exists()

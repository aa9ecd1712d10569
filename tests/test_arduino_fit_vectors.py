"""The board's sphere fit (sc_selfcal.h ``sc_sphere_fit``, compiled with g++ on the host and driven
through ``sc_vectors fit``) against the host's one-pass fit (``SphereStats`` in
``streamcal.fitting.sphere_stream``) on the same magnetometer windows."""
from __future__ import annotations

import os
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest

from firmware_bridge import frames as fr
from firmware_bridge.fake_board import sphere_sums_add
from streamcal.fitting.sphere_stream import SphereStats
from streamcal.inputs.track import Track

REPO = Path(__file__).resolve().parent.parent
DEMO = REPO / "streamcal" / "data" / "demo_track.csv.gz"
UT_PER_LSB = 4912.0 / 32760.0
ASA = (0xB0, 0xB2, 0xA5)        # the simavr tests' fuse ROM; body x, y, z use ASA y, x, z
AGREE = 0.005                   # issue #15: the board's fit within 0.5 % of the host's

pytestmark = pytest.mark.toolchain


def _f32(x: float) -> float:
    return struct.unpack("<f", struct.pack("<f", x))[0]


def _bits(x: float) -> int:
    return struct.unpack("<I", struct.pack("<f", x))[0]


def _float(bits: str) -> float:
    return struct.unpack("<f", struct.pack("<I", int(bits)))[0]


SCALE = tuple(_f32(UT_PER_LSB * (a + 128) / 256.0) for a in (ASA[1], ASA[0], ASA[2]))


@pytest.fixture(scope="module")
def fit_exe(tmp_path_factory):
    gxx = shutil.which("g++")
    if gxx is None:
        if os.environ.get("CI"):
            pytest.fail("g++ not found")
        pytest.skip("g++ not found")
    exe = tmp_path_factory.mktemp("fit") / "sc_vectors"
    subprocess.run([gxx, "-std=c++11", "-Wall", "-Wextra", "-Werror", "-O1", "-ffp-contract=off", "-o",
                    str(exe), str(REPO / "arduino" / "test_vectors" / "sc_vectors.cpp")], check=True, timeout=120)
    return exe


def _board_fit(exe, counts: np.ndarray):
    """(centre µT (3,), R µT) from the board's fit of these (n,3) int counts, or None (FAIL)."""
    sums = sphere_sums_add(fr.SphereSums(), counts)
    line = "fit " + " ".join(str(v) for v in [*map(_bits, SCALE), *sums.values()])
    out = subprocess.run([str(exe)], input=line + "\n", capture_output=True, text=True, timeout=60,
                         check=True).stdout.split()
    if out[0] != "OK":
        return None
    b = np.array([_float(v) for v in out[1:4]])
    return b, _float(out[4]), int(out[6])


def _host_fit(counts: np.ndarray):
    stats = SphereStats()
    stats.update(counts * np.array(SCALE))
    return stats.fit()


def _demo_counts() -> np.ndarray:
    track = Track.read(DEMO)
    m = np.column_stack([track.columns[n] for n in ("mx", "my", "mz")])
    m = m[np.all(np.isfinite(m), axis=1)]
    return np.round(m / np.array(SCALE)).astype(np.int64)


def _sphere_counts(rng, n, centre, radius, noise, cap_z=-1.0) -> np.ndarray:
    """n points on a sphere (µT) with directions of z >= cap_z, Gaussian noise, as counts."""
    u = rng.normal(size=(4 * n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    u = u[u[:, 2] >= cap_z][:n]
    m = np.asarray(centre) + radius * u + rng.normal(scale=noise, size=u.shape)
    return np.round(m / np.array(SCALE)).astype(np.int64)


def _windows():
    demo = _demo_counts()
    rng = np.random.default_rng(15)
    yield "demo 0-30 s", demo[:3000]
    yield "demo 60-120 s", demo[6000:12000]
    yield "demo whole", demo
    yield "offset sphere", _sphere_counts(rng, 4000, (60.0, -35.0, 110.0), 48.0, 0.6)
    yield "upper half only", _sphere_counts(rng, 3000, (-20.0, 15.0, -40.0), 52.0, 0.4, cap_z=0.0)
    yield "strong field, few samples", _sphere_counts(rng, 200, (5.0, 5.0, 5.0), 90.0, 1.0)


@pytest.mark.parametrize("name, counts", list(_windows()), ids=[w[0] for w in _windows()])
def test_board_fit_agrees_with_sphere_stream(fit_exe, name, counts):
    board = _board_fit(fit_exe, counts)
    assert board is not None, f"{name}: the board's fit failed"
    b, R, iters = board
    c_host, R_host = _host_fit(counts)
    err = max(np.max(np.abs(b - c_host)), abs(R - R_host)) / R_host
    print(f"{name}: n={len(counts)} board vs host sphere_stream: max(|db|, |dR|)/R = {100 * err:.5f} %, "
          f"{iters} iterations")
    assert err <= AGREE


def test_board_fit_refuses_a_plane(fit_exe):
    rng = np.random.default_rng(3)
    a = rng.uniform(0, 2 * np.pi, 500)
    counts = np.round(np.column_stack([300 * np.cos(a), 300 * np.sin(a), np.zeros_like(a)])).astype(np.int64)
    assert _board_fit(fit_exe, counts) is None

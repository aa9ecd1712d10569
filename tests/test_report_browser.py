"""The HTML report in a real browser (headless Chromium): it renders, is not blank, and every
inline image decodes (the page's own script sets ``data-images="loaded"`` on <body>)."""
import io
import os
import re
import shutil
import subprocess

import numpy as np
import pytest
from matplotlib.image import imread

from streamcal.diagnosis import diagnose
from streamcal.report import write_report
from streamcal.sim import simulate

CHROMIUM = "/usr/bin/chromium"
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def _chromium() -> str:
    path = CHROMIUM if os.access(CHROMIUM, os.X_OK) else shutil.which("chromium")
    if path:
        return path
    if os.environ.get("CI"):
        pytest.fail("chromium is missing: CI must install Debian's chromium package")
    pytest.skip("chromium not installed (apt-get install -y chromium)")


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    track = simulate(30.0, 4, effects={"temperature_offset": 0.6}, outlier_bursts=1).track
    d = diagnose(track, candidates=["temperature_offset", "time_drift"])
    return write_report(tmp_path_factory.mktemp("report") / "report.html", track, d)


def _run(args, tmp_path):
    cmd = [_chromium(), *FLAGS, f"--user-data-dir={tmp_path / 'profile'}", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120, stdin=subprocess.DEVNULL)


@pytest.mark.slow
def test_every_image_loads_in_chromium(report, tmp_path):
    done = _run(["--virtual-time-budget=10000", "--dump-dom", report.as_uri()], tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    body = re.search(r"<body[^>]*>", done.stdout)
    assert body, done.stdout[:500]
    n_images = len(re.findall(r"<img\s", report.read_text()))
    assert 'data-images="loaded"' in body.group(0), body.group(0)
    assert f'data-image-count="{n_images}"' in body.group(0)


def test_screenshot_is_not_blank(report, tmp_path):
    shot = tmp_path / "shot.png"
    done = _run([f"--screenshot={shot}", "--window-size=1200,3000", "--hide-scrollbars",
                 report.as_uri()], tmp_path)
    assert shot.is_file(), done.stderr[-2000:]
    pixels = imread(io.BytesIO(shot.read_bytes()), format="png")[..., :3]
    assert pixels.shape[:2] == (3000, 1200)
    assert pixels.std() > 0.05
    # figures fill the page: most 100-row bands below the header carry ink
    bands = [pixels[y:y + 100].std() > 0.02 for y in range(200, 3000, 100)]
    assert np.mean(bands) > 0.8

"""The live page in a real browser (headless Chromium) against ``streamcal daemon --bus fake:… --http``:
the page's script renders the coverage figure into ``<span id="coverage">`` (the served HTML
holds only "–" there), and two loads a few seconds apart show it grow; a screenshot is kept."""
import io
import re
import subprocess
import time

import pytest
from matplotlib.image import imread

from tests.test_live_page import start_daemon
from tests.test_report_browser import FLAGS, _chromium


def _run(args, tmp_path, name):
    cmd = [_chromium(), *FLAGS, f"--user-data-dir={tmp_path / ('profile-' + name)}", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120,
                          stdin=subprocess.DEVNULL)


def _coverage(dom: str) -> float:
    found = re.search(r'<span id="coverage" data-value="([0-9.]+)">([0-9.]+)%</span>', dom)
    assert found, dom[:3000]
    value = float(found.group(1))
    assert abs(100 * value - float(found.group(2))) < 0.06      # the shown text is the value
    return value


def test_coverage_grows_in_chromium(tmp_path):
    chromium = _chromium()
    assert chromium
    proc, url = start_daemon(tmp_path, speed="2", seconds="90")
    try:
        time.sleep(1.0)
        first = _run(["--dump-dom", url], tmp_path, "a")
        assert first.returncode == 0, first.stderr[-2000:]
        time.sleep(4.0)
        second = _run(["--dump-dom", url], tmp_path, "b")
        assert second.returncode == 0, second.stderr[-2000:]
        shot = tmp_path / "live_page.png"
        _run([f"--screenshot={shot}", "--window-size=1100,900", "--hide-scrollbars", url],
             tmp_path, "c")
        assert proc.poll() is None
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    c1, c2 = _coverage(first.stdout), _coverage(second.stdout)
    assert 0 <= c1 < c2 <= 1, (c1, c2)
    assert "no calibration yet" in first.stdout or 'id="cal"' in first.stdout
    assert shot.is_file()
    pixels = imread(io.BytesIO(shot.read_bytes()), format="png")[..., :3]
    assert pixels.shape[:2] == (900, 1100)
    # the sphere discs are drawn: some of the "seen" green (34, 170, 119) is on the page
    green = (abs(pixels[..., 0] - 34 / 255) < 0.02) & (abs(pixels[..., 1] - 170 / 255) < 0.02)
    assert green.sum() > 500, green.sum()

"""The live page in a real browser (Debian's headless Chromium driven by Python ``playwright``,
whose wheel carries only its driver: no browser download) against ``streamcal daemon --bus
fake:… --http``. One page session: ``#coverage`` is read once the page has rendered, then
again a few seconds later in the same page, so the growth seen is the Server-Sent Events
updating the DOM (the served HTML holds only the snapshot of the moment it was loaded). A
screenshot is kept under tmp_path."""
import io
import os
import time

import pytest
from matplotlib.image import imread

from tests.test_live_page import start_daemon
from tests.test_report_browser import _chromium

ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--disable-component-update", "--disable-sync", "--no-first-run"]


def _coverage(page) -> tuple[float, str, int]:
    """(data-value, shown text, SSE events received) of the page as it is now."""
    # one evaluate: two separate reads could straddle an update of the page (both fields are
    # set in the same handler, so one read sees them together)
    value, text, events = page.evaluate(
        "() => { const e = document.getElementById('coverage'); "
        "return [e.dataset.value, e.textContent, document.body.dataset.events || 0]; }")
    value = float(value)
    assert abs(100 * value - float(text.rstrip("%"))) < 0.06      # the shown text is the value
    return value, text, int(events)


@pytest.mark.slow
def test_live_stream_updates_the_dom_in_chromium(tmp_path):
    chromium = _chromium()
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        if os.environ.get("CI"):
            pytest.fail("playwright is missing: CI installs it with the test extra")
        pytest.skip("python playwright not installed (pip install playwright; no browser "
                    "download needed: Debian's chromium is used)")
    proc, url = start_daemon(tmp_path, speed="2", seconds="90")
    shot = tmp_path / "live_page.png"
    try:
        time.sleep(1.0)
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium, args=ARGS)
            try:
                page = browser.new_page(viewport={"width": 1100, "height": 900})
                page.goto(url, wait_until="load", timeout=30_000)
                page.wait_for_function("document.body.dataset.events >= 1", timeout=15_000)
                # "not measured" until the running sphere frames the directions
                page.wait_for_function("document.getElementById('coverage').dataset.value !== ''",
                                       timeout=15_000)
                c1, text1, n1 = _coverage(page)
                served = page.evaluate("JSON.parse(document.getElementById('initial')"
                                       ".textContent)")
                page.wait_for_timeout(3000)
                c2, text2, n2 = _coverage(page)
                page.screenshot(path=str(shot))
            finally:
                browser.close()
        assert proc.poll() is None
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    assert n2 - n1 >= 6, (n1, n2)                      # ~4 events a second arrived meanwhile
    assert 0 <= c1 < c2 <= 1, (c1, c2, text1, text2)   # and changed the same page's DOM
    assert served is None or served["coverage"] is None or served["coverage"] <= c1
    pixels = imread(io.BytesIO(shot.read_bytes()), format="png")[..., :3]
    assert pixels.shape[:2] == (900, 1100)
    # the sphere discs are drawn: some of the "seen" green (34, 170, 119) is on the page
    green = (abs(pixels[..., 0] - 34 / 255) < 0.02) & (abs(pixels[..., 1] - 170 / 255) < 0.02)
    assert green.sum() > 500, green.sum()

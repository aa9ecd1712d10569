"""The live page in a real browser (Debian's headless Chromium driven by Python ``playwright``,
whose wheel carries only its driver: no browser download) against ``streamcal daemon --bus
fake:… --http``. One page session: ``#coverage`` is read once the page has rendered, then
again a few seconds later in the same page, so the growth seen is the Server-Sent Events
updating the DOM (the served HTML holds only the snapshot of the moment it was loaded). A
screenshot is kept under tmp_path. Then the page's layout at 900 px and 1400 px, its 3-D sphere
and magnitude axis, over the bundled track fed in-process (screenshots kept likewise)."""
import io
import json
import os
import time

import numpy as np
import pytest
from matplotlib.image import imread

from tests.test_live_page import TRACK, start_daemon
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


def _playwright():
    """Debian's chromium and playwright's ``sync_playwright``; a skip (a failure in CI) when
    playwright is not installed."""
    chromium = _chromium()
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        if os.environ.get("CI"):
            pytest.fail("playwright is missing: CI installs it with the test extra")
        pytest.skip("python playwright not installed (pip install playwright; no browser "
                    "download needed: Debian's chromium is used)")
    return chromium, sync_playwright


@pytest.mark.slow
def test_live_stream_updates_the_dom_in_chromium(tmp_path):
    chromium, sync_playwright = _playwright()
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


class _Feed:
    """The bundled track fed in-process through a streaming calibrator into a live page, on a
    clock that is the track's time (captures every 0.25 s of track): what the page shows is
    fixed by the data, not by how fast this machine runs."""

    def __init__(self):
        from streamcal.inputs.track import Track
        from streamcal.service.http_page import LivePage
        from streamcal.service.live_state import LiveState
        from streamcal.service.replay_feed import ReplayFeed
        from streamcal.stream import StreamingCalibrator

        track = Track.read(TRACK)
        self.now = 0.0
        self.state = LiveState(clock=lambda: self.now)
        self.calibrator = StreamingCalibrator(synchronous=True, unit=track.mag_unit)
        self.feed = ReplayFeed(self.calibrator, [self.state])
        self.blocks = iter(track.blocks(50))
        self.page = LivePage(self.state).start()

    def until(self, t_end: float) -> None:
        for block in self.blocks:
            self.now = float(block.t[-1])
            self.feed.observe(block, self.calibrator.ingest(block))
            if self.now >= t_end:
                return


def _canvas_colour_count(page, canvas_id: str, rgb, tol=40) -> int:
    """Pixels of the canvas within ``tol`` of ``rgb`` (read from the canvas itself)."""
    return page.evaluate("""([id, rgb, tol]) => {
        const c = document.getElementById(id), d = c.getContext('2d')
            .getImageData(0, 0, c.width, c.height).data;
        let n = 0;
        for (let i = 0; i < d.length; i += 4)
            if (Math.abs(d[i] - rgb[0]) <= tol && Math.abs(d[i + 1] - rgb[1]) <= tol
                && Math.abs(d[i + 2] - rgb[2]) <= tol && d[i + 3] > 200) n++;
        return n; }""", [canvas_id, list(rgb), tol])


LAYOUT = """() => {
    const W = innerWidth, out = {scroll: document.documentElement.scrollWidth, W, bad: []};
    for (const e of document.querySelectorAll('.legend, canvas, .box')) {
        const r = e.getBoundingClientRect();
        if (r.left < -0.5 || r.right > W + 0.5 || e.scrollWidth > e.clientWidth + 1)
            out.bad.push([e.id || e.className || e.tagName, r.left, r.right, e.scrollWidth,
                          e.clientWidth]);
    }
    const g = document.getElementById('globe').getBoundingClientRect();
    out.globe = [g.left + scrollX, g.top + scrollY, g.width, g.height];
    return out; }"""


@pytest.mark.slow
def test_page_layout_sphere_and_magnitude_at_900_and_1400_px(tmp_path):
    """The bundled track fed in-process: before its first calibration (21 s) the magnitude plot
    has no 'after calibration' trace and says 'none yet'; after the whole track the page at
    900 px and 1400 px has no horizontal overflow, its legends and canvases inside the viewport,
    a non-blank 3-D sphere with seen cells, a µT axis with at least four labels; a drag turns the
    sphere and a double-click turns it back. Screenshots are kept under tmp_path."""
    chromium, sync_playwright = _playwright()
    feed = _Feed()
    try:
        feed.until(15.0)
        assert feed.calibrator.calibration is None
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium, args=ARGS)
            try:
                page = browser.new_page(viewport={"width": 900, "height": 1000})
                page.goto(feed.page.url, wait_until="load", timeout=30_000)
                page.wait_for_function("document.body.dataset.events >= 1", timeout=15_000)
                legend = page.inner_text("#mag-legend")
                assert "after calibration: none yet" in legend and "µT" in legend, legend
                assert _canvas_colour_count(page, "mag", (0x00, 0x66, 0xcc), 30) == 0
                assert _canvas_colour_count(page, "mag", (0xcc, 0x66, 0x00), 30) > 20
                assert "no calibration yet" in page.inner_text("#cal")

                feed.until(float("inf"))
                assert feed.calibrator.calibration is not None
                last = feed.state.wait(0, timeout=0)         # the newest capture's number
                page.wait_for_function(f"document.body.dataset.seq == {last}", timeout=15_000)
                latest = json.loads(feed.page.latest)
                assert latest["seq"] == last
                assert "µT" in page.inner_text("#cal") and "uT" not in page.inner_text("body")
                assert _canvas_colour_count(page, "mag", (0x00, 0x66, 0xcc), 30) > 20
                ticks, unit = page.evaluate("() => { const c = document.getElementById('mag'); "
                                            "return [c.dataset.yticks, c.dataset.unit]; }")
                shown = latest["magnitude"]
                shots = {}
                for width in (900, 1400):
                    page.set_viewport_size({"width": width, "height": 1000})
                    page.wait_for_timeout(300)
                    layout = page.evaluate(LAYOUT)
                    assert layout["scroll"] <= layout["W"], layout
                    assert not layout["bad"], layout["bad"]
                    shots[width] = tmp_path / f"live_page_{width}.png"
                    page.screenshot(path=str(shots[width]), full_page=True)
                    _assert_globe_drawn(shots[width], layout["globe"])
                before = page.evaluate("globe.view")
                box = page.locator("#globe").bounding_box()
                cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
                page.mouse.move(cx, cy)
                page.mouse.down()
                page.mouse.move(cx + 60, cy + 25, steps=6)
                page.mouse.up()
                page.wait_for_timeout(100)
                turned = page.evaluate("globe.view")
                page.screenshot(path=str(tmp_path / "live_page_turned.png"), full_page=True)
                page.mouse.dblclick(cx, cy)
                page.wait_for_timeout(100)
                reset = page.evaluate("globe.view")
            finally:
                browser.close()
    finally:
        feed.page.close()
    before, turned, reset = (np.array(v) for v in (before, turned, reset))
    assert np.abs(turned - before).max() > 0.2                  # the drag turned the view
    assert np.allclose(turned @ turned.T, np.eye(3), atol=1e-9)  # still a rotation
    assert np.allclose(reset, before)
    # the magnitude axis: µT, at least four round labels spanning every plotted value
    assert unit == "µT"
    ticks = [float(v) for v in ticks.split()]
    steps = np.diff(ticks)
    assert len(ticks) >= 4 and np.allclose(steps, steps[0]), ticks
    mantissa = steps[0] / 10 ** np.floor(np.log10(steps[0]))
    assert any(abs(mantissa - m) < 1e-6 for m in (1, 2, 5)), ticks
    values = [v for v in shown["raw"] + shown["calibrated"] if v is not None]
    assert ticks[0] <= min(values) and max(values) <= ticks[-1], (ticks, min(values), max(values))


def _assert_globe_drawn(png, rect) -> None:
    """The 3-D sphere's canvas in the screenshot: mostly drawn (not the white box behind it)
    and holding seen (green) cells."""
    pixels = imread(io.BytesIO(png.read_bytes()), format="png")[..., :3]
    x, y, w, h = (int(round(v)) for v in rect)
    crop = pixels[y:y + h, x:x + w]
    assert crop.shape[0] > 100 and crop.shape[1] > 100, crop.shape
    drawn = (crop < 0.97).any(axis=2).mean()
    green = ((crop[..., 1] > crop[..., 0] + 0.25) & (crop[..., 1] > crop[..., 2] + 0.08)).sum()
    assert drawn > 0.4, drawn                     # the disc covers ~0.5 of its square canvas
    assert green > 2000, green

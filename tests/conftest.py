"""Where the real recordings are, and what happens without them.

The real recordings are not in the repository (their owners did not license them for
redistribution). Tests find them through one option, the environment variable ``STREAMCAL_SHARED``:
the folder that holds ``data/real/tracks`` and ``data/real/flight`` (unset: ``../shared`` beside
the checkout). Without them each real-data test skips (or fails when ``CI`` is set: CI has the
data) and the run ends with one line counting those skips; every behaviour they protect is also
covered on simulated or self-made data (docs/testing.md).
"""
import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
SHARED_ENV = "STREAMCAL_SHARED"
SHARED = Path(os.environ.get(SHARED_ENV) or REPO.parent / "shared")
REAL_DATA = SHARED / "data" / "real"
REAL_TRACKS = REAL_DATA / "tracks"
REAL_FLIGHTS = REAL_DATA / "flight"

#: How every skip for missing real data begins (the terminal summary counts these).
MISSING_REAL_DATA = "real recordings not found"
HOW_TO_RUN = (f"set {SHARED_ENV}=DIR, the folder holding data/real/tracks and data/real/flight "
              "(docs/testing.md)")


def real_path(path: Path) -> Path:
    """``path`` when it exists; else a failure in CI (which must have the data) or a skip."""
    if not path.exists():
        if os.environ.get("CI"):
            pytest.fail(f"{path} is missing: CI must have the real recordings ({HOW_TO_RUN})")
        pytest.skip(f"{MISSING_REAL_DATA}: {path} ({HOW_TO_RUN})")
    return path


def real_track(name: str) -> Path:
    """``data/real/tracks/<name>`` (see :func:`real_path`)."""
    return real_path(REAL_TRACKS / name)


def real_flight(name: str) -> Path:
    """``data/real/flight/<name>`` (see :func:`real_path`)."""
    return real_path(REAL_FLIGHTS / name)


@pytest.fixture(scope="session")
def real_tracks_dir() -> Path:
    return real_path(REAL_TRACKS)


@pytest.fixture(scope="session")
def flight_dir() -> Path:
    return real_path(REAL_FLIGHTS)


@pytest.fixture(scope="session")
def real_data_dir() -> Path:
    return real_path(REAL_DATA)


def _skipped_for_missing_data(report) -> bool:
    longrepr = report.longrepr
    message = longrepr[2] if isinstance(longrepr, tuple) and len(longrepr) == 3 else str(longrepr)
    return MISSING_REAL_DATA in message


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    """One line: how many tests skipped for missing real recordings, and how to run them."""
    n = sum(_skipped_for_missing_data(r) for r in terminalreporter.stats.get("skipped", ()))
    if n:
        tests = "test" if n == 1 else "tests"
        terminalreporter.write_line(
            f"{n} real-data {tests} skipped ({MISSING_REAL_DATA} under {SHARED}); "
            f"to run them {HOW_TO_RUN}; each behaviour is also tested on simulated data")

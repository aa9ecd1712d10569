import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
SHARED = Path(os.environ.get("STREAMCAL_SHARED", REPO.parent / "shared"))
REAL_TRACKS = SHARED / "data" / "real" / "tracks"
REAL_FLIGHTS = SHARED / "data" / "real" / "flight"


def _shared_dir(path: Path, what: str) -> Path:
    """``path`` when it exists; else a failure in CI (which must have ../shared) or a skip."""
    if not path.is_dir():
        if os.environ.get("CI"):
            pytest.fail(f"{path} is missing: CI must have ../shared beside the checkout")
        pytest.skip(f"{what} not found at {path} (set STREAMCAL_SHARED)")
    return path


@pytest.fixture(scope="session")
def real_tracks_dir() -> Path:
    return _shared_dir(REAL_TRACKS, "real tracks")


@pytest.fixture(scope="session")
def flight_dir() -> Path:
    return _shared_dir(REAL_FLIGHTS, "flight logs")


@pytest.fixture(scope="session")
def real_data_dir() -> Path:
    return _shared_dir(SHARED / "data" / "real", "real data")

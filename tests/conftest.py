import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
SHARED = Path(os.environ.get("STREAMCAL_SHARED", REPO.parent / "shared"))
REAL_TRACKS = SHARED / "data" / "real" / "tracks"


@pytest.fixture(scope="session")
def real_tracks_dir() -> Path:
    if not REAL_TRACKS.is_dir():
        if os.environ.get("CI"):
            pytest.fail(f"{REAL_TRACKS} is missing: CI must have ../shared beside the checkout")
        pytest.skip(f"real tracks not found at {REAL_TRACKS} (set STREAMCAL_SHARED)")
    return REAL_TRACKS

"""Recordings in: track files (CSV/CSV.gz) and the readers of other formats, all into a
:class:`~streamcal.inputs.track.Track`."""
from .track import Track

__all__ = ["Track"]

"""Streaming calibration (DESIGN §1): a bounded coverage buffer, the running sphere estimate, a
recalibration policy, fits off the ingest path, an acceptance guard and an atomic store.

    from streamcal.stream import StreamingCalibrator, CalibrationStore
    cal = StreamingCalibrator(store=CalibrationStore("state"))
    events = cal.ingest(block)          # block: streamcal.samples.SampleBlock

Names are imported lazily so that e.g. ``streamcal.stream.store`` loads without the fit code.
"""
from __future__ import annotations

import importlib

_WHERE = {
    "StreamingCalibrator": "calibrator", "Event": "events", "default_fitter": "fitworker",
    "CoverageBuffer": "coverage", "CoverageReport": "coverage", "Snapshot": "coverage",
    "SphereCells": "coverage", "AcceptanceGuard": "guard", "Decision": "guard",
    "RecalPolicy": "policy", "CalibrationStore": "store", "LoadResult": "store",
}

__all__ = sorted(_WHERE)


def __getattr__(name):
    if name in _WHERE:
        return getattr(importlib.import_module(f".{_WHERE[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

"""Streaming calibration (DESIGN §1): a bounded coverage buffer, the running sphere estimate, a
recalibration policy, fits off the ingest path, an acceptance guard and an atomic store.

    from streamcal.stream import StreamingCalibrator, CalibrationStore
    cal = StreamingCalibrator(store=CalibrationStore("state"))
    events = cal.ingest(block)          # block: firmware_bridge.sample.SampleBlock
"""
from .calibrator import Event, StreamingCalibrator, default_fitter
from .coverage import CoverageBuffer, CoverageReport, Snapshot, SphereCells
from .guard import AcceptanceGuard, Decision
from .policy import RecalPolicy
from .store import CalibrationStore, LoadResult

__all__ = ["AcceptanceGuard", "CalibrationStore", "CoverageBuffer", "CoverageReport", "Decision",
           "Event", "LoadResult", "RecalPolicy", "Snapshot", "SphereCells", "StreamingCalibrator",
           "default_fitter"]

"""Physics simulator of an MPU-9250 turned by hand, writing tracks with a known truth.

    from streamcal.sim import simulate, paper_protocol
    res = simulate(duration_s=120, seed=1, effects={"temperature_offset": 0.05}, outlier_bursts=1)
    res.track            # a streamcal Track (docs/tracks_and_inputs.md columns, async mag/IMU rows)
    res.truth.K, res.truth.b, res.truth.effects, res.truth.outlier_spans
    m, K, b, inliers = paper_protocol(n=1000, sigma=1.0, eta=0.1, seed=0)

Modules: :mod:`.motion` (orientation paths and coverage patterns), :mod:`.sensor` (sensor error
models, the effect terms, MPU-9250 quantization), :mod:`.scenario` (a recording session →
track + truth), :mod:`.paper` (the autocalibration paper's synthetic protocol).
"""
from .motion import COVERAGES
from .paper import paper_protocol
from .scenario import SimResult, SimTruth, simulate
from .sensor import SIM_EFFECTS

__all__ = ["COVERAGES", "SIM_EFFECTS", "SimResult", "SimTruth", "paper_protocol", "simulate"]

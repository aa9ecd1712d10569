"""Model diagnosis (docs/cli.md ``streamcal diagnose``): residual families, the noise floor,
outlier spans and the ranking of missing effects."""
from .result import Diagnosis
from .entry import diagnose
from .noise import NoiseFloor, noise_floor
from ..fitting.outlier_rule import outlier_spans

__all__ = ["Diagnosis", "NoiseFloor", "diagnose", "noise_floor", "outlier_spans"]

"""The result of :func:`streamcal.fitting.fit` with ``full_output=True``: the calibration and
how the solver ended (in the manner of scipy's ``OptimizeResult``)."""
from __future__ import annotations

from dataclasses import dataclass

from ..calibration import Calibration


@dataclass(frozen=True)
class FitResult:
    """``calibration``; ``status`` of the last robust LM pass — ``converged`` (relative cost
    decrease below the tolerance), ``stalled`` (no step lowered the cost: a minimum or a
    numerically flat spot), ``max_iter`` (budget used while the cost still fell), or ``None``
    for a reference method that reports none; ``iterations`` of that solver (rounds summed over
    the width passes of the gravity-tied fit); ``message`` in words."""

    calibration: Calibration
    status: str | None
    iterations: int
    message: str

    @property
    def success(self) -> bool:
        return self.status == "converged"

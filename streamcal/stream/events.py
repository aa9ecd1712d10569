"""What the streaming calibrator reports: :class:`Event`."""
from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class Event:
    """Something the calibrator did or noticed.

    ``kind``: ``loaded``, ``load_problem``, ``coverage``, ``fit_started``, ``fit_failed``,
    ``accepted``, ``rejected``, ``discarded``, ``disturbance`` (a disagreement ended:
    ``outcome`` ``transient``, or undecided: ``reference_replaced``, ``undecided`` (not
    judgeable within the persistence time while a finished fit waited), ``open`` at the end of
    the stream; ``start``, ``end``, ``peak`` error in the sensor unit, ``held`` samples held back),
    ``drift`` (an environment change), ``forgot``, ``recalled``, ``clock_reset`` (sample times
    went back; later ones are shifted by ``shift`` s), ``stored``, ``store_error``. ``t`` is
    the sample time (s) at which it happened, ``data`` its figures
    (JSON-ready); ``detail`` an object behind them, not serialized (a ``coverage`` event's
    :class:`~.coverage.CoverageReport`, with the occupied cells, for a map that agrees with it).
    """

    kind: str
    message: str
    data: dict = field(default_factory=dict)
    t: float | None = None
    detail: object = field(default=None, repr=False, compare=False)

    def to_dict(self) -> dict:
        return {"event": self.kind, "t": self.t, "message": self.message, **self.data}

"""The per-sample views of a track and its diagnosis that every figure draws (:class:`FigureData`).

No matplotlib here: building the views is numpy only.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np



def unit_label(unit: str) -> str:
    """Display form of a sensor unit (``uT`` → ``µT``): :func:`streamcal.units.display_unit`;
    ``unit unknown`` for a unit the track does not name in words streamcal knows (an axis
    label keeps its brackets meaningful)."""
    from ..units import display_unit

    return display_unit(unit) or "unit unknown"


@dataclass
class FigureData:
    """Per-sample views of a track and its diagnosis, shared by every figure.

    Attributes (N magnetometer samples):
        t: (N,) s. m: (N,3) readings, sensor unit. cov: covariates at the samples {name: (N,)}.
        unit: sensor unit. diagnosis: the :class:`~streamcal.diagnose.Diagnosis` or None.
        reason: why there is no diagnosis (the fit's refusal), else None.
        inliers: (N,) bool: not the diagnosis' ``outliers`` (the model ``outliers_model``, the
        one its ``n_outliers`` and spans come from), else the calibration's.
        directions: (N,3) unit field directions (calibrated, or from the coarse sphere when
        refused). residual: (N,) signed distance to the fitted surface along
        its outward normal, sensor unit (None when refused). field_after: (N,) ‖calibrated
        field‖, sensor unit (None when refused). scale: field strength used, sensor unit.
    """

    t: np.ndarray
    m: np.ndarray
    cov: dict
    unit: str
    diagnosis: object = None
    reason: str | None = None
    inliers: np.ndarray = None
    directions: np.ndarray = None
    residual: np.ndarray | None = None
    field_after: np.ndarray | None = None
    scale: float = float("nan")
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def calibration(self):
        return None if self.diagnosis is None else self.diagnosis.calibration

    @property
    def accel(self) -> np.ndarray | None:
        if all(k in self.cov for k in ("ax", "ay", "az")):
            return np.stack([self.cov["ax"], self.cov["ay"], self.cov["az"]], axis=1)
        return None

    @classmethod
    def build(cls, track, diagnosis=None, reason: str | None = None) -> "FigureData":
        """Views of ``track`` (:class:`streamcal.inputs.track.Track`) with ``diagnosis`` (or, when
        None, the raw data only, ``reason`` saying why)."""
        m = np.asarray(track.mag, dtype=float)
        cov = {k: np.asarray(v, dtype=float) for k, v in track.covariates_at_mag().items()}
        t = cov.get("t", np.asarray(track.t_mag, dtype=float))
        data = cls(t=t, m=m, cov=cov, unit=track.mag_unit, diagnosis=diagnosis, reason=reason)
        cal = data.calibration
        if cal is None:
            data._coarse()
        else:
            data._calibrated(cal)
        return data

    def _calibrated(self, cal) -> None:
        from ..fitting.outlier_rule import outlier_mask
        from ..diagnosis.residuals import sensor_residual

        r, x, s, _ = sensor_residual(cal, self.m, self.cov)
        # The diagnosis' outliers (its n_outliers and spans, one model) when it has them.
        out = getattr(self.diagnosis, "outliers", None)
        inl = ~np.asarray(out, bool) if out is not None and np.shape(out) == (len(self.m),) \
            else getattr(cal, "inliers", None)
        if inl is None or np.shape(inl) != (len(self.m),):
            inl = ~outlier_mask(np.linalg.norm(r, axis=1), None,
                                floor=self.diagnosis.noise_floor)
        self.inliers = np.asarray(inl, bool)
        self.directions, self.residual = x, s
        self.scale = float(cal.field or cal.radius)
        self.field_after = np.linalg.norm(cal.apply(self.m, self.cov), axis=1) * self.scale
        self.center = np.asarray(cal.b, dtype=float)

    def _coarse(self) -> None:
        from ..fitting.sphere_stream import SphereStats

        stats = SphereStats()
        stats.update(self.m)
        try:
            center, radius = stats.fit()
        except Exception:   # fewer than 4 samples or degenerate: centre on the median
            center = np.median(self.m, axis=0) if len(self.m) else np.zeros(3)
            radius = float("nan")
        d = self.m - center
        norm = np.linalg.norm(d, axis=1, keepdims=True)
        self.directions = d / np.where(norm > 0, norm, 1.0)
        self.inliers = np.ones(len(self.m), bool)
        self.center, self.scale = np.asarray(center, float), float(radius)

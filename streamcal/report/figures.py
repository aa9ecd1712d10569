"""Figures of a diagnosis: what the model sees, where it fails, and what fixes it.

Every figure is drawn on its own :class:`matplotlib.figure.Figure` with the Agg canvas (no
``pyplot``, no global backend switch, safe in threads and on a machine without a display) and
saved as PNG with the software/date metadata removed, so the same inputs give the same bytes.
Large tracks are thinned with a fixed stride for the scatter plots (every outlier is kept).

The figures (names are the PNG file names without ``.png``):

- ``ellipsoid``: raw readings in three orthogonal projections with the fitted surface
  ``m = K x + b`` (‖x‖ = 1) as a wireframe, inliers and outliers marked (autocalibration paper,
  Fig. 1/7 top).
- ``magnitude``: ‖m‖ before and ‖calibrated field‖ after calibration per sample, and the angle
  between the field and gravity (dip) before/after when the track has an accelerometer (Fig. 7
  bottom).
- ``coverage``: the sphere of field directions on two Lambert azimuthal equal-area discs (the
  hemispheres around +Z and −Z), cut into the equal-area cells of
  :class:`streamcal.sphere_cells.SphereCells`; each seen cell coloured by the rms residual of
  its samples, empty cells grey, the largest empty cap marked.
- ``residuals``: the signed residual (distance to the fitted surface along its normal) against
  time, temperature and each auxiliary channel, with the binned rms of the diagnosis and the
  noise floor; outlier spans shaded on the time axis.
- ``ladder``: rms after each effect the ladder added, the noise floor as a line, and every
  candidate's promised ``rms_after`` — each against the model without it *on the same
  residual*: the sensor residual (eq. 41) and the gravity- and gyro-tied residuals of the
  registration effects are different scales (:data:`RESIDUAL_FAMILIES`), so each gets its own
  panel, its own "model now" line and its own noise level, and the ladder marks where it
  switches residual.

When the fit refused the track (:class:`~streamcal.errors.InsufficientDataError`) the figures
show what does not need a calibration: raw readings, ‖m‖, and coverage seen from the centre of a
one-pass sphere fit.

Where they live: :mod:`.figure_data` (the per-sample views), :mod:`.figure_common` (colours,
thinning, PNG), :mod:`.figures_sphere` (ellipsoid, coverage), :mod:`.figures_residual`
(magnitude, residuals), :mod:`.figures_ladder` (ladder); this module lists them in page order.
"""
from __future__ import annotations

from .figure_common import RenderedFigure, png_bytes
from .figure_data import FigureData
from .figures_ladder import ladder_figure
from .figures_residual import magnitude_figure, residuals_figure
from .figures_sphere import coverage_figure, ellipsoid_figure


#: (name, title, caption, function, needs a diagnosis)
FIGURES = (
    ("ellipsoid", "Raw readings and the fitted ellipsoid",
     "Three orthogonal projections of the raw magnetometer readings. A calibrated sensor's "
     "readings lie on the ellipsoid m = K x + b; points far from the wireframe are outliers "
     "(red), points spread around it show what the model misses.", ellipsoid_figure, False),
    ("magnitude", "Field magnitude and dip angle",
     "Before calibration the field magnitude swings with the orientation; after it, it should "
     "stay at the local field strength, and the dip (angle between field and gravity) should be "
     "constant. What is left is error the model does not explain (or motion, for the dip).",
     magnitude_figure, False),
    ("coverage", "Coverage of the sphere of directions",
     "Each equal-area cell of the sphere of field directions, coloured by the rms residual of "
     "the samples that fell in it. Grey cells were never seen: turn the sensor so the field "
     "arrives from there. Cells brighter than the rest show where the model fails.",
     coverage_figure, False),
    ("residuals", "Residual against time and covariates",
     "The signed distance of each reading to the fitted surface against time, temperature and "
     "each auxiliary channel, with the binned rms; a trend here is an effect the model lacks. "
     "Shaded: outlier spans.", residuals_figure, False),
    ("ladder", "Model ladder and candidates",
     "Left: the rms after adding, one by one, the effect that explains most; it should fall to "
     "the noise floor. Right: what each candidate effect would give on its own, one panel per "
     "residual: misalignment and lag leave no trace where every direction is free, so they are "
     "measured on a residual whose direction is tied to gravity (or the gyro), which has its "
     "own, higher level. Compare each bar with the black line of its own panel (the model "
     "without the effect on that residual); the percentage is that change.", ladder_figure, True),
)


def render_figures(data: FigureData) -> list[RenderedFigure]:
    """Every figure that ``data`` supports, as PNG."""
    out = []
    for name, title, caption, draw, needs_diagnosis in FIGURES:
        if needs_diagnosis and data.diagnosis is None:
            continue
        out.append(RenderedFigure(name, title, caption, png_bytes(draw(data))))
    return out

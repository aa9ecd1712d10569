"""Numbers used across layers (bottom layer: imports nothing from the package)."""
from __future__ import annotations

#: Standard gravity (m/s², CGPM 1901): the accelerometer's known field, m/s² per g.
GRAVITY = 9.80665
#: Median of |N(0,1)|: a median residual norm over this is σ (half-normal).
HALF_NORMAL_MEDIAN = 0.6744897501960817
#: σ = MAD_TO_SIGMA × median |r| for Gaussian r (1 / HALF_NORMAL_MEDIAN ≈ 1.4826).
MAD_TO_SIGMA = 1.0 / HALF_NORMAL_MEDIAN
#: ‖gyro‖ below this (rad/s) counts as still.
STILL_RATE = 0.05
#: A residual farther than this many kernel widths is reported an outlier.
OUTLIER_WIDTHS = 2.0
#: Cauchy kernel width in noise σ̂ (95 % Gaussian efficiency, three digits) of the fits that
#: re-estimate σ̂: the held fit, the gyro link and the fits against a reference field
#: (fitting.reference_fit, fitting.no_tumble).
CAUCHY_C = 2.385
#: Track columns of the vehicle's logged attitude: the unit quaternion (scalar first) that turns
#: body-frame (forward-right-down) vectors into the local NED earth frame. They are not
#: auxiliary channels (no effect term is fitted on them).
ATTITUDE_COLUMNS = ("att_qw", "att_qx", "att_qy", "att_qz")

"""The running sphere estimate: framing and change watching before the first calibration.

Until a calibration is in force, the calibrator keeps O(1) running sums of the samples
(:class:`~streamcal.fitting.sphere_stream.SphereStats`) and refits a sphere (centre ``c``,
radius ``R``) from them every ``every`` samples: it frames directions for the coverage buffer
and, once it fits the stored samples well, watches for an environment change (as a
:class:`~.reference.Reference` that holds nothing back).
"""
from __future__ import annotations

import numpy as np

from ..calibration import Calibration
from ..constants import MAD_TO_SIGMA
from ..fitting.sphere_stream import SphereStats
from .reference import Reference

#: The sphere fit stops at this relative step and after this many Gauss–Newton iterations: it
#: only frames directions.
TOL, MAX_ITER = 1e-6, 8
#: The estimate judges new samples only when the stored ones fit it within this relative spread
#: (MAD_TO_SIGMA × median |‖m − c‖/R − 1|): soft iron leaves a few percent; a sphere through a
#: noise cluster (a board at rest) or through two environments leaves far more.
MAX_SPREAD = 0.05
#: Above this relative spread the estimate does not even frame directions: the stored samples
#: are no sphere and the coverage they would show is not measured. A board at rest (its noise
#: cluster) leaves 0.45 whatever the noise (σ = 0.1–1 µT, 30 s through the calibrator); soft iron
#: with axes 1.5 : 1 about 0.2 on a full sphere and 0.03 on the cap the first 20 s of turning
#: cover (axes 2 : 1: 0.34 on a full sphere, by when a first calibration frames them).
FRAME_SPREAD = 0.3
#: A stage of readings is a board at rest when their spread (RMS distance from their mean) is at
#: most REST_RATIO times their sample-to-sample noise (RMS step / √2; white noise alone gives 1,
#: the slowest turn a stage of 0.9–2.6 s holds moves the reading by tens of times the 0.1–1 µT
#: noise) and at most REST_OF_FIELD of their mean's magnitude (samples in random order spread
#: like noise, but over the whole sphere). One in REST_KEEP of them enters the sums. Fewer than
#: REST_MIN readings are not judged: over a fraction of a second a slow turn moves the reading
#: less than its noise.
REST_RATIO, REST_OF_FIELD, REST_KEEP, REST_MIN = 3.0, 0.1, 16, 128
#: A sphere whose radius exceeds this many times the RMS distance of its samples from their mean
#: is undetermined: they lie on a cap narrower than about 8° (a cap of half-angle θ spreads
#: about R·θ/√2), or on no sphere, and such a fit returns radii of thousands of µT that frame
#: every direction into one cell.
MAX_RADIUS_SPREAD = 10.0
#: Why the buffer is unframed before the first estimate.
NO_ESTIMATE = ("no sphere through the readings yet (an estimate comes every {n} samples): "
               "keep rotating the board through many orientations")


def at_rest(m: np.ndarray) -> bool:
    """The readings ``m`` (n,3) (finite, in time order) spread no more than their noise: a board
    at rest (:data:`REST_RATIO`)."""
    if len(m) < REST_MIN:
        return False
    mean = m.mean(axis=0)
    step2 = float(np.mean(np.sum(np.diff(m, axis=0) ** 2, axis=1)))
    spread2 = float(np.mean(np.sum((m - mean) ** 2, axis=1)))
    return spread2 <= min(REST_RATIO ** 2 * step2 / 2.0, REST_OF_FIELD ** 2 * float(mean @ mean))


def sphere_of(stats: SphereStats, min_n: int):
    """Sphere ``(centre (3,), radius)`` of the sums ``stats``, or None with fewer than ``min_n``
    samples or when undetermined (too few directions, or a radius over :data:`MAX_RADIUS_SPREAD`
    times the samples' spread)."""
    if stats.n < min_n:
        return None
    try:
        c, R = stats.fit(tol=TOL, max_iter=MAX_ITER)
    except Exception:           # too few directions yet
        return None
    if not (np.all(np.isfinite(c)) and np.isfinite(R) and R > 0):
        return None
    mean = stats.s1 / stats.n
    spread = np.sqrt(max(float(np.trace(stats.s2)) / stats.n - float(mean @ mean), 0.0))
    return (c, R) if R <= MAX_RADIUS_SPREAD * spread else None


def sphere_of_samples(m: np.ndarray, min_n: int):
    """:func:`sphere_of` the samples ``m`` (n,3) (sensor unit)."""
    stats = SphereStats()
    stats.update(m)
    return sphere_of(stats, min_n)


class RunningSphere:
    """Running sums over a sliding window, the latest estimate ``(c, R)`` (or None) and its
    reference (or None).

    A stage of readings at rest (:func:`at_rest`) adds one in :data:`REST_KEEP` of them (they
    frame the buffer while nothing else is there; the first stage that moves replaces sums of
    readings at rest only), and the sums cover the last
    ``window`` to ``2 window`` samples (two epochs, each ``window`` samples; the older is dropped
    when the newer is full): sums of a whole stream that began at rest and then changed its
    field fitted a sphere through the thousands of copies of one point and the new shell,
    hundreds of times the field's radius, which framed every direction into one cell.

    Args:
        every: samples between refits.
        min_n: fewest samples for a fit.
        window: samples per epoch of the sums (memory stays O(1)).
    """

    def __init__(self, every: int = 200, min_n: int = 100, window: int = 4096):
        self.every, self.min_n = int(every), int(min_n)
        self.window = max(int(window), self.min_n)
        self.stats = SphereStats()
        self._older = SphereStats()
        self.estimate: tuple[np.ndarray, float] | None = None
        self.reference: Reference | None = None
        self._since = 0
        self._rest_only = True      # the sums hold readings at rest only (or none)

    @property
    def n(self) -> int:
        """Samples in the sums."""
        return self.stats.n + self._older.n

    @property
    def nbytes(self) -> int:
        return self.stats.s22.nbytes + self._older.s22.nbytes

    def add(self, m: np.ndarray, counted: int | None = None) -> bool:
        """Add samples ``m`` (n,3) (finite, in time order) to the sums, one in :data:`REST_KEEP`
        when they are at rest (``counted``: samples seen, default n); True when a refit
        (:meth:`refit`) is due."""
        seen = len(m) if counted is None else int(counted)
        if at_rest(m):
            m = m[::REST_KEEP]
        elif len(m):
            if self._rest_only:     # the board moves: the rest cluster has nothing more to say
                self.stats.reset()
                self._older.reset()
            self._rest_only = False
        if self.stats.n >= self.window:
            self._older, self.stats = self.stats, self._older
            self.stats.reset()
        self.stats.update(m)
        self._since += seen
        return self._since >= self.every

    def _sums(self) -> SphereStats:
        """Both epochs' sums as one."""
        if not self._older.n:
            return self.stats
        return self._older.copy().merge(self.stats)

    def refit(self) -> tuple[tuple | None, bool]:
        """Refit from the sums: ``(estimate, moved)``; ``estimate`` None (kept the old one) when
        undetermined; ``moved`` when the centre or radius moved by over 5 % of the radius."""
        self._since = 0
        found = sphere_of(self._sums(), self.min_n)
        if found is None:
            return None, False
        c, R = found
        previous, self.estimate = self.estimate, (c, R)
        moved = previous is None or (np.linalg.norm(c - previous[0]) > 0.05 * R
                                     or abs(R - previous[1]) > 0.05 * R)
        return found, moved

    def reset(self, m: np.ndarray) -> None:
        """Restart from the samples ``m`` (n,3) (those kept after an environment change)."""
        self.stats.reset()
        self._older.reset()
        self.stats.update(m)
        self._rest_only = not len(m)
        self.estimate = None
        self.reference = None
        self._since = 0

    def judge_reference(self, stored: np.ndarray, occupied: np.ndarray, drift_limit):
        """The estimate as a :class:`~.reference.Reference` judging the cells ``occupied`` (C,)
        bool, with its limit ``drift_limit(rms, R)`` from how well the stored samples
        ``stored`` (n,3) fit it; None without an estimate or when they fit it worse than
        :data:`MAX_SPREAD` (a sphere fitted to a cluster of noise, or to a mixture)."""
        spread = self.spread(stored)
        if spread is None or spread > MAX_SPREAD:
            return None
        c, R = self.estimate
        return Reference(c, np.eye(3) / R, R, spread * R, drift_limit(spread * R, R),
                         occupied.copy(), None, False)

    def spread(self, stored: np.ndarray) -> float | None:
        """Relative spread MAD_TO_SIGMA × median |‖m − c‖/R − 1| of the samples ``stored``
        (n,3) about the estimate; None without an estimate or samples."""
        if self.estimate is None or not len(stored):
            return None
        c, R = self.estimate
        return MAD_TO_SIGMA * float(np.median(np.abs(np.linalg.norm(stored - c, axis=1) / R
                                                     - 1.0)))

    def frame_problem(self, stored: np.ndarray) -> str:
        """Why the estimate cannot frame the directions of ``stored`` (n,3) ("" when it can)."""
        spread = self.spread(stored)
        if spread is None:
            return NO_ESTIMATE.format(n=self.every)
        if spread > FRAME_SPREAD:
            return (f"the readings lie on no sphere yet (relative spread {spread:.0%} about the "
                    f"best one, more than {FRAME_SPREAD:.0%}: a board at rest, or turned too "
                    "little): rotate the board slowly through many orientations")
        return ""

    def calibration(self, unit: str) -> Calibration | None:
        """The estimate as a hard-iron-only :class:`Calibration` (None without one)."""
        if self.estimate is None:
            return None
        c, R = self.estimate
        return Calibration(K=R * np.eye(3), b=c, model=("hard_iron",), method="sphere_stream",
                           unit=unit, n=self.n)

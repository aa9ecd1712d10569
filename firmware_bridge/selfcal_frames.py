"""The SELF_CAL frame (type 0x08, board → host): the board's own calibration (PROTOCOL.md).

The sketch fits a sphere to each window of magnetometer samples whose coverage mask is full,
checks it on the next window (held out), and keeps it only if it beats the calibration in
force there. Each fit and each decision is one SELF_CAL frame; ``frames.MESSAGES`` decodes it
as :class:`SelfCal`.
"""
from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from .messages import Message, MsgType, SetCalibration


class SelfCalEvent(enum.IntEnum):
    FITTED = 1        # a window's sphere fit: the candidate, checked on the next window
    ACCEPTED = 2      # the candidate won its held-out check: stored in EEPROM, applied
    REJECTED = 3      # the candidate lost (or failed) its held-out check: nothing changed
    FIT_FAILED = 4    # the window's samples did not determine a sphere


class SelfCalReason(enum.IntEnum):
    NONE = 0
    NO_CAL_IN_FORCE = 1   # accepted: nothing was in force and the candidate is good enough
    BEATS_IN_FORCE = 2    # accepted: held-out loss below 3/4 of the calibration in force
    NOT_BETTER = 3        # rejected: held-out loss not below 3/4 of the calibration in force
    EEPROM_FAILED = 4     # rejected: the EEPROM read-back did not match
    UNDETERMINED = 5      # fit failed: too few directions
    TOO_POOR = 6          # rejected: nothing in force, but the held-out loss is too high


class CalOrigin(enum.IntEnum):
    NONE = 0
    HOST = 1          # SET_CAL from a host
    BOARD = 2         # the board's own fit
    BUILTIN = 3       # sc_initial_cal.h compiled into the sketch


REASON_TEXT = {
    SelfCalReason.NO_CAL_IN_FORCE: "no calibration was in force and it fits the held-out samples",
    SelfCalReason.BEATS_IN_FORCE: "it fits the held-out samples better by more than a quarter",
    SelfCalReason.NOT_BETTER: "it does not fit the held-out samples better by a quarter",
    SelfCalReason.EEPROM_FAILED: "the EEPROM write did not read back",
    SelfCalReason.UNDETERMINED: "the window's samples do not determine a sphere",
    SelfCalReason.TOO_POOR: "it fits the held-out samples too poorly to use",
}


@dataclass(frozen=True)
class SelfCal(Message):
    """One fit or decision of the board's own calibration.

    ``origin``/``in_force_id``: the calibration in force after this event (:class:`CalOrigin`);
    ``cells``: coverage cells (of 64) of the window that ended; ``n_fit``: samples in the
    candidate's fit; ``n_check``: held-out samples scored; ``fit_cost``: the fit's mean squared
    residual ``(1 − |u|²/R²)²``; ``loss_new``/``loss_old``: mean held-out loss
    ``min((|x|² − 1)², 0.0625)`` of the candidate and of the calibration in force (NaN: none);
    ``fit_cycles``: the fit's CPU cycles; ``sample_cycles``: mean cycles of one magnetometer
    sample's calibration work (sums, cell, scores); then the candidate (K = R·I, b, µT).
    """

    TYPE: ClassVar = MsgType.SELF_CAL
    LAYOUT: ClassVar = (("event", "B", 1), ("reason", "B", 1), ("origin", "B", 1),
                        ("in_force_id", "H", 1), ("cells", "B", 1), ("n_fit", "I", 1),
                        ("n_check", "I", 1), ("fit_cost", "f", 1), ("loss_new", "f", 1),
                        ("loss_old", "f", 1), ("fit_cycles", "I", 1), ("sample_cycles", "I", 1)) \
        + SetCalibration.LAYOUT
    event: int = 0
    reason: int = 0
    origin: int = 0
    in_force_id: int = 0
    cells: int = 0
    n_fit: int = 0
    n_check: int = 0
    fit_cost: float = 0.0
    loss_new: float = math.nan
    loss_old: float = math.nan
    fit_cycles: int = 0
    sample_cycles: int = 0
    cal_id: int = 0
    k: tuple = (0.0,) * 6
    b: tuple = (0.0,) * 3
    crc: int = 0

    def matrices(self) -> tuple[np.ndarray, np.ndarray]:
        """The candidate's ``(K (3,3), b (3,))`` in µT, float64."""
        K = np.zeros((3, 3))
        K[np.triu_indices(3)] = self.k
        return K, np.array(self.b, dtype=float)

    def describe(self) -> str:
        """One line for a person: what happened, why, and what is in force."""
        event = SelfCalEvent(self.event).name.lower() if self.event in SelfCalEvent._value2member_map_ \
            else f"event {self.event}"
        b = ", ".join(f"{v:.2f}" for v in self.b)
        text = f"board fit 0x{self.cal_id:04X} (R {self.k[0]:.2f} uT, b [{b}] uT, {self.n_fit} samples) {event}"
        if self.event in (SelfCalEvent.ACCEPTED, SelfCalEvent.REJECTED):
            old = "none in force" if math.isnan(self.loss_old) else f"in force {self.loss_old:.5f}"
            text += f": held-out loss {self.loss_new:.5f} vs {old} over {self.n_check} samples"
        why = REASON_TEXT.get(self.reason)
        if why:
            text += f" ({why})"
        origin = CalOrigin(self.origin).name.lower() if self.origin in CalOrigin._value2member_map_ else "?"
        return text + f"; in force: {origin} 0x{self.in_force_id:04X}" if self.origin else text + "; in force: none"

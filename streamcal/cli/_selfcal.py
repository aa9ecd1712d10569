"""The board's own calibration beside the host's, for ``streamcal serial`` (issue #15).

The ``streamcal_bridge`` sketch fits a sphere to each window of its own magnetometer samples and
announces every fit and decision in a SELF_CAL frame (``firmware_bridge.selfcal_frames``). The
host meanwhile sends each calibration it accepts (its robust fit) to the board, which stores it
and applies it. :func:`board_self_cal` says, from those frames and the board's final
CAL_REPORT, which calibration the board has in force and why, and how far the board's latest
fit lies from the host's calibration (paper eq. 40); :func:`format_board_self_cal` is the text.
"""
from __future__ import annotations

import math

from firmware_bridge.selfcal_frames import REASON_TEXT, CalOrigin, SelfCalEvent

from ..calibration import Calibration

WHY_HOST = ("the host's calibration: this host sends each calibration it accepts, and the board's "
            "own fit replaces it only if that fits the board's held-out samples better by a quarter")
WHY_BUILTIN = "the calibration compiled into the sketch (sc_initial_cal.h): none is stored in EEPROM"


def _origin_name(origin: int) -> str:
    return CalOrigin(origin).name.lower() if origin in CalOrigin._value2member_map_ else f"origin {origin}"


def board_self_cal(frames, host: Calibration | None, board_cal_id: int | None = None,
                   sent_ids=()) -> dict | None:
    """The board's own calibration and what is in force, or None if no SELF_CAL frame arrived.

    ``frames``: the SELF_CAL messages in arrival order; ``host``: the host's calibration in use
    (None: none yet); ``board_cal_id``: the cal_id the board reported at the end (CAL_REPORT;
    None: unknown or none valid); ``sent_ids``: cal_ids this host sent to the board.
    Returns a JSON-ready dict: ``events`` (count per event), ``last`` (the last frame in words),
    ``fit`` (the latest fit: cal_id, R µT, b µT, samples, mean squared residual, cycles),
    ``in_force`` (origin, cal_id, why) and ``board_fit_vs_host`` (eq. 40, None if either is missing).
    """
    frames = list(frames)
    if not frames:
        return None
    events: dict[str, int] = {}
    for f in frames:
        name = SelfCalEvent(f.event).name.lower() if f.event in SelfCalEvent._value2member_map_ else str(f.event)
        events[name] = events.get(name, 0) + 1
    fits = [f for f in frames if f.event == SelfCalEvent.FITTED]
    last = frames[-1]
    out: dict = {"events": events, "last": last.describe(), "fit": None, "board_fit_vs_host": None}
    if fits:
        f = fits[-1]
        out["fit"] = {"cal_id": f.cal_id, "R": f.k[0], "b": list(f.b), "n_fit": f.n_fit,
                      "fit_cost": f.fit_cost, "fit_cycles": f.fit_cycles}
        if host is not None:
            K, b = f.matrices()
            out["board_fit_vs_host"] = Calibration(K=K, b=b).model_error(host)
    origin, cal_id = last.origin, last.in_force_id
    if board_cal_id is not None and board_cal_id != cal_id:
        # the board's answer at the end is newer than its last SELF_CAL frame
        cal_id = board_cal_id
        origin = (CalOrigin.HOST if board_cal_id in set(sent_ids) else
                  CalOrigin.BOARD if any(f.cal_id == board_cal_id for f in fits) else last.origin)
    if origin == CalOrigin.BOARD:
        won = [f for f in frames if f.event == SelfCalEvent.ACCEPTED and f.cal_id == cal_id]
        why = "the board's own fit, accepted on its held-out check"
        if won:
            why += ": " + REASON_TEXT.get(won[-1].reason, f"reason {won[-1].reason}")
            if not math.isnan(won[-1].loss_old):
                why += f" (held-out loss {won[-1].loss_new:.5f} vs {won[-1].loss_old:.5f})"
            else:
                why += f" (held-out loss {won[-1].loss_new:.5f})"
    elif origin == CalOrigin.HOST:
        why = WHY_HOST
    elif origin == CalOrigin.BUILTIN:
        why = WHY_BUILTIN
    else:
        why = "no calibration is in force on the board"
    out["in_force"] = {"origin": _origin_name(origin), "cal_id": cal_id if origin else None, "why": why}
    return out


def format_board_self_cal(info: dict) -> str:
    """A few lines for a person from :func:`board_self_cal`'s dict."""
    lines = ["board's own calibration: " + ", ".join(f"{n} {k}" for k, n in info["events"].items())
             + " (SELF_CAL frames)"]
    fit = info["fit"]
    if fit is not None:
        b = ", ".join(f"{v:.2f}" for v in fit["b"])
        line = (f"  latest board fit 0x{fit['cal_id']:04X}: sphere R {fit['R']:.2f} uT, b [{b}] uT, "
                f"{fit['n_fit']} samples, mean squared residual (1 - |u|^2/R^2)^2 {fit['fit_cost']:.5f}")
        if info["board_fit_vs_host"] is not None:
            line += f"; differs from the host's calibration by {100 * info['board_fit_vs_host']:.2f} % (relative model error, eq. 40 of the paper)"
        else:
            line += "; the host has no calibration yet"
        lines.append(line)
    lines.append(f"  last board event: {info['last']}")
    f = info["in_force"]
    which = f"{f['origin']} 0x{f['cal_id']:04X}" if f["cal_id"] is not None else "none"
    lines.append(f"  in force on the board: {which} -- {f['why']}")
    return "\n".join(lines)

"""What every destination needs: the calibration as a symmetric correction matrix and offsets.

Streamcal's model is ``m = K x + b (+ effect terms)`` with ``K`` upper triangular (µT) and the
calibrated field ``f = |B| K⁻¹ (m − b)``. Autopilots correct with a *symmetric* matrix,
``f' = S (m − b)``. Write ``A = |B| K⁻¹`` as ``A = U S`` (polar decomposition: ``U``
orthogonal, ``S = (AᵀA)^½`` symmetric positive definite); then ``|S (m − b)| = |A (m − b)|``
for every reading, so the field magnitude, which is all a magnetometer calibration can observe
without another attitude reference, is the same. ``f' = Uᵀ f``: the two differ by the rotation
``U``, which the magnetometer alone cannot observe and which the symmetric form sets to the
smallest rotation.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..calibration import Calibration
from ..errors import InputError
from ..inputs.autopilot_cal import BOARD_ROTATION
from ..units import effect_params

#: Effects that are part of the matrix and offsets themselves.
CORE = ("hard_iron", "soft_iron", "scale")
#: aux_interference channels the autopilots' motor compensation can take: battery current (A) or
#: throttle (0..1).
CURRENT_CHANNELS = ("battery_current_a", "motor_current", "current", "curr")
THROTTLE_CHANNELS = ("throttle",)
#: The second battery's current (A), which PX4 compensates (CAL_MAG_COMP_TYP 3) and ArduPilot,
#: whose COMPASS_MOTCT 2 takes the first battery's, does not.
SECOND_BATTERY_CHANNELS = ("battery2_current_a",)


@dataclass
class Correction:
    """A calibration in correction form ``f = S (m − o) − comp``, µT.

    Attributes:
        S: (3,3) symmetric positive definite, dimensionless.
        offset: (3,) µT, subtracted from the reading (``= b`` plus any aux term at its median).
        rotation: (3,3) ``U`` of the polar decomposition (not exported; for tests and notes).
        field_uT: the calibrated field strength the matrix yields, µT, and whether it is the
            calibration's ``field_uT`` (``field_known``) or K's mean radius.
        channels: ``{aux name: (3,) µT per channel unit}`` sensor-frame interference terms.
        levels: ``{aux name: a0}``, the level of each channel its term is referred to (folded
            into ``offset`` as ``g a0``); :func:`hold_others` puts back those not exported.
        not_expressed: human-readable notes about what the destination cannot carry.
    """

    S: np.ndarray
    offset: np.ndarray
    rotation: np.ndarray
    field_uT: float
    field_known: bool
    channels: dict = field(default_factory=dict)
    levels: dict = field(default_factory=dict)
    not_expressed: list = field(default_factory=list)


def polar(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``A = U S`` with ``U`` orthogonal and ``S`` symmetric positive semidefinite (via SVD)."""
    W, sigma, Vt = np.linalg.svd(A)
    return W @ Vt, (Vt.T * sigma) @ Vt


def correction(cal: Calibration) -> Correction:
    """The :class:`Correction` of a magnetometer calibration in µT."""
    if cal.sensor != "mag":
        raise InputError(f"export: only magnetometer calibrations can be exported, this one is "
                         f"for {cal.sensor!r}")
    if cal.unit != "uT":
        raise InputError(f"export: the calibration is in {cal.unit!r}, not µT; destinations "
                         "need physical units (fit a track in µT, or convert its unit)")
    known = bool(cal.field)
    field_uT = float(cal.field) if known else float(np.prod(np.diag(cal.K)) ** (1 / 3))
    U, S = polar(field_uT * np.linalg.inv(cal.K))
    S = (S + S.T) / 2
    offset = cal.b.copy()
    channels, levels, notes = {}, {}, []
    for name, params in cal.effects.items():
        if name == "aux_interference":
            for chan, p in params.get("channels", {}).items():
                g = np.asarray(p["g"], dtype=float)
                offset = offset - g * float(p.get("a0", 0.0))  # term g (a − a0) = g a − g a0
                channels[chan] = g
                levels[chan] = float(p.get("a0", 0.0))
        elif name not in CORE:
            notes.append(f"{name}: {effect_params(name, params, cal.unit, digits=4)}")
    for name in cal.model:
        if name not in CORE and name not in cal.effects and name != "aux_interference":
            notes.append(f"{name} (in the model)")
    if not known:
        notes.append(f"field strength unknown: the matrix scales the field to K's mean radius "
                     f"{field_uT:.4g} µT")
    return Correction(S=S, offset=offset, rotation=U, field_uT=field_uT, field_known=known,
                      channels=channels, levels=levels, not_expressed=notes)


def motor_channel(channels, second_battery: bool = False
                  ) -> tuple[str | None, str | None, list[str]]:
    """The aux channel an autopilot's one motor compensation takes: the first of ``channels``
    (names, in order) that is a battery current (:data:`CURRENT_CHANNELS`), the throttle
    (:data:`THROTTLE_CHANNELS`) or, where the firmware can take it (``second_battery``), the
    second battery's current (:data:`SECOND_BATTERY_CHANNELS`). Returns (its name,
    ``"current"``, ``"throttle"`` or ``"current2"``, the other channels in order); (None, None,
    all of them) when none is."""
    kinds = {**dict.fromkeys(CURRENT_CHANNELS, "current"),
             **dict.fromkeys(THROTTLE_CHANNELS, "throttle"),
             **(dict.fromkeys(SECOND_BATTERY_CHANNELS, "current2") if second_battery else {})}
    chosen, kind, others = None, None, []
    for name in channels:
        if name in kinds and chosen is None:
            chosen, kind = name, kinds[name]
        else:
            others.append(name)
    return chosen, kind, others


def joint_fit_note(chosen: str | None, others: list[str]) -> list[str]:
    """The warning that the motor term exported alone was fitted beside other channels (which
    move with it on a vehicle): then it is not the fit's correction by itself."""
    if chosen is None or not others:
        return []
    return [f"aux_interference on {chosen!r} was fitted together with {', '.join(others)}: "
            f"alone it is not the fitted correction; for parameters to load, fit with "
            f"--add aux_interference={chosen}"]


def hold_others(corr: Correction, keep: str | None) -> None:
    """Drop every aux channel of ``corr`` but ``keep``, each held at its level ``a0``.

    The offset carries ``g a0`` of every channel so that ``S (m − o − g a)`` removes the whole
    term ``g (a − a0)``. A channel the destination cannot compensate leaves ``g a`` in the field
    unless ``g a0`` goes back into the offset: then only its swing ``g (a − a0)`` is left, which
    is what the fit assumed when it referred the term to ``a0``."""
    for name in [n for n in corr.channels if n != keep]:
        corr.offset = corr.offset + corr.channels.pop(name) * corr.levels.pop(name, 0.0)


def fmt(value: float) -> str:
    """A parameter value: shortest round-tripping decimal of a float32-precise number."""
    return f"{float(value) + 0.0:.7g}"  # + 0.0 turns -0.0 into 0.0


def mounting(cal: Calibration, firmware: str) -> tuple[np.ndarray | None, int | None, list[str]]:
    """The mounting rotation a calibration found (``extra["orientation"]``, docs/flight_logs.md):
    (its sensor → body matrix, the number ``firmware`` is to be set to — the rotation found, or
    after the one configured in the log when ``orientation["set"]`` says so —, notes);
    (None, None, []) without one. The board's rotation (an internal compass) is never written:
    it turns the IMU too; a note says what it would be when it differs from the log's."""
    from ..inputs.mount_rotations import by_name

    orient = (cal.extra or {}).get("orientation")
    if not orient or orient.get("name", "NONE") == "NONE":
        return None, None, []
    try:
        matrix = by_name(str(orient["name"])).matrix
    except KeyError:
        return None, None, [f"mounting rotation {orient['name']!r}: not a known rotation"]
    number = orient.get(firmware)
    chosen = orient.get("set") or {}
    configured = (orient.get("configured") or {}).get("value")
    if chosen.get("param"):
        if _firmware_of(chosen["param"]) != firmware:
            return None, None, [f"mounting rotation {orient['name']} was found relative to the "
                                f"frame of {chosen['param']} = {configured} of the other "
                                "autopilot; its rotation parameter is not written"]
        number = chosen.get("value")     # found after the rotation already configured in the log
        if chosen["param"] == BOARD_ROTATION[firmware]:
            return None, None, [] if number == configured else [
                f"the compass is internal and appears mounted {orient['name']} from the frame "
                f"of the readings: {chosen['param']} {number} would turn it, but that is the "
                f"board's rotation (now {configured}) and turns the accelerometer and gyro too; "
                "not written: set it by hand only if the whole board is mounted so"]
    if number is None:
        return None, None, [f"mounting rotation {orient['name']}: {firmware} has no number for it"
                            + (" combined with the one configured in the log"
                               if chosen.get("param") else "")]
    return matrix, int(number), []


def _firmware_of(param: str) -> str:
    """The autopilot a rotation parameter belongs to (COMPASS_ORIENTn, AHRS_ORIENTATION:
    ArduPilot; CAL_MAGn_ROT, SENS_BOARD_ROT: PX4)."""
    return "ardupilot" if param.startswith(("COMPASS_ORIENT", "AHRS_ORIENTATION")) else "px4"


def orientation_words(cal: Calibration) -> str:
    """``YAW_90`` or ``YAW_90 found after the configured COMPASS_ORIENT 8``."""
    orient = (cal.extra or {}).get("orientation") or {}
    conf = orient.get("configured")
    words = str(orient.get("name"))
    if conf and conf.get("value"):
        words += f" found after the configured {conf['param']} {conf['value']}"
    return words


#: Spellings in plain ASCII of the symbols streamcal's texts use (units, signs, arrows).
_ASCII = {"µ": "u", "μ": "u", "°": "deg", "²": "^2", "³": "^3", "⁻": "^-", "¹": "1",
          "−": "-", "–": "-", "—": "-", "→": "->", "≤": "<=", "≥": ">=", "×": "x", "·": "*",
          "±": "+/-", "σ": "sigma", "…": "...", "’": "'", "‘": "'", "“": '"', "”": '"',
          "√": "sqrt", "θ": "theta", "Δ": "d", "≈": "~"}


def ascii_text(text: str) -> str:
    """``text`` in plain ASCII ("µT/°C" → "uT/degC"; accents dropped, anything else "?").

    Parameter files stay ASCII: Mission Planner and QGroundControl skip ``#`` lines whatever
    their bytes, but MAVProxy's ``param load`` (pymavlink ``mavparm``) reads the file in the
    platform's encoding, where UTF-8 bytes of a comment can stop the whole load (Windows code
    page 1252 has no character for 0x81, the middle byte of "⁻¹")."""
    import unicodedata

    plain = "".join(_ASCII.get(c, c) for c in text)
    plain = unicodedata.normalize("NFKD", plain)
    plain = "".join(c for c in plain if not unicodedata.combining(c))
    return plain.encode("ascii", "replace").decode("ascii")


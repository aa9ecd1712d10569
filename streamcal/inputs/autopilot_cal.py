"""An autopilot's own compass calibration (ArduPilot ``COMPASS_*``, PX4 ``CAL_MAGn_*``) as a
streamcal Calibration.

ArduPilot corrects a body-frame reading ``r`` (milligauss) in ``AP_Compass_Backend::
correct_field``; the place of the motor term changed with the per-motor compensation (2018):

* Copter 3.6, Plane 3.9, Rover 3.3, Sub 4.0, AntennaTracker 1.1 and later
  (:data:`MOTOR_AFTER_MATRIX`)::

    f = S (r + o) + mot · c          S = [[DIA_X, ODI_X, ODI_Y],
                                          [ODI_X, DIA_Y, ODI_Z],
                                          [ODI_Y, ODI_Z, DIA_Z]]

* Copter 3.4–3.5, Plane 3.4–3.8, Rover 3.0–3.2, Sub 3.4–3.5, AntennaTracker 1.0
  (:data:`MOTOR_BEFORE_MATRIX`)::

    f = S (r + o + mot · c)

with ``o`` = COMPASS_OFS_* (mG, *added*), ``mot`` = COMPASS_MOT_* and ``c`` the battery current
(A, COMPASS_MOTCT = 2) or the throttle (0..1, COMPASS_MOTCT = 1). An all-zero DIA means 1; older
firmware has no DIA/ODI (``S = 1``, both orders agree). Solving for the reading in µT
(``m = r / 10``) with ``f = |F| x``::

    m = (|F|/10) S⁻¹ x − o/10 − S⁻¹ mot c / 10      (motor after the matrix)
    m = (|F|/10) S⁻¹ x − o/10 − mot c / 10          (motor before the matrix)

which is streamcal's ``m = A x + b + g c`` with ``A = |F| S⁻¹`` (|F| in µT), ``b = −o/10`` µT and
``aux_interference`` ``g = −S⁻¹ mot / 10`` (or ``−mot / 10``) µT per unit of the channel. ``A``
is symmetric; its canonical upper-triangular form ``K`` (``A = K Q``) describes the same
ellipsoid, with directions rotated by ``Q``.

PX4 corrects a reading ``r`` (gauss) as ``c = R S (r + p·comp − o)`` (``sensor_calibration/
Magnetometer``): ``o`` = CAL_MAGn_XOFF.. (G, *subtracted*), ``S`` symmetric from XSCALE.. and
XODIAG/YODIAG/ZODIAG (S12, S13, S23), ``R`` the board/CAL_MAGn_ROT rotation, ``comp`` =
CAL_MAGn_XCOMP.. with ``p`` the power signal of CAL_MAG_COMP_TYP (1 throttle 0..1, 2 battery
0's current in kA, 3 battery 1's). With ``c = |F| u`` and ``m = 100 r`` µT::

    m = |F| S⁻¹ Rᵀ u + 100 o − 100 comp p

so ``A = |F| S⁻¹ Rᵀ``: the rotation only turns the free directions, and ``K`` is the canonical
form of ``|F| S⁻¹`` whatever ``R`` (``A = K Q``, ``Q`` = ``frame_rotation_Q`` carries ``R``:
:func:`px4_rotation`, the one place that says which frame a PX4 reading ends up in);
``b = 100 o``; ``g = −100 comp`` µT per unit throttle, ``−0.1 comp`` µT/A
on battery current. (PX4 applies the throttle term only while armed; the throttle it scales
with is 0 when disarmed.)
"""
from __future__ import annotations

import re
from typing import Collection, Mapping

import numpy as np

from ..calibration import Calibration, canonical_form
from ..errors import InputError
from .mount_rotations import by_number

MG_PER_UT = 10.0
UT_PER_GAUSS = 100.0
#: CAL_MAG_COMP_TYP values (PX4): 0 off, 1 throttle, 2 battery_status instance 0's current,
#: 3 instance 1's (streamcal's ``battery2_current_a``).
PX4_COMP_CHANNELS = {1: "throttle", 2: "battery_current_a", 3: "battery2_current_a"}
#: PX4's current signal is in kA: g (µT/A) = −UT_PER_GAUSS · 0.001 · comp.
PX4_KA_PER_A = 0.001
#: COMPASS_MOTCT values (ArduPilot): 0 disabled, 1 throttle, 2 current.
MOTCT_CHANNELS = {1: "throttle", 2: "battery_current_a"}
#: Compass parameters of every instance (COMPASS_OFS_X, COMPASS_OFS2_X, …) and the shared ones.
COMPASS_PARAMS = re.compile(r"COMPASS_(?:(?:OFS|DIA|ODI|MOT)[23]?_[XYZ]|MOTCT|PRIMARY"
                            r"|(?:SCALE|ORIENT|DEV_ID|USE)[23]?|EXTERNAL|EXTERN[23]|PRIO[123]_ID)")
#: ArduPilot's orders of the compass corrections (``AP_Compass_Backend::correct_field``).
MOTOR_AFTER_MATRIX = "offsets, matrix, motor"
MOTOR_BEFORE_MATRIX = "offsets, motor, matrix"
#: The first release of each vehicle whose motor term comes after the matrix (the per-motor
#: compensation, ArduPilot pull request 7539, reached master early 2018). Sub 3.5–3.5.4
#: (2017–2019) came from a branch cut in April 2017, Sub 4.0 (March 2020) from master
#: (ArduSub release notes; Sub 3.4's AP_Compass_Backend adds the motor term before the
#: matrix); AntennaTracker 1.0 is of July 2016, 1.1 (2019) was branched from master
#: (AntennaTracker release notes).
_MOTOR_AFTER_MATRIX_FROM = {"copter": (3, 6), "plane": (3, 9), "rover": (3, 3), "sub": (4, 0),
                            "tracker": (1, 1)}
#: The first release of each vehicle with COMPASS_DIA/ODI (the onboard calibrator, 2015):
#: every ArduSub (its first release, 3.4, has them) and every AntennaTracker that writes a
#: DataFlash log (0.7.5, December 2015, on).
_MATRIX_FROM = {"copter": (3, 4), "plane": (3, 4), "rover": (3, 0), "sub": (3, 4),
                "tracker": (0, 0)}
FIRMWARE_VERSION = re.compile(r"(copter|plane|rover|sub|tracker)\S*\s+v?(\d+)\.(\d+)", re.I)
#: Per-compass parameter kinds (``AP_Compass`` var_info); MOTCT and PRIMARY are shared.
_PER_COMPASS = ("OFS", "DIA", "ODI", "MOT", "SCALE", "ORIENT", "DEV_ID", "USE", "EXTERNAL")
_SHARED = ("COMPASS_MOTCT", "COMPASS_PRIMARY", "AHRS_ORIENTATION")
#: The rotation parameter of an internal compass, which turns with the board: each firmware
#: ignores the compass's own one there (ArduPilot ``AP_Compass_Backend::rotate_field`` turns an
#: internal compass by AHRS_ORIENTATION, an external one by COMPASS_ORIENTn; PX4
#: ``sensor_calibration::Magnetometer`` by the board rotation SENS_BOARD_ROT when CAL_MAGn_ROT
#: is −1, internal). The board rotation turns the accelerometer and gyro too.
BOARD_ROTATION = {"ardupilot": "AHRS_ORIENTATION", "px4": "SENS_BOARD_ROT"}


def ardupilot_param(kind: str, instance: int = 0, axis: str | None = None) -> str:
    """ArduPilot's name of parameter ``kind`` of compass ``instance`` (from 0):
    ``("OFS", 1, "X")`` → ``COMPASS_OFS2_X``, ``("DEV_ID", 2)`` → ``COMPASS_DEV_ID3``,
    ``("EXTERNAL", 1)`` → ``COMPASS_EXTERN2``."""
    suffix = "" if instance == 0 else str(instance + 1)
    if kind == "EXTERNAL" and instance:
        kind = "EXTERN"
    return f"COMPASS_{kind}{suffix}" + (f"_{axis}" if axis else "")


def ardupilot_param_index(params: Mapping[str, float], instance: int) -> int:
    """The parameter set (0: COMPASS_OFS_*, 1: COMPASS_OFS2_*, …) of logged compass
    ``instance``. From ArduPilot 4.0 the logged instance is the compass's priority and its
    parameters are those whose COMPASS_DEV_IDn equals COMPASS_PRIO{instance+1}_ID
    (``Compass::_get_state_id``); without priorities they are the instance's own."""
    wanted = params.get(f"COMPASS_PRIO{instance + 1}_ID")
    if wanted:
        for n in range(3):
            if params.get(ardupilot_param("DEV_ID", n)) == wanted:
                return n
    return instance


def compass_rotation_param(meta: Mapping[str, str]) -> tuple[str, str] | None:
    """``(firmware, parameter)`` whose rotation turns an autopilot log's compass into the body
    frame, from the track's metadata: ArduPilot COMPASS_ORIENTn of the compass's parameter set,
    or AHRS_ORIENTATION when its COMPASS_EXTERNAL/EXTERNn is logged as 0 (internal); PX4
    CAL_MAGn_ROT, or SENS_BOARD_ROT when it is −1 (internal). None for other inputs."""
    if meta.get("input_format") == "ardupilot-dataflash":
        index = int(float(meta.get("compass_params_index", 0) or 0))
        external = meta.get(f"param.{ardupilot_param('EXTERNAL', index)}")
        internal = external is not None and float(external) == 0
        return "ardupilot", BOARD_ROTATION["ardupilot"] if internal else \
            ardupilot_param("ORIENT", index)
    if meta.get("input_format") == "px4-ulog" and meta.get("mag_cal_params"):
        own = meta["mag_cal_params"] + "ROT"
        internal = _param_value(meta, own) < 0
        return "px4", BOARD_ROTATION["px4"] if internal else own
    return None


def compass_params(params: Mapping[str, float], instance: int = 0) -> dict:
    """The logged parameters of compass ``instance`` and the shared ones, under their names."""
    names = [ardupilot_param(k, instance, a) for k in ("OFS", "DIA", "ODI", "MOT") for a in "XYZ"]
    names += [ardupilot_param(k, instance) for k in _PER_COMPASS[4:]] + list(_SHARED)
    return {n: float(params[n]) for n in names if n in params}


def ardupilot_matrix(params: Mapping[str, float], instance: int = 0) -> np.ndarray:
    """The symmetric soft-iron matrix ``S`` (3,3) of compass ``instance`` (identity when
    absent)."""
    dia = np.array([params.get(ardupilot_param("DIA", instance, a), 0.0) for a in "XYZ"],
                   dtype=float)
    if not np.any(dia):
        dia = np.ones(3)
    odi = [params.get(ardupilot_param("ODI", instance, a), 0.0) for a in "XYZ"]
    S = np.diag(dia)
    S[0, 1] = S[1, 0] = odi[0]
    S[0, 2] = S[2, 0] = odi[1]
    S[1, 2] = S[2, 1] = odi[2]
    scale = float(params.get(ardupilot_param("SCALE", instance), 0.0) or 1.0)
    return S * scale


def ardupilot_correction_order(firmware: str | None) -> tuple[str, str]:
    """(order, why) of the corrections the firmware named by ``firmware`` applies (its version
    text as logged, e.g. "ArduCopter V3.5.7 (b11c6af3)" or "APM:Rover v3.2.0"):
    :data:`MOTOR_BEFORE_MATRIX` for Copter < 3.6, Plane < 3.9, Rover < 3.3, Sub < 4.0,
    AntennaTracker < 1.1, else (also when the version or vehicle is unknown)
    :data:`MOTOR_AFTER_MATRIX`."""
    match = FIRMWARE_VERSION.search(firmware or "")
    if not match:
        return MOTOR_AFTER_MATRIX, "no ArduPilot version in the log: the current order assumed"
    vehicle, version = match.group(1).lower(), (int(match.group(2)), int(match.group(3)))
    first = _MOTOR_AFTER_MATRIX_FROM.get(vehicle)
    name = f"{vehicle.capitalize()} {version[0]}.{version[1]}"
    if first is None:
        return MOTOR_AFTER_MATRIX, f"{name}: the current order assumed"
    if version < _MATRIX_FROM[vehicle]:
        return MOTOR_BEFORE_MATRIX, (f"{name} has no COMPASS_DIA/ODI matrix: COMPASS_MOT is "
                                     "added with the offsets")
    if version < first:
        return MOTOR_BEFORE_MATRIX, (f"{name} adds COMPASS_MOT before the COMPASS_DIA/ODI matrix "
                                     f"(after it from {first[0]}.{first[1]})")
    return MOTOR_AFTER_MATRIX, f"{name} adds COMPASS_MOT after the COMPASS_DIA/ODI matrix"


def _check(params: Mapping[str, float], offsets: list[str], S: np.ndarray, matrix_params: str,
           field_uT: float, source: str) -> None:
    """InputError naming what is missing or unusable: an offset parameter, the field strength,
    an invertible matrix ``S``."""
    missing = [name for name in offsets if name not in params]
    if missing:
        raise InputError(f"{source}: no {', '.join(missing)} parameter: the autopilot's "
                         "calibration cannot be rebuilt")
    if not (np.isfinite(field_uT) and field_uT > 0):
        raise InputError(f"{source}: field strength must be a positive number of µT, "
                         f"got {field_uT!r}")
    if not np.all(np.isfinite(S)) or np.linalg.cond(S) > 1e6:
        raise InputError(f"{source}: {matrix_params} give a singular matrix")


def calibration_from_ardupilot(params: Mapping[str, float], field_uT: float,
                               source: str = "ArduPilot parameters",
                               instance: int = 0,
                               order: str = MOTOR_AFTER_MATRIX) -> Calibration:
    """Calibration equivalent to the ``COMPASS_*`` parameters of compass ``instance`` (from 0:
    COMPASS_OFS_*, …; 1: COMPASS_OFS2_*, …; 2: COMPASS_OFS3_*, …).

    Args:
        params: ``{name: value}`` as logged in PARM messages (the last value of each).
        field_uT: the field strength ArduPilot's corrected field has, µT (e.g. the median
            norm of the logged MAG field / 10); sets the scale of ``K``.
        source: said in the calibration's ``extra["source"]``.
        order: where the firmware adds the motor term (:func:`ardupilot_correction_order`);
            kept in ``extra["ardupilot_correction_order"]``.
    Raises :class:`InputError` if the offsets are missing or the matrix is not invertible.
    """
    if order not in (MOTOR_AFTER_MATRIX, MOTOR_BEFORE_MATRIX):
        raise InputError(f"{source}: unknown ArduPilot correction order {order!r}")
    S = ardupilot_matrix(params, instance)
    ofs = [ardupilot_param("OFS", instance, a) for a in "XYZ"]
    _check(params, ofs, S, f"{ardupilot_param('DIA', instance)}/ODI", field_uT, source)
    S_inv = np.linalg.inv(S)
    K, Q = canonical_form(field_uT * S_inv)
    offsets = np.array([params[n] for n in ofs], dtype=float)
    b = -offsets / MG_PER_UT
    model = ["hard_iron", "soft_iron"]
    effects = {}
    motct = int(params.get("COMPASS_MOTCT", 0) or 0)
    mot = np.array([params.get(ardupilot_param("MOT", instance, a), 0.0) for a in "XYZ"],
                   dtype=float)
    if motct in MOTCT_CHANNELS and np.any(mot):
        g = -(S_inv @ mot if order == MOTOR_AFTER_MATRIX else mot) / MG_PER_UT
        model.append("aux_interference")
        effects["aux_interference"] = {"channels": {MOTCT_CHANNELS[motct]: {
            "a0": 0.0, "g": [float(v) for v in g]}}}
    extra = {"source": source, "frame_rotation_Q": Q.tolist(),
             "ardupilot_correction_order": order,
             "note": "K is the canonical form of ArduPilot's symmetric matrix; calibrated "
                     "directions are ArduPilot's corrected field rotated by frame_rotation_Q"}
    return Calibration(K=K, b=b, model=tuple(model), effects=effects, field=float(field_uT),
                       method="ardupilot_params", unit="uT", extra=extra)


def px4_matrix(params: Mapping[str, float], prefix: str = "CAL_MAG0_") -> np.ndarray:
    """The symmetric matrix ``S`` (3,3) of PX4's calibration ``prefix`` (identity when absent)."""
    S = np.diag([params.get(f"{prefix}{a}SCALE", 1.0) for a in "XYZ"]).astype(float)
    odiag = [params.get(f"{prefix}{a}ODIAG", 0.0) for a in "XYZ"]
    S[0, 1] = S[1, 0] = odiag[0]
    S[0, 2] = S[2, 0] = odiag[1]
    S[1, 2] = S[2, 1] = odiag[2]
    return S


def px4_offsets(params: Mapping[str, float], prefix: str = "CAL_MAG0_") -> np.ndarray:
    """PX4's offsets ``o`` (3,) G of the calibration ``prefix`` (0 where absent)."""
    return np.array([params.get(f"{prefix}{a}OFF", 0.0) for a in "XYZ"], dtype=float)


def calibration_from_px4(params: Mapping[str, float], field_uT: float, prefix: str = "CAL_MAG0_",
                         compensation_in_readings: bool = False,
                         channels: Collection[str] = tuple(PX4_COMP_CHANNELS.values()),
                         source: str = "PX4 parameters",
                         rotation: np.ndarray | None = None) -> Calibration:
    """Calibration equivalent to PX4's ``prefix`` (``CAL_MAGn_``) parameters, on readings in µT.

    Args:
        params: ``{name: value}`` of the log's parameters (``CAL_MAGn_*``, ``CAL_MAG_COMP_TYP``).
        field_uT: the strength of PX4's corrected field, µT (e.g. the median norm of the
            calibrated topic × 100); sets the scale of ``K``.
        compensation_in_readings: the readings already carry PX4's power compensation (a
            calibrated topic whose S and o were undone): it is then not a term of the model.
        channels: the columns the readings come with; a compensation whose signal is not
            among them cannot be a term.
        source: said in the calibration's ``extra["source"]``.
        rotation: (3,3) the rotation PX4 turns the corrected readings by into the body frame
            (:func:`px4_rotation` of the track; None: the readings' frame is the body frame).
            It goes into ``extra["frame_rotation_Q"]``: the calibrated directions are then
            body-frame directions, as PX4's corrected field is.
    Raises :class:`InputError` if the offsets are missing or ``S`` is not invertible. Power
    compensation that cannot be a term (its signal not among ``channels``) is left out and said
    in ``extra["note"]``.
    """
    S = px4_matrix(params, prefix)
    _check(params, [f"{prefix}{a}OFF" for a in "XYZ"], S, f"{prefix}SCALE/ODIAG", field_uT, source)
    R = np.eye(3) if rotation is None else np.asarray(rotation, float)
    K, Q = canonical_form(field_uT * np.linalg.inv(S) @ R.T)
    b = UT_PER_GAUSS * px4_offsets(params, prefix)      # present: _check
    model, effects = ["hard_iron", "soft_iron"], {}
    notes = ["K is the canonical form of |F| S⁻¹ (PX4's rotation R only turns the directions); "
             "calibrated directions are PX4's corrected field (body frame) rotated by "
             "frame_rotation_Q"]
    comp_type = int(params.get("CAL_MAG_COMP_TYP", 0) or 0)
    comp = np.array([params.get(f"{prefix}{a}COMP", 0.0) for a in "XYZ"], dtype=float)
    if comp_type and np.any(comp):
        if compensation_in_readings:
            notes.append(f"power compensation (CAL_MAG_COMP_TYP={comp_type}) is already in the "
                         "readings (PX4 applied it before the calibration that was undone)")
        elif PX4_COMP_CHANNELS.get(comp_type) in channels:
            channel = PX4_COMP_CHANNELS[comp_type]
            g = -UT_PER_GAUSS * comp * (PX4_KA_PER_A if comp_type >= 2 else 1.0)
            model.append("aux_interference")
            effects["aux_interference"] = {"channels": {channel: {
                "a0": 0.0, "g": [float(v) for v in g]}}}
        else:
            signal = PX4_COMP_CHANNELS.get(comp_type, "a signal streamcal does not know")
            notes.append(f"power compensation CAL_MAG_COMP_TYP={comp_type} left out: its signal "
                         f"({signal}) is not a channel of the readings")
    extra = {"source": source, "frame_rotation_Q": Q.tolist(), "note": "; ".join(notes)}
    return Calibration(K=K, b=b, model=tuple(model), effects=effects, field=float(field_uT),
                       method="px4_params", unit="uT", extra=extra)


def px4_rotation(meta: Mapping[str, str]) -> np.ndarray | None:
    """The rotation (3,3) that takes a track's PX4 readings, once corrected, into the body frame
    (``body = R · corrected``), from the track's metadata: CAL_MAGn_ROT for an external
    compass, SENS_BOARD_ROT for an internal one (ROT = −1), when the readings are
    ``sensor_mag``'s (the sensor's own frame; PX4 rotates after its calibration). None when
    they are already in the body frame (a calibrated topic, another autopilot's log), or the
    rotation is the identity or not a numbered one (:mod:`.mount_rotations`)."""
    prefix = meta.get("mag_cal_params")
    if meta.get("input_format") != "px4-ulog" or not prefix \
            or not str(meta.get("mag_calibrated_by_px4", "")).startswith("no"):
        return None
    try:
        rot = int(float(meta.get(f"param.{prefix}ROT", -1)))
        number = rot if rot >= 0 else int(float(meta.get("param.SENS_BOARD_ROT", 0)))
    except ValueError:
        return None
    found = by_number(number, "px4")
    return None if found is None or found.name == "NONE" else np.array(found.matrix)


def compass_slot(metadata: dict) -> dict:
    """``{"compass_params_index": i, "compass_instance": j}`` of an autopilot log's compass:
    which parameter set the autopilot keeps its calibration in (ArduPilot 0 → ``COMPASS_OFS_*``,
    1 → ``COMPASS_OFS2_*``, 2 → ``COMPASS_OFS3_*``; PX4 ``CAL_MAGi_*``) and which compass it
    is; also ``motor_field_in_readings`` (:func:`motor_field_in_readings`) and, for ArduPilot,
    ``firmware`` (the log's version text, which ``export`` reads) and ``scale_in_force`` ``{"param", "value"}`` when its COMPASS_SCALEn is neither 0 nor 1 (it
    multiplies the corrected field); empty for a recording of one magnetometer."""
    out = {}
    if "compass_params_index" in metadata:
        out["compass_params_index"] = int(metadata["compass_params_index"])
    elif re.fullmatch(r"CAL_MAG\d+_", str(metadata.get("mag_cal_params", ""))):
        out["compass_params_index"] = int(metadata["mag_cal_params"][7:-1])
    if "compass_instance" in metadata:
        out["compass_instance"] = int(metadata["compass_instance"])
    in_readings = motor_field_in_readings(metadata, out.get("compass_params_index", 0))
    if in_readings:
        out["motor_field_in_readings"] = in_readings
    if metadata.get("input_format") == "ardupilot-dataflash":
        if metadata.get("firmware"):
            out["firmware"] = str(metadata["firmware"])
        name = ardupilot_param("SCALE", out.get("compass_params_index", 0))
        scale = _param_value(metadata, name)
        if scale not in (0.0, 1.0):   # 0: no scale factor (ArduPilot then applies none)
            out["scale_in_force"] = {"param": name, "value": scale}
    return out


def motor_field_in_readings(metadata: dict, index: int) -> str | None:
    """The motor-compensation parameters (``COMPASS_MOT2``, ``CAL_MAG1_xCOMP``) in force in the
    log whose compensation is *not* in the track's readings (the reader undid ArduPilot's MOfs;
    PX4's sensor_mag never had it), when they are non-zero; None otherwise. A calibration
    fitted on such readings without a motor term holds the mean motor field in its offsets, so
    loading it beside that compensation would remove the field twice."""
    if metadata.get("input_format") == "ardupilot-dataflash":
        names = [ardupilot_param("MOT", index, a) for a in "XYZ"]
        if _param_value(metadata, "COMPASS_MOTCT") in MOTCT_CHANNELS and \
                any(_param_value(metadata, n) for n in names):
            return names[0][:-2]
    elif metadata.get("input_format") == "px4-ulog" and \
            str(metadata.get("mag_calibrated_by_px4", "")).startswith("no"):
        names = [f"CAL_MAG{index}_{a}COMP" for a in "XYZ"]
        if _param_value(metadata, "CAL_MAG_COMP_TYP") and \
                any(_param_value(metadata, n) for n in names):
            return f"CAL_MAG{index}_xCOMP"
    return None


def _param_value(metadata: dict, name: str) -> float:
    """The logged parameter ``name`` (``param.NAME`` in a track's metadata) as a number; 0 when
    absent or not a number."""
    try:
        return float(metadata.get(f"param.{name}", 0.0))
    except ValueError:
        return 0.0

"""The compass rows of an ArduPilot DataFlash log undone to the raw field, and what was undone
(see :mod:`.dataflash`): ``raw = S⁻¹ (MAG − MOfs) − Ofs`` row by row, so a log read whole or in
pieces gives the same values.

Both take the parsed messages (``has``, ``array``, ``params``, ``path``) of the reader.
"""
from __future__ import annotations

import numpy as np

from ..errors import InputError
from .autopilot_cal import (MG_PER_UT, MOTOR_AFTER_MATRIX, MOTOR_BEFORE_MATRIX,
                            ardupilot_correction_order, ardupilot_matrix, ardupilot_param)


def mag_meta(msgs, name: str, params_of: int, meta: dict, mofs_nonzero: bool,
             ofs_sets: np.ndarray | None) -> None:
    """What :func:`mag_values` undoes, into ``meta``: ``mofs_nonzero`` whether any logged motor
    offset is not 0, ``ofs_sets`` the distinct logged OfsX/Y/Z rows (None: no such fields); the
    order of the corrections from ``meta["firmware"]``
    (:func:`~.autopilot_cal.ardupilot_correction_order`) as ``ardupilot_correction_order``."""
    order, why = ardupilot_correction_order(meta.get("firmware"))
    meta["ardupilot_correction_order"] = order
    meta["ardupilot_correction_order_from"] = why
    if msgs.has(name, "MOfsX", "MOfsY", "MOfsZ"):
        meta["mag_motor_offsets_undone"] = (
            f"{name}.MOfsX/Y/Z subtracted per sample ({order})" if mofs_nonzero
            else f"none ({name}.MOfs all 0)")
    else:
        meta["mag_motor_offsets_undone"] = f"could not: {name} has no MOfsX/Y/Z"
    S = ardupilot_matrix(msgs.params, params_of)
    dia, odi = ardupilot_param("DIA", params_of), ardupilot_param("ODI", params_of)[8:]
    if np.allclose(S, np.eye(3)):
        meta["mag_soft_iron_undone"] = f"none ({dia}/{odi} identity or not logged)"
    else:
        meta["mag_soft_iron_undone"] = f"inverse of the PARM {dia}/{odi} matrix applied" + (
            f" ({order}: {why})" if mofs_nonzero else "")
    ofs_names = [ardupilot_param("OFS", params_of, a) for a in "XYZ"]
    if ofs_sets is not None:
        shown = ",".join(f"{v:g}" for v in ofs_sets[0]) if len(ofs_sets) == 1 else \
            f"{len(ofs_sets)} different sets over the log"
        meta["mag_offsets_undone"] = (f"{name}.OfsX/Y/Z subtracted per sample (ArduPilot adds "
                                      f"them: logged = raw + Ofs); Ofs = {shown} mG")
    elif all(n in msgs.params for n in ofs_names):
        ofs = np.array([msgs.params[n] for n in ofs_names])
        meta["mag_offsets_undone"] = (f"PARM {ofs_names[0][:-2]}_X/Y/Z subtracted ({name} has no "
                                      f"OfsX/Y/Z; assumed constant) = "
                                      f"{','.join(f'{v:g}' for v in ofs)} mG")
    else:
        meta["mag_offsets_undone"] = (f"could not: {name} has no OfsX/Y/Z and no "
                                      f"{ofs_names[0][:-2]}_* parameter was logged; mx,my,mz are "
                                      "the corrected field")


def mag_values(msgs, name: str, params_of: int, logged: np.ndarray | None = None,
               order: str = MOTOR_AFTER_MATRIX) -> dict:
    """``{"mx","my","mz": (n,)}`` µT: the raw field of the rows of ``name`` in ``msgs`` (row by
    row, so a log read in pieces gives the same values): ``S⁻¹ (MAG − MOfs) − Ofs`` in the
    current ``order`` (:data:`~.autopilot_cal.MOTOR_AFTER_MATRIX`), ``S⁻¹ MAG − MOfs − Ofs``
    in the older one (:data:`~.autopilot_cal.MOTOR_BEFORE_MATRIX`)."""
    if logged is None:
        logged = np.column_stack([msgs.array(name, c) for c in ("MagX", "MagY", "MagZ")])
    raw = logged.copy()
    mofs = np.column_stack([msgs.array(name, c) for c in ("MOfsX", "MOfsY", "MOfsZ")]) \
        if msgs.has(name, "MOfsX", "MOfsY", "MOfsZ") else None
    if mofs is not None and order == MOTOR_AFTER_MATRIX:
        raw -= mofs
    S = ardupilot_matrix(msgs.params, params_of)
    if not np.allclose(S, np.eye(3)):
        try:
            raw = np.linalg.solve(S, raw.T).T
        except np.linalg.LinAlgError:
            raise InputError(f"{msgs.path}: the soft-iron matrix of the PARM "
                             f"{ardupilot_param('DIA', params_of)}/"
                             f"{ardupilot_param('ODI', params_of)[8:]} parameters is singular: "
                             "cannot undo it (damaged parameters?)") from None
    if mofs is not None and order == MOTOR_BEFORE_MATRIX:
        raw -= mofs
    ofs_names = [ardupilot_param("OFS", params_of, a) for a in "XYZ"]
    if msgs.has(name, "OfsX", "OfsY", "OfsZ"):
        raw -= np.column_stack([msgs.array(name, c) for c in ("OfsX", "OfsY", "OfsZ")])
    elif all(n in msgs.params for n in ofs_names):
        raw -= np.array([msgs.params[n] for n in ofs_names])
    mag = raw / MG_PER_UT
    return {"mx": mag[:, 0], "my": mag[:, 1], "mz": mag[:, 2]}

"""The local geomagnetic field as a physical reference (World Magnetic Model: WMM2025, and the
2010, 2015 and 2020 models for older recordings).

:func:`wmm_field` gives the expected total intensity (µT), inclination and declination (°) at a
place and date from ``pygeomag``, whose wheel ships the WMM coefficient files (no network at run
time; imported here only, when a location is given). :func:`compare` sets a fitted field
strength and a fitted dip (angle of the field below the horizontal plane, from the
accelerometer's gravity) beside them and words the differences.

Uncertainty of the model itself (WMM2025 error model, one sigma against observations):
0.138 µT in total intensity, 0.20° in inclination, √(0.26² + (5.417 µT / H)²)° in declination
(H the horizontal intensity); crustal anomalies and buildings (steel, cables) commonly add
more.
"""
from __future__ import annotations

import datetime as _dt
import math

#: Model used for current dates; the coefficient file inside ``pygeomag``.
MODEL = "WMM2025"
_COF = "wmm/WMM_2025.COF"
#: Earlier models ``pygeomag`` ships, for logs recorded before 2025: (name, file, first year);
#: each covers five years from its first.
_EARLIER = (("WMM2020", "wmm/WMM_2020.COF", 2020), ("WMM2015", "wmm/WMM_2015v2.COF", 2015),
            ("WMM2010", "wmm/WMM_2010.COF", 2010))
#: Hint thresholds: a field ratio off 1 by more than this (µT tracks) and a dip off by more
#: than this (degrees) are worth a sentence.
FIELD_HINT_FRACTION = 0.10
DIP_HINT_DEG = 2.0
NO_LOCATION = "no location given (--lat/--lon)"


def decimal_year(date: _dt.date) -> float:
    """``date`` (a day, taken at 00:00 UTC) as a decimal year (2025-07-02 → 2025.5)."""
    start = _dt.date(date.year, 1, 1)
    days = (_dt.date(date.year + 1, 1, 1) - start).days
    return date.year + (date - start).days / days


def parse_date(text: str | None) -> _dt.date:
    """``YYYY-MM-DD`` → date; today (UTC) when None."""
    from .errors import InputError

    if text is None:
        return _dt.datetime.now(_dt.timezone.utc).date()
    try:
        return _dt.date.fromisoformat(text)
    except ValueError:
        raise InputError(f"--date: expected YYYY-MM-DD, got {text!r}") from None


def wmm_field(lat: float, lon: float, alt_km: float = 0.0, date: _dt.date | None = None) -> dict:
    """Expected main field at geodetic ``lat``, ``lon`` (degrees, east positive), ``alt_km``
    above the WGS-84 ellipsoid, on ``date`` (default: today).

    Returns ``{"source", "lat", "lon", "alt_km", "date", "decimal_year", "intensity_uT",
    "inclination_deg", "declination_deg", "caution"}``; ``caution`` is true near the magnetic
    poles (horizontal field under 6 µT: declination unreliable).
    Raises :class:`~streamcal.errors.InputError` for a place or date outside the model.
    """
    from .errors import InputError

    lat, lon, alt_km = float(lat), float(lon), float(alt_km)
    if not (math.isfinite(lat) and -90.0 <= lat <= 90.0):
        raise InputError(f"--lat: expected degrees in -90..90, got {lat}")
    if not (math.isfinite(lon) and -180.0 <= lon <= 360.0):
        raise InputError(f"--lon: expected degrees in -180..360 (east positive), got {lon}")
    if not (math.isfinite(alt_km) and -1.0 <= alt_km <= 850.0):
        raise InputError(f"--alt-km: the model covers -1..850 km, got {alt_km}")
    date = date or parse_date(None)
    year = decimal_year(date)
    try:
        from pygeomag import GeoMag
    except ImportError:
        raise InputError("--lat/--lon need the pygeomag package (pip install pygeomag)") from None
    name, cof = next(((n, f) for n, f, first in _EARLIER if first <= year < first + 5),
                     _EARLIER[-1][:2] if year < _EARLIER[-1][2] else (MODEL, _COF))
    model = GeoMag(coefficients_file=cof)
    start, end = model.life_span
    if not start <= year < end:
        raise InputError(f"--date {date.isoformat()}: {name} covers {start:g} to {end:g}"
                         + (" (the earliest model shipped)" if year < start else ""))
    r = model.calculate(glat=lat, glon=lon, alt=alt_km, time=year, allow_date_outside_lifespan=True)
    return {"source": name, "lat": lat, "lon": lon, "alt_km": alt_km, "date": date.isoformat(),
            "decimal_year": round(year, 4), "intensity_uT": round(r.f / 1000.0, 4),
            "inclination_deg": round(r.i, 3), "declination_deg": round(r.d, 3),
            "caution": bool(r.h < 6000.0)}


def ned_field(ref: dict):
    """The field of :func:`wmm_field`'s result as a (3,) vector in µT, north-east-down."""
    import numpy as np

    f = ref["intensity_uT"]
    inc, dec = np.radians(ref["inclination_deg"]), np.radians(ref["declination_deg"])
    h = f * np.cos(inc)
    return np.array([h * np.cos(dec), h * np.sin(dec), f * np.sin(inc)])


def compare(ref: dict | None, fitted_field: float | None, unit: str,
            fitted_dip_deg: float | None = None, dip_spread_deg: float | None = None,
            reason: str = NO_LOCATION) -> dict:
    """The fitted field beside the reference ``ref`` (:func:`wmm_field`, or None).

    Args:
        fitted_field: fitted field strength in ``unit`` (the calibration's ``field`` or radius).
        unit: the sensor unit (``"uT"``, ``"counts"``…).
        fitted_dip_deg: median angle of the calibrated field below the plane normal to gravity
            (°, positive downward as WMM's inclination), None without an accelerometer.
        dip_spread_deg: its robust spread over samples (1.4826·MAD, °).
        reason: why there is no reference when ``ref`` is None.

    Returns the ``"reference_field"`` object of ``diagnose --json``: ``{"source": None,
    "reason"}`` without a reference, else the reference's figures plus ``fitted_field``,
    ``field_unit``, ``field_ratio`` (fitted / reference; for a counts track the scale in
    counts per µT, ``uT_per_count`` its inverse), ``field_difference_uT`` (µT tracks),
    ``fitted_dip_deg``, ``dip_difference_deg`` (fitted − inclination) and ``notes`` (sentences).
    """
    if ref is None:
        return {"source": None, "reason": reason}
    out = dict(ref)
    notes = []
    ref_f = ref["intensity_uT"]
    uT = unit in ("uT", "µT")
    out.update(fitted_field=_round(fitted_field), field_unit=unit, field_ratio=None,
               field_difference_uT=None, fitted_dip_deg=_round(fitted_dip_deg, 3),
               dip_spread_deg=_round(dip_spread_deg, 3), dip_difference_deg=None)
    if fitted_field is not None and math.isfinite(fitted_field) and fitted_field > 0:
        ratio = fitted_field / ref_f
        out["field_ratio"] = round(ratio, 5)
        if uT:
            diff = fitted_field - ref_f
            out["field_difference_uT"] = round(diff, 3)
            notes.append(f"fitted field {fitted_field:.2f} µT vs {MODEL} {ref_f:.2f} µT: "
                         f"{diff:+.2f} µT ({100 * (ratio - 1):+.1f} %)")
            if abs(ratio - 1) > FIELD_HINT_FRACTION:
                notes.append("hint: a field off the model by more than "
                             f"{100 * FIELD_HINT_FRACTION:.0f} % suggests a local disturbance "
                             "(steel, cables, a building) or a scale error of the sensor")
        else:
            out["uT_per_count"] = round(1.0 / ratio, 6)
            notes.append(f"fitted field {fitted_field:.5g} {unit} vs {MODEL} {ref_f:.2f} µT: "
                         f"scale {1 / ratio:.5g} µT per {unit.rstrip('s')} (if the local field "
                         f"is the model's)")
    if fitted_dip_deg is not None and math.isfinite(fitted_dip_deg):
        d = fitted_dip_deg - ref["inclination_deg"]
        out["dip_difference_deg"] = round(d, 3)
        spread = f" (spread {dip_spread_deg:.2f}°)" if dip_spread_deg is not None else ""
        notes.append(f"fitted dip {fitted_dip_deg:.2f}°{spread} vs inclination "
                     f"{ref['inclination_deg']:.2f}°: {d:+.2f}°")
        if abs(d) > DIP_HINT_DEG:
            notes.append(f"hint: a dip off by more than {DIP_HINT_DEG:g}° points at a "
                         "magnetometer–accelerometer misalignment or soft iron the model misses "
                         "(or a local disturbance); not a verdict")
    else:
        notes.append("no dip: the track has no accelerometer")
    if ref.get("caution"):
        notes.append("near a magnetic pole: the model's declination is unreliable here")
    out["notes"] = notes
    return out


def text_lines(cmp: dict) -> list[str]:
    """The comparison as indented text lines (first line names the reference)."""
    if cmp.get("source") is None:
        return [f"reference  none: {cmp['reason']}"]
    head = (f"reference  {cmp['source']} at {cmp['lat']:.4f}°, {cmp['lon']:.4f}°, "
            f"{cmp['alt_km']:g} km, {cmp['date']}: {cmp['intensity_uT']:.2f} µT, "
            f"inclination {cmp['inclination_deg']:.2f}°, declination "
            f"{cmp['declination_deg']:.2f}°")
    return [head] + ["           " + n for n in cmp["notes"]]


def dip_deg(field, down) -> tuple[float | None, float | None]:
    """Median and robust spread (1.4826·MAD) of the angle of ``field`` (N,3) below the plane
    normal to ``down`` (N,3 unit gravity directions, same frame), degrees; (None, None) when no
    finite pair is left."""
    import numpy as np

    f = np.asarray(field, dtype=float)
    g = np.asarray(down, dtype=float)
    nf = np.linalg.norm(f, axis=1)
    ng = np.linalg.norm(g, axis=1)
    ok = np.isfinite(nf) & np.isfinite(ng) & (nf > 0) & (ng > 0)
    if not ok.any():
        return None, None
    s = np.einsum("ij,ij->i", f[ok], g[ok]) / (nf[ok] * ng[ok])
    angle = np.degrees(np.arcsin(np.clip(s, -1.0, 1.0)))
    med = float(np.median(angle))
    return med, float(1.4826 * np.median(np.abs(angle - med)))


def _round(v, digits=4):
    if v is None:
        return None
    v = float(v)
    return round(v, digits) if math.isfinite(v) else None

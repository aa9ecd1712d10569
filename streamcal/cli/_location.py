"""``--lat/--lon/--alt-km/--date``: where and when the recording was made, for the local field
from the World Magnetic Model (:mod:`streamcal.geomag`), and the attitude reference as text."""
from __future__ import annotations


def add_location_options(p) -> None:
    g = p.add_argument_group("local field (World Magnetic Model)")
    g.add_argument("--lat", type=float, metavar="DEG",
                   help="latitude of the recording (degrees, north positive): compare the fitted "
                        "field and dip with the World Magnetic Model there")
    g.add_argument("--lon", type=float, metavar="DEG", help="longitude (degrees, east positive)")
    g.add_argument("--alt-km", type=float, default=0.0, metavar="KM",
                   help="height above the WGS-84 ellipsoid (default: %(default)s)")
    g.add_argument("--date", metavar="YYYY-MM-DD", help="date of the recording (default: today)")


def location_reference(args) -> dict | None:
    """The model field at ``args``' place (:func:`streamcal.geomag.wmm_field`), None when no
    location was given; one of --lat/--lon alone, a place or a date the model does not cover
    and a malformed --date (given alone too) are errors. A few milliseconds: commands call it
    before reading anything, so that a mistyped option is said at once."""
    from ..errors import InputError
    from ..geomag import parse_date, wmm_field

    lat, lon = getattr(args, "lat", None), getattr(args, "lon", None)
    date = getattr(args, "date", None)
    date = parse_date(date) if date is not None else None
    if lat is None and lon is None:
        return None
    if lat is None or lon is None:
        raise InputError("--lat and --lon go together (the place of the recording)")
    return wmm_field(lat, lon, args.alt_km, date)


def attitude_lines(out: dict) -> list[str]:
    """The attitude reference and the mounting found (``diagnose --json``'s
    ``attitude_reference`` and ``orientation``) as text lines; none when the log has neither."""
    lines = []
    a = out.get("attitude_reference")
    if a:
        h = a.get("heading_error_deg") or {}

        def pair(before, after, unit):
            if before is None:
                return "–"
            return f"{before:.3g} {unit}" + ("" if after is None else f" → {after:.3g} {unit}")
        lines += ["", f"attitude   the expected field (World Magnetic Model rotated by the logged "
                      f"attitude) against the calibration in force → streamcal's fit: rms "
                      f"{pair(a.get('rms_uT_before'), a.get('rms_uT_after'), 'µT')}, heading "
                      f"error rms {pair(h.get('rms_before'), h.get('rms_after'), '°')}, p95 "
                      f"{pair(h.get('p95_before'), h.get('p95_after'), '°')}"]
        if a.get("reason"):
            lines.append(f"           {a['reason']}")
        if a.get("caveat"):
            lines.append(f"           caveat: {a['caveat']}")
    o = out.get("orientation")
    if o:
        lines.append(f"mounting   {o.get('name')} (ArduPilot {o.get('ardupilot')}, PX4 "
                     f"{o.get('px4')})")
        chosen, configured = o.get("set") or {}, o.get("configured") or {}
        if chosen.get("param") and chosen.get("value") is not None \
                and chosen["value"] != configured.get("value"):
            from ..inputs.autopilot_cal import BOARD_ROTATION

            how = ("the board's rotation: it turns the accelerometer and gyro too, so only if "
                   "the whole board is mounted so" if chosen["param"] in BOARD_ROTATION.values()
                   else "`streamcal fit … --attitude` then `export` write it")
            lines.append(f"           set {chosen['param']} {chosen['value']} (now "
                         f"{configured.get('value')}; {how})")
    return lines


def beside_diagnosis(track, d) -> dict:
    """What ``diagnose`` says beside the diagnosis ``d`` of ``track``, at the place it used
    (``d.location``): ``{"reference_field", "attitude_reference"?, "orientation"?}``."""
    from ..diagnosis.reference_field import reference_field
    from ..fitting.attitude_reference import log_attitude_reference

    return {"reference_field": reference_field(track, d.calibration, d.location,
                                                gravity=d.gravity),
            **log_attitude_reference(track, d.location, d.calibration)}

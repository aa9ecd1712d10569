"""``--lat/--lon/--alt-km/--date``: where and when the recording was made, for the local field
from the World Magnetic Model (:mod:`streamcal.geomag`)."""
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
    location was given; one of --lat/--lon alone is an error."""
    from ..errors import InputError
    from ..geomag import parse_date, wmm_field

    lat, lon = getattr(args, "lat", None), getattr(args, "lon", None)
    if lat is None and lon is None:
        return None
    if lat is None or lon is None:
        raise InputError("--lat and --lon go together (the place of the recording)")
    return wmm_field(lat, lon, args.alt_km, parse_date(args.date))

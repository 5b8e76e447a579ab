"""The Earth's field from IGRF (ppigrf) at a place and date, as a calibration reference."""

from __future__ import annotations

import datetime as dt
import math

from rig.errors import UserInputError


def parse_igrf_site(text: str) -> tuple[float, float, float, dt.datetime]:
    """``"LAT,LON,ALT_KM,DATE"`` (degrees, degrees east, km above the ellipsoid, YYYY-MM-DD)."""
    parts = [p.strip() for p in text.split(",")]
    if len(parts) != 4:
        raise UserInputError(
            f"--igrf {text}: give LAT,LON,ALT_KM,DATE, e.g. --igrf 52.38,4.64,0.0,2026-11-25"
        )
    try:
        lat, lon, alt = (float(p) for p in parts[:3])
    except ValueError:
        raise UserInputError(f"--igrf {text}: LAT, LON and ALT_KM must be numbers") from None
    if not (math.isfinite(lat) and -90.0 <= lat <= 90.0):
        raise UserInputError(f"--igrf: latitude {parts[0]} is outside -90..90 degrees")
    if not (math.isfinite(lon) and -180.0 <= lon <= 360.0):
        raise UserInputError(f"--igrf: longitude {parts[1]} is outside -180..360 degrees east")
    if not (math.isfinite(alt) and -1.0 <= alt <= 2000.0):
        raise UserInputError(f"--igrf: altitude {parts[2]} km is outside -1..2000 km")
    try:
        date = dt.datetime.strptime(parts[3], "%Y-%m-%d")
    except ValueError:
        raise UserInputError(f"--igrf: date {parts[3]!r} is not YYYY-MM-DD") from None
    if not 1900 <= date.year <= 2030:
        raise UserInputError(f"--igrf: {parts[3]} is outside IGRF's years 1900-2030")
    return lat, lon, alt, date


def igrf_magnitude_ut(lat_deg: float, lon_deg: float, alt_km: float, date: dt.datetime) -> float:
    """|B| (uT) of IGRF at a geodetic place and date."""
    import numpy as np
    import ppigrf

    be, bn, bu = ppigrf.igrf(lon_deg, lat_deg, alt_km, date)
    return float(np.sqrt(np.ravel(be)[0] ** 2 + np.ravel(bn)[0] ** 2 + np.ravel(bu)[0] ** 2) / 1000)

"""Orbit replay: the field a satellite sees, from a TLE (sgp4) and IGRF (ppigrf), in its body frame.

Frames: sgp4 gives TEME; ECEF = R_z(-GMST) TEME (polar motion and nutation ignored, below 1e-5
rad); geodetic coordinates on WGS-84; IGRF gives east/north/up components, rotated back to the
inertial frame and then into the body frame of the chosen attitude. The sun direction is the
low-precision solar position of the Astronomical Almanac; eclipse uses a cylindrical shadow.
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]
R_EARTH_KM = 6378.137
WGS84_F = 1 / 298.257223563
FACES = {
    "+x": (1, 0, 0),
    "-x": (-1, 0, 0),
    "+y": (0, 1, 0),
    "-y": (0, -1, 0),
    "+z": (0, 0, 1),
    "-z": (0, 0, -1),
}


@dataclass(frozen=True)
class OrbitTrack:
    """Per sample: orbit time offset (s), body-frame field (uT), sunlit flag, sun direction (body)."""

    t_orbit_s: Array
    field_body_ut: Array
    sunlit: npt.NDArray[np.bool_]
    sun_body: Array


def _rz(angle: Array) -> Array:
    c, s = np.cos(angle), np.sin(angle)
    out = np.zeros((angle.size, 3, 3))
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1], out[:, 2, 2] = c, -s, s, c, 1.0
    return out


def geodetic(r_ecef_km: Array) -> tuple[Array, Array, Array]:
    """Latitude, longitude (deg) and height (km) on WGS-84 (Bowring's iteration)."""
    x, y, z = r_ecef_km.T
    a = R_EARTH_KM
    e2 = WGS84_F * (2 - WGS84_F)
    lon = np.arctan2(y, x)
    p = np.hypot(x, y)
    lat = np.arctan2(z, p * (1 - e2))

    def height(lat: Array) -> tuple[Array, Array]:
        n = a / np.sqrt(1 - e2 * np.sin(lat) ** 2)
        # valid at the poles too (no division by cos(lat))
        return n, p * np.cos(lat) + (z + e2 * n * np.sin(lat)) * np.sin(lat) - n

    for _ in range(5):
        n, h = height(lat)
        lat = np.arctan2(z, p * (1 - e2 * n / (n + h)))
    _, h = height(lat)
    return np.degrees(lat), np.degrees(lon), h


def sun_direction_eci(jd: Array) -> Array:
    """Unit vectors to the sun (mean equator and equinox of date, good to 0.01 deg)."""
    n = jd - 2451545.0
    L = np.radians(280.460 + 0.9856474 * n)
    g = np.radians(357.528 + 0.9856003 * n)
    lam = L + np.radians(1.915) * np.sin(g) + np.radians(0.020) * np.sin(2 * g)
    eps = np.radians(23.439 - 4e-7 * n)
    return np.column_stack([np.cos(lam), np.cos(eps) * np.sin(lam), np.sin(eps) * np.sin(lam)])


def attitude_matrices(kind: str, r: Array, v: Array, t_s: Array, tumble_deg_s: float) -> Array:
    """Rows = body axes in the inertial frame, per sample."""
    n = r.shape[0]
    if kind == "inertial":
        return np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    if kind == "nadir":
        z = -r / np.linalg.norm(r, axis=1)[:, None]
        y = np.cross(z, v)
        y /= np.linalg.norm(y, axis=1)[:, None]
        x = np.cross(y, z)
        return np.stack([x, y, z], axis=1)
    if kind == "tumbling":
        # A spin about one body axis while that axis precesses (as a tumbling, slightly
        # asymmetric body does): the body sees the field from every direction within minutes.
        def spin(axis: Array, ang: Array) -> Array:
            axis = axis / np.linalg.norm(axis)
            k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
            s_, c_ = np.sin(ang)[:, None, None], np.cos(ang)[:, None, None]
            return np.asarray(np.eye(3) + s_ * k + (1 - c_) * (k @ k), dtype=np.float64)

        w = np.radians(tumble_deg_s) * t_s
        rot = spin(np.array([0.0, 0.0, 1.0]), 0.37 * w) @ spin(np.array([0.3, 0.5, 0.8]), w)
        return np.transpose(rot, (0, 2, 1))
    raise ValueError(f"unknown attitude {kind!r}: use inertial, nadir or tumbling")


def orbit_track(tle1: str, tle2: str, start: dt.datetime, t_orbit_s: Array, attitude: str,
                tumble_deg_s: float = 2.0) -> OrbitTrack:  # fmt: skip
    """Field and sun in the body frame along the orbit at ``start + t_orbit_s``."""
    from sgp4.api import Satrec, jday

    sat = Satrec.twoline2rv(tle1.strip(), tle2.strip())
    jd0, fr0 = jday(
        start.year,
        start.month,
        start.day,
        start.hour,
        start.minute,
        start.second + start.microsecond / 1e6,
    )
    fr = fr0 + t_orbit_s / 86400.0
    jd = np.full(t_orbit_s.shape, jd0)
    err, r, v = sat.sgp4_array(jd, fr)
    if np.any(err != 0):
        raise ValueError(
            f"sgp4 could not propagate the TLE (error code {int(err[err != 0][0])}): check the TLE and epoch"
        )
    return _track_from_states(r, v, jd, fr, start, t_orbit_s, attitude, tumble_deg_s)


def circular_orbit_track(altitude_km: float, inclination_deg: float, start: dt.datetime,
                         t_orbit_s: Array, attitude: str = "nadir",
                         raan_deg: float = 0.0) -> OrbitTrack:  # fmt: skip
    """Like :func:`orbit_track` for an ideal circular orbit (two-body, no TLE needed).

    ``nadir`` attitude is Earth pointing: body z to nadir, y along the negative orbit normal, so
    the body turns about y once per orbit.
    """
    from sgp4.api import jday

    mu_km3_s2 = 398600.4418
    a_km = R_EARTH_KM + altitude_km
    n_rad_s = math.sqrt(mu_km3_s2 / a_km**3)
    inc, raan = math.radians(inclination_deg), math.radians(raan_deg)
    arg = n_rad_s * t_orbit_s
    p_hat = np.array([math.cos(raan), math.sin(raan), 0.0])
    q_hat = np.array(
        [-math.sin(raan) * math.cos(inc), math.cos(raan) * math.cos(inc), math.sin(inc)]
    )
    r = a_km * (np.cos(arg)[:, None] * p_hat + np.sin(arg)[:, None] * q_hat)
    v = a_km * n_rad_s * (-np.sin(arg)[:, None] * p_hat + np.cos(arg)[:, None] * q_hat)
    jd0, fr0 = jday(start.year, start.month, start.day, start.hour, start.minute,
                    start.second + start.microsecond / 1e6)  # fmt: skip
    jd = np.full(t_orbit_s.shape, jd0)
    return _track_from_states(r, v, jd, fr0 + t_orbit_s / 86400.0, start, t_orbit_s, attitude, 2.0)


def _track_from_states(r: Array, v: Array, jd: Array, fr: Array, start: dt.datetime,
                       t_orbit_s: Array, attitude: str, tumble_deg_s: float) -> OrbitTrack:  # fmt: skip
    """Field and sun in the body frame from inertial (TEME) positions and velocities (km, km/s)."""
    import ppigrf
    from sgp4.propagation import gstime

    gmst = np.array([gstime(a + b) for a, b in zip(jd, fr, strict=True)])
    r_ecef = np.einsum("nij,nj->ni", np.transpose(_rz(gmst), (0, 2, 1)), r)
    lat, lon, h = geodetic(r_ecef)
    # IGRF at decimated points (it varies over minutes), interpolated to every sample
    step = max(1, int(len(t_orbit_s) / 600))
    idx = np.unique(np.r_[np.arange(0, len(t_orbit_s), step), len(t_orbit_s) - 1])
    be, bn, bu = ppigrf.igrf(lon[idx], lat[idx], h[idx], start)
    enu = np.column_stack([np.ravel(be), np.ravel(bn), np.ravel(bu)]) / 1000.0  # nT -> uT
    enu = np.column_stack([np.interp(t_orbit_s, t_orbit_s[idx], enu[:, i]) for i in range(3)])
    la, lo = np.radians(lat), np.radians(lon)
    east = np.column_stack([-np.sin(lo), np.cos(lo), np.zeros_like(lo)])
    north = np.column_stack([-np.sin(la) * np.cos(lo), -np.sin(la) * np.sin(lo), np.cos(la)])
    up = np.column_stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)])
    b_ecef = enu[:, :1] * east + enu[:, 1:2] * north + enu[:, 2:3] * up
    b_eci = np.einsum("nij,nj->ni", _rz(gmst), b_ecef)
    att = attitude_matrices(attitude, r, v, t_orbit_s, tumble_deg_s)
    b_body = np.einsum("nij,nj->ni", att, b_eci)
    sun = sun_direction_eci(jd + fr)
    along = np.einsum("ij,ij->i", r, sun)
    perp = np.linalg.norm(r - along[:, None] * sun, axis=1)
    sunlit = ~((along < 0) & (perp < R_EARTH_KM))
    sun_body = np.einsum("nij,nj->ni", att, sun)
    return OrbitTrack(t_orbit_s, b_body, sunlit, sun_body)


def panel_current(track: OrbitTrack, face: str, max_a: float) -> Array:
    """Current of a body-mounted solar panel: ``max_a cos(incidence)`` in sunlight, 0 in eclipse."""
    normal = np.array(FACES[face], float)
    return np.asarray(max_a * np.clip(track.sun_body @ normal, 0.0, None) * track.sunlit)


def validate_orbit(params: Mapping[str, Any], where: str, max_setpoints: int) -> str | None:
    """What is wrong with a step's ``tle``, ``start`` and ``duration_s`` x ``rate_hz`` (one
    sentence naming ``where`` and the fix), None when nothing is."""
    tle = params["tle"]
    if not isinstance(tle, list) or len(tle) != 2:
        return f"{where}: 'tle' must be the two TLE lines"
    try:
        parse_start(str(params["start"]))
    except ValueError as exc:
        return f"{where}: {exc}"
    setpoints = float(params["duration_s"]) * float(params["rate_hz"])
    if setpoints > max_setpoints:
        return (f"{where}: duration_s x rate_hz makes {setpoints:.0f} field set-points, more than"
                f" {max_setpoints} (MAX_FIELD_SETPOINTS_PER_STEP): lower the rate or split the"
                " step into several")  # fmt: skip
    return None


def parse_start(text: str) -> dt.datetime:
    """ISO date-time (UTC)."""
    try:
        value = dt.datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError:
        raise ValueError(
            f"start {text!r} is not an ISO date-time like 2026-06-01T12:00:00Z"
        ) from None
    return value.astimezone(dt.UTC).replace(tzinfo=None) if value.tzinfo else value


__all__ = [
    "FACES",
    "OrbitTrack",
    "math",
    "orbit_track",
    "panel_current",
    "parse_start",
    "validate_orbit",
]

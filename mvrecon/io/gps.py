"""GPS positions in image EXIF, and the local metric frame they are compared in.

A drone or phone writes its position into each photo's EXIF GPS block (latitude, longitude in degrees, minutes,
seconds with N/S and E/W references; altitude in metres with an above/below sea level flag). `read_gps` reads it
from the file's header without decoding pixels; `gps_exif` builds the block for a written image (the scene
catalog's drone views). Positions are compared in metres: `to_enu` turns WGS84 latitude/longitude/altitude into
east/north/up about an origin (through earth-centred coordinates, exact at any distance), `from_enu` back.
"""

from pathlib import Path

import numpy as np
from PIL import Image

from .images import header_exif

_GPS_IFD = 0x8825  # the EXIF pointer to the GPS block
# GPS tags (EXIF 2.3, section 4.6.6)
_LAT_REF, _LAT, _LON_REF, _LON, _ALT_REF, _ALT = 1, 2, 3, 4, 5, 6
_H_ERROR = 31  # GPSHPositioningError: the horizontal accuracy in metres (EXIF 2.31)

_A = 6378137.0  # WGS84 semi-major axis, metres
_E2 = 6.69437999014e-3  # WGS84 first eccentricity squared


def _dms(value: float) -> tuple[float, float, float]:
    """Degrees, minutes, seconds of a non-negative angle in degrees (seconds to 1e-4, about 3 mm)."""
    seconds = round(abs(value) * 3600.0, 4)
    degrees, rest = divmod(seconds, 3600.0)
    minutes, seconds = divmod(rest, 60.0)
    return float(degrees), float(minutes), round(seconds, 4)


def gps_exif(lat: float, lon: float, alt: float, exif: Image.Exif | None = None,
             accuracy: float | None = None) -> Image.Exif:
    """An EXIF block (a new one, or `exif` added to) carrying the position (and the horizontal `accuracy` in
    metres when given), for Pillow's `save(..., exif=)`."""
    exif = Image.Exif() if exif is None else exif
    exif[_GPS_IFD] = {
        0: b"\x02\x03\x00\x00",  # GPSVersionID
        _LAT_REF: "N" if lat >= 0 else "S",
        _LAT: _dms(lat),
        _LON_REF: "E" if lon >= 0 else "W",
        _LON: _dms(lon),
        _ALT_REF: 0 if alt >= 0 else 1,
        _ALT: round(abs(float(alt)), 3),
        **({} if accuracy is None else {_H_ERROR: round(float(accuracy), 3)}),
    }
    return exif


def _degrees(dms) -> float:
    d, m, s = (float(x) for x in dms)
    return d + m / 60.0 + s / 3600.0


def read_gps(path: Path | str) -> tuple[float, float, float] | None:
    """(latitude, longitude, altitude) in degrees and metres from an image's EXIF, or None when it has no
    complete position (no GPS block, or no latitude/longitude). A missing altitude reads as 0: a position on
    the ground plane is still a useful prior for choosing pairs."""
    fix = read_gps_fix(path)
    return None if fix is None else fix[0]


def read_gps_fix(path: Path | str) -> tuple[tuple[float, float, float], float | None] | None:
    """`read_gps`'s position and the horizontal accuracy the receiver wrote (GPSHPositioningError, metres;
    None when absent or unreadable), or None without a position."""
    try:
        with Image.open(path) as im:
            gps = header_exif(im).get_ifd(_GPS_IFD)
    except (OSError, SyntaxError, ValueError):
        return None
    try:
        lat, lon = _degrees(gps[_LAT]), _degrees(gps[_LON])
    except (KeyError, TypeError, ValueError, ZeroDivisionError):
        return None
    if not (np.isfinite(lat) and np.isfinite(lon)):
        return None
    lat = -lat if str(gps.get(_LAT_REF, "N")).upper().startswith("S") else lat
    lon = -lon if str(gps.get(_LON_REF, "E")).upper().startswith("W") else lon
    try:
        alt = float(gps.get(_ALT, 0.0))
    except (TypeError, ValueError, ZeroDivisionError):
        alt = 0.0
    ref = gps.get(_ALT_REF, 0)
    below = ref in (1, b"\x01") or (isinstance(ref, bytes) and ref[:1] == b"\x01")
    try:
        accuracy = float(gps[_H_ERROR]) if _H_ERROR in gps else None
    except (TypeError, ValueError, ZeroDivisionError):
        accuracy = None
    if accuracy is not None and not (np.isfinite(accuracy) and accuracy > 0):
        accuracy = None
    return (lat, lon, -alt if below else alt), accuracy


def implausible_position(lat: float, lon: float, alt: float) -> str | None:
    """Why a WGS84 position cannot be a camera's (out of range, the (0, 0) of an unset receiver, a sentinel
    altitude such as -9999), or None when it can be."""
    if not all(np.isfinite([lat, lon, alt])):
        return "not a number"
    if abs(lat) > 90 or abs(lon) > 180:
        return f"latitude {lat:g}, longitude {lon:g} out of range"
    if lat == 0 and lon == 0:
        return "latitude and longitude 0, 0 (a receiver without a fix)"
    if not -500.0 <= alt <= 12000.0:
        return f"altitude {alt:g} m (outside -500..12000 m)"
    return None


def _ecef(lla: np.ndarray) -> np.ndarray:
    lat, lon, alt = np.radians(lla[:, 0]), np.radians(lla[:, 1]), lla[:, 2]
    n = _A / np.sqrt(1.0 - _E2 * np.sin(lat) ** 2)
    return np.stack([(n + alt) * np.cos(lat) * np.cos(lon),
                     (n + alt) * np.cos(lat) * np.sin(lon),
                     (n * (1.0 - _E2) + alt) * np.sin(lat)], axis=1)


def _enu_axes(origin: np.ndarray) -> np.ndarray:
    """Rows: east, north, up at `origin` (lat, lon in degrees), in earth-centred coordinates."""
    lat, lon = np.radians(origin[0]), np.radians(origin[1])
    return np.array([[-np.sin(lon), np.cos(lon), 0.0],
                     [-np.sin(lat) * np.cos(lon), -np.sin(lat) * np.sin(lon), np.cos(lat)],
                     [np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)]])


def to_enu(lla: np.ndarray, origin: np.ndarray | None = None) -> np.ndarray:
    """East/north/up metres (N, 3) of WGS84 positions `lla` (N, 3: degrees, degrees, metres) about `origin`
    (default: the first position)."""
    lla = np.atleast_2d(np.asarray(lla, float))
    origin = lla[0] if origin is None else np.asarray(origin, float)
    return (_ecef(lla) - _ecef(origin[None])) @ _enu_axes(origin).T


def from_enu(enu: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """WGS84 positions (N, 3) of east/north/up metres about `origin`: the inverse of `to_enu`."""
    enu = np.atleast_2d(np.asarray(enu, float))
    origin = np.asarray(origin, float)
    return from_ecef(_ecef(origin[None]) + enu @ _enu_axes(origin))


def to_ecef(lla: np.ndarray) -> np.ndarray:
    """Earth-centred, earth-fixed metres (N, 3) of WGS84 positions (N, 3: degrees, degrees, metres)."""
    return _ecef(np.atleast_2d(np.asarray(lla, float)))


def enu_to_ecef(origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) with ecef = R @ enu + t for east/north/up metres about `origin` (lat, lon, alt)."""
    origin = np.asarray(origin, float)
    return _enu_axes(origin).T, _ecef(origin[None])[0]


def from_ecef(xyz: np.ndarray) -> np.ndarray:
    """WGS84 positions (N, 3) of earth-centred metres (Bowring's closed form, sub-millimetre near the earth's
    surface)."""
    xyz = np.atleast_2d(np.asarray(xyz, float))
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    b = _A * np.sqrt(1.0 - _E2)
    ep2 = (_A**2 - b**2) / b**2
    p = np.hypot(x, y)
    theta = np.arctan2(z * _A, p * b)
    lat = np.arctan2(z + ep2 * b * np.sin(theta) ** 3, p - _E2 * _A * np.cos(theta) ** 3)
    n = _A / np.sqrt(1.0 - _E2 * np.sin(lat) ** 2)
    alt = p / np.cos(lat) - n
    return np.stack([np.degrees(lat), np.degrees(np.arctan2(y, x)), alt], axis=1)

"""Camera position priors: from the images' EXIF GPS, or from a CSV file of surveyed positions.

A prior is what COLMAP's `pose_priors` table holds: a position, its 3x3 covariance and the coordinate system it is
in (`WGS84`: latitude, longitude in degrees and altitude in metres; `CARTESIAN`: x, y, z metres in a local frame
without a place on the earth). The covariance is in metres squared along east, north, up (x, y, z for CARTESIAN).

The CSV file (`--pose-priors FILE`) has a header row naming its columns, `name` first, then either `lat,lon,alt`
or `x,y,z`, and optionally `sigma` (metres, every axis) or `sigma_h,sigma_v` (horizontal, vertical). x, y, z are
in the frame a first comment line names: `# frame: enu LAT LON ALT` (metres east, north, up of that origin),
`# frame: ecef` (earth-centred metres), or `# frame: local` (any metric frame, the default: the model then comes out
in it, without geographic coordinates). Lines starting with `#` are comments; blank lines are skipped.
"""

import csv
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from .gps import from_ecef, from_enu, implausible_position, read_gps_fix

log = logging.getLogger(__name__)

WGS84, CARTESIAN = "WGS84", "CARTESIAN"
COORDINATE_SYSTEMS = {"UNDEFINED": -1, WGS84: 0, CARTESIAN: 1}  # pycolmap 4.2's PosePriorCoordinateSystem
# the accuracy of a GPS fix whose EXIF gives none: a phone or drone receiver's usual 5 m horizontally; altitude
# from GPS is about twice as uncertain
DEFAULT_SIGMA_H, DEFAULT_SIGMA_V = 5.0, 10.0


@dataclass(kw_only=True)
class PosePrior:
    """A camera centre prior: `position` in `coordinate_system`, `covariance` (3x3, metres squared)."""

    position: np.ndarray
    covariance: np.ndarray
    coordinate_system: str = WGS84

    @property
    def sigmas(self) -> np.ndarray:
        """Standard deviations (metres) along east, north, up (or x, y, z)."""
        return np.sqrt(np.clip(np.diag(self.covariance), 1e-12, None))


def covariance(sigma_h: float, sigma_v: float) -> np.ndarray:
    return np.diag([sigma_h**2, sigma_h**2, sigma_v**2]).astype(float)


def default_covariance() -> np.ndarray:
    return covariance(DEFAULT_SIGMA_H, DEFAULT_SIGMA_V)


def exif_priors(folder: Path | str, names: list[str]) -> dict[str, PosePrior]:
    """name -> the prior of each image whose EXIF has a plausible GPS position, with the receiver's horizontal
    accuracy when it wrote one (vertical: twice that) and DEFAULT_SIGMA_H/V otherwise. Images whose position is
    impossible (`gps.implausible_position`) are named in one warning and get no prior."""
    out, bad = {}, []
    for name in names:
        fix = read_gps_fix(Path(folder) / name)
        if fix is None:
            continue
        (lat, lon, alt), accuracy = fix
        why = implausible_position(lat, lon, alt)
        if why is not None:
            bad.append(f"{name} ({why})")
            continue
        sigma_h = accuracy if accuracy is not None else DEFAULT_SIGMA_H
        sigma_v = 2.0 * accuracy if accuracy is not None else DEFAULT_SIGMA_V
        out[name] = PosePrior(position=np.array([lat, lon, alt], float), covariance=covariance(sigma_h, sigma_v))
    if bad:
        log.warning("%s: GPS position ignored for %d image(s) whose EXIF position is impossible: %s", folder,
                    len(bad), "; ".join(bad[:10]) + (f"; and {len(bad) - 10} more" if len(bad) > 10 else ""))
    return out


def prior_position(frame: str, xyz: np.ndarray, origin: np.ndarray | None, where: str) -> tuple[np.ndarray, str]:
    """(position, coordinate system) of a prior given in `frame`: 'wgs84' (lat, lon, alt), 'enu' (metres east,
    north, up of `origin`) and 'ecef' become WGS84 latitude, longitude and altitude; any other frame is CARTESIAN
    metres as given. A WGS84 position off the earth raises InputError `where: impossible position: why`."""
    if frame == "enu":
        xyz = from_enu(np.asarray(xyz, float)[None], origin)[0]
    elif frame == "ecef":
        xyz = from_ecef(np.asarray(xyz, float)[None])[0]
    elif frame != "wgs84":
        return np.asarray(xyz, float), CARTESIAN
    why = implausible_position(*xyz)
    if why is not None:
        raise InputError(f"{where}: impossible position: {why}")
    return np.asarray(xyz, float), WGS84


def enu_origin(path: Path, words: list[str], what: str) -> np.ndarray:
    """The ENU origin (lat, lon, alt) given as three words after `what` in a file's frame statement; InputError
    naming the file when they are not three numbers or not a place on the earth."""
    try:
        origin = np.array([float(w) for w in words], float)
    except ValueError:
        origin = np.zeros(0)
    if origin.shape != (3,) or implausible_position(*origin):
        raise InputError(f"{path}: {what} needs the origin as LAT LON ALT (degrees, metres)")
    return origin


def _frame(path: Path, first_comment: str | None) -> tuple[str, np.ndarray | None]:
    """('wgs84' | 'enu' | 'ecef' | 'local', the ENU origin or None) named by a `# frame: ...` comment."""
    if first_comment is None or not first_comment.lower().startswith("frame:"):
        return "local", None
    words = first_comment.split(":", 1)[1].split()
    kind = words[0].lower() if words else ""
    if kind == "enu":
        return "enu", enu_origin(path, words[1:], "'# frame: enu'")
    if kind in ("ecef", "local", "wgs84") and len(words) == 1:
        return kind, None
    raise InputError(f"{path}: unknown frame {first_comment!r}; use '# frame: enu LAT LON ALT', 'ecef' or 'local'")


def read_priors_csv(path: Path | str, names: list[str] | None = None) -> dict[str, PosePrior]:
    """name -> prior of each row of a pose-prior CSV file (the module docstring has the format). A malformed
    file, an impossible position, or (given `names`, the images there are) rows naming images that are not
    there raise InputError naming the file and the rows."""
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8-sig").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read the pose priors: {exc}") from None
    comments = [ln.lstrip("#").strip() for ln in lines if ln.strip().startswith("#")]
    frame, origin = _frame(path, next((c for c in comments if c.lower().startswith("frame:")), None))
    rows = [r for r in csv.reader(ln for ln in lines if ln.strip() and not ln.strip().startswith("#"))]
    if not rows:
        raise InputError(f"{path}: no header row (name,lat,lon,alt or name,x,y,z, then optional sigma columns)")
    header = [h.strip().lower() for h in rows[0]]
    geo = header[1:4] == ["lat", "lon", "alt"]
    if not header or header[0] != "name" or not (geo or header[1:4] == ["x", "y", "z"]):
        raise InputError(f"{path}: header {','.join(rows[0])!r} must start name,lat,lon,alt or name,x,y,z")
    if geo and frame not in ("local", "wgs84"):
        raise InputError(f"{path}: lat,lon,alt columns with '# frame: {frame}'; the frame comment is for x,y,z")
    extra = header[4:]
    if extra not in ([], ["sigma"], ["sigma_h", "sigma_v"]):
        raise InputError(f"{path}: columns after the position must be sigma, or sigma_h,sigma_v; got "
                         f"{','.join(extra)!r}")
    out: dict[str, PosePrior] = {}
    for k, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise InputError(f"{path}: data row {k - 1} has {len(row)} fields, the header {len(header)}")
        name = row[0].strip()
        try:
            values = np.array([float(v) for v in row[1:]], float)
        except ValueError:
            raise InputError(f"{path}: data row {k - 1} ({name}): a position or sigma is not a number") from None
        pos = values[:3]
        sig = values[3:]
        sigma_h, sigma_v = (DEFAULT_SIGMA_H, DEFAULT_SIGMA_V) if len(sig) == 0 else (
            (sig[0], sig[0]) if len(sig) == 1 else (sig[0], sig[1]))
        if not (np.all(np.isfinite(pos)) and sigma_h > 0 and sigma_v > 0 and np.isfinite([sigma_h, sigma_v]).all()):
            raise InputError(f"{path}: data row {k - 1} ({name}): positions must be finite, sigmas positive")
        if name in out:
            raise InputError(f"{path}: {name} is listed twice")
        lla, system = prior_position("wgs84" if geo else ("local" if frame == "wgs84" else frame), pos, origin,
                                     f"{path}: data row {k - 1} ({name})")
        out[name] = PosePrior(position=np.asarray(lla, float), covariance=covariance(sigma_h, sigma_v),
                              coordinate_system=system)
    if not out:
        raise InputError(f"{path}: no positions (only a header)")
    if names is not None:
        unknown = sorted(set(out) - set(names))
        if unknown:
            shown = ", ".join(unknown[:10]) + (f" and {len(unknown) - 10} more" if len(unknown) > 10 else "")
            raise InputError(f"{path}: names {len(unknown)} image(s) that are not among the images: {shown}")
    return out

"""Ground control points observed in images: OpenDroneMap's gcp_list.txt.

The first line names the coordinates' frame; every other line is one observation of a control point,
whitespace-separated: `geo_x geo_y geo_z im_x im_y image_name [gcp_name]` (further fields are ignored, as
OpenDroneMap does). im_x, im_y are pixels from the image's top-left corner with the top-left pixel's centre at
(0, 0), as OpenDroneMap and OpenSfM read them. Lines with the same gcp_name (or, without names, the same
coordinates) are one point seen in several images. Frames:

- `WGS84`, `EPSG:4326` or `+proj=longlat +datum=WGS84 ...`: geo_x longitude, geo_y latitude (degrees), geo_z
  altitude (metres), OpenDroneMap's order;
- `EPSG:4978` or `ECEF`: earth-centred metres;
- `ENU LAT LON ALT`: metres east, north, up of that origin;
- `LOCAL`: x, y, z metres in any frame without a place on the earth.

Projected systems (UTM and the like) need a projection library mvrecon does not carry: such a file is refused
with a line saying so. Control points are taken as surveyed to GCP_SIGMA_H / GCP_SIGMA_V.
"""

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from .pose_priors import WGS84, PosePrior, covariance, enu_origin, prior_position

GCP_SIGMA_H, GCP_SIGMA_V = 0.05, 0.1  # metres: a GNSS survey of a marker (RTK: centimetres; 5 cm horizontal)
PIXEL_CENTRE = 0.5  # added to the file's pixels: mvrecon's keypoints put the top-left pixel's centre at 0.5


@dataclass
class ControlPoint:
    """A control point: its surveyed position (a prior in WGS84 or CARTESIAN) and its pixels per image
    (mvrecon's convention: the top-left pixel's centre at (0.5, 0.5))."""

    name: str
    prior: PosePrior
    observations: dict[str, np.ndarray] = field(default_factory=dict)


def is_gcp_list(path: Path | str) -> bool:
    """Whether a control file is a gcp_list (its first line a frame), not a CSV of camera positions (its
    first line a comment or a `name,...` header)."""
    try:
        with open(path, encoding="utf-8-sig") as f:
            first = next((ln.strip() for ln in f if ln.strip()), "")
    except (OSError, UnicodeDecodeError):
        return False
    return not (first.startswith("#") or first.split(",")[0].strip().lower() == "name")


def _frame(path: Path, line: str) -> tuple[str, np.ndarray | None]:
    """('wgs84' | 'ecef' | 'enu' | 'local', the ENU origin or None) of a gcp_list's first line."""
    words = line.split()
    head = words[0].upper() if words else ""
    if head in ("WGS84", "EPSG:4326") or (head.startswith("+PROJ=LONGLAT") and "+datum=WGS84" in line.lower()):
        return "wgs84", None
    if head in ("ECEF", "EPSG:4978") and len(words) == 1:
        return "ecef", None
    if head == "LOCAL" and len(words) == 1:
        return "local", None
    if head == "ENU":
        return "enu", enu_origin(path, words[1:], "first line 'ENU'")
    raise InputError(f"{path}: first line {line!r} is not a frame mvrecon reads: WGS84 (EPSG:4326), ECEF "
                     "(EPSG:4978), 'ENU LAT LON ALT' or LOCAL (projected systems such as UTM are not supported); a CSV "
                     "of camera positions starts with a name,... header")


def read_gcp_list(path: Path | str, names: list[str] | None = None) -> dict[str, ControlPoint]:
    """gcp name -> ControlPoint of an OpenDroneMap gcp_list file (module docstring). A malformed line, a point
    given two positions, an impossible position, or (given `names`, the images there are) observations in
    images that are not there raise InputError naming the file and the lines or images."""
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8-sig").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read the control points: {exc}") from None
    rows = [(k, ln.split()) for k, ln in enumerate(lines, start=1) if ln.strip() and not ln.strip().startswith("#")]
    if not rows:
        raise InputError(f"{path}: empty (a frame line, then geo_x geo_y geo_z im_x im_y image_name [gcp_name])")
    frame, origin = _frame(path, lines[rows[0][0] - 1].strip())
    points: dict[str, ControlPoint] = {}
    for k, words in rows[1:]:
        if len(words) < 6:
            raise InputError(f"{path}: line {k} has {len(words)} fields; needs geo_x geo_y geo_z im_x im_y "
                             "image_name [gcp_name]")
        try:
            geo, pixel = np.array(words[:3], float), np.array(words[3:5], float)
        except ValueError:
            raise InputError(f"{path}: line {k}: a coordinate or pixel is not a number") from None
        if not (np.isfinite(geo).all() and np.isfinite(pixel).all()):
            raise InputError(f"{path}: line {k}: coordinates and pixels must be finite")
        image = words[5]
        label = words[6] if len(words) > 6 else " ".join(words[:3])
        # OpenDroneMap's order is longitude, latitude
        position, system = prior_position(frame, geo[[1, 0, 2]] if frame == "wgs84" else geo, origin,
                                          f"{path}: line {k} ({label})")
        point = points.get(label)
        if point is None:
            point = points[label] = ControlPoint(label, PosePrior(position=position, coordinate_system=system,
                                                                  covariance=covariance(GCP_SIGMA_H, GCP_SIGMA_V)))
        elif not np.allclose(point.prior.position, position, rtol=0, atol=1e-9 if system == WGS84 else 1e-4):
            raise InputError(f"{path}: line {k}: control point {label} is given two different positions")
        if image in point.observations:
            raise InputError(f"{path}: line {k}: control point {label} is listed twice in {image}")
        point.observations[image] = pixel + PIXEL_CENTRE
    if not points:
        raise InputError(f"{path}: no observations after the frame line")
    if names is not None:
        unknown = sorted({im for p in points.values() for im in p.observations} - set(names))
        if unknown:
            shown = ", ".join(unknown[:10]) + (f" and {len(unknown) - 10} more" if len(unknown) > 10 else "")
            raise InputError(f"{path}: names {len(unknown)} image(s) that are not among the model's images: {shown}")
    return points

"""The eucentric tilt model under parallel projection, and heights from the parallax of one image pair.

An SEM at moderate to high magnification images along (nearly) parallel rays, so a view is an orthographic
projection. Conventions used by every module in `mvrecon.sem`:

- Image coordinates are pixels with the centre of the top-left pixel at (0, 0) (OpenCV), measured from the image
  centre c = ((w - 1) / 2, (h - 1) / 2): a tilt axis through the image centre is what "eucentric" means.
- The world frame is the specimen at tilt 0 in pixel units of the reference image: x right, y down (the image
  axes) and z = height, positive towards the detector.
- The tilt axis lies in the image plane at `axis_deg` from the image +x axis towards +y; 90 deg is the image's
  vertical axis ("y"). Its direction is a = (cos, sin, 0) and the parallax direction is n = (-sin, cos) (for
  the vertical axis, n = -x). Tilting by theta is the rotation `angle_axis_to_rotmat(-a * theta)`; a world point
  alpha * n + q * a + h * z then images at p = alpha * cos(theta) + h * sin(theta) along n and q along a,
  plus a per-image shift (stage drift, imperfect eucentricity).
- Parallel projection cannot tell (theta, h) from (-theta, -h) (the depth reversal of orthographic views), so
  a tilt's sign is a convention: positive tilts move high points towards +n, i.e. to the left for the
  vertical axis. This is the scene catalog's `sem_tilt` convention (the specimen turns by +theta about the
  world y axis, which points up the image).
"""

import numpy as np

from ..geometry.rotation import angle_axis_to_rotmat


def parse_axis(text: str | float) -> float:
    """Tilt axis in degrees from the CLI: "y" (vertical, 90), "x" (horizontal, 0) or a number of degrees."""
    value = str(text).strip().lower()
    if value == "y":
        return 90.0
    if value == "x":
        return 0.0
    try:
        return float(value) % 180.0
    except ValueError:
        raise ValueError(f"tilt axis must be 'x', 'y' or an angle in degrees, got {text!r}") from None


def axis_vectors(axis_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """(a, n): unit 2D vectors along the tilt axis and along the parallax direction in the image."""
    phi = np.radians(axis_deg)
    return np.array([np.cos(phi), np.sin(phi)]), np.array([-np.sin(phi), np.cos(phi)])


def tilt_rotation(axis_deg: float, tilt_deg: float) -> np.ndarray:
    """World-to-view rotation of the specimen tilted by `tilt_deg` about the in-plane axis `axis_deg`."""
    a, _ = axis_vectors(axis_deg)
    return angle_axis_to_rotmat(-np.radians(tilt_deg) * np.array([a[0], a[1], 0.0]))


def image_center(width: int, height: int) -> np.ndarray:
    return np.array([(width - 1) / 2.0, (height - 1) / 2.0])


def project_tilted(points: np.ndarray, axis_deg: float, tilt_deg: float, center: np.ndarray,
                   shift: tuple[float, float] | np.ndarray = (0.0, 0.0)) -> np.ndarray:
    """World points (N,3) in reference pixels -> pixels (N,2) of the view tilted by `tilt_deg`."""
    R = tilt_rotation(axis_deg, tilt_deg)
    return np.asarray(points, dtype=float) @ R[:2].T + np.asarray(center, float) + np.asarray(shift, float)


def heights_from_parallax(uv1: np.ndarray, uv2: np.ndarray, tilt1_deg: float, tilt2_deg: float,
                          axis_deg: float, center: np.ndarray,
                          shift2: np.ndarray | None = None) -> np.ndarray:
    """World points (N,3) from matched pixels of two views with known tilts (the paper's photogrammetry step).

    Along the parallax direction p1 = alpha cos(t1) + h sin(t1) and p2 = alpha cos(t2) + h sin(t2), so
    h = (p2 cos t1 - p1 cos t2) / sin(t2 - t1); for a symmetric pair that is the textbook
    parallax / (2 sin(dt / 2)). `shift2` is the second view's drift relative to the first; without it the
    along-axis drift is the median along-axis offset of the matches (tilting cannot move points along the axis)
    and the drift across it is taken as zero, which only offsets all heights by a constant.
    """
    uv1 = np.asarray(uv1, dtype=float) - center
    uv2 = np.asarray(uv2, dtype=float) - center
    a, n = axis_vectors(axis_deg)
    if shift2 is None:
        shift2 = np.median((uv2 - uv1) @ a) * a
    uv2 = uv2 - np.asarray(shift2, dtype=float)
    t1, t2 = np.radians(tilt1_deg), np.radians(tilt2_deg)
    s = np.sin(t2 - t1)
    if abs(s) < 1e-9:
        raise ValueError(f"views at {tilt1_deg} and {tilt2_deg} deg have no parallax (equal tilts)")
    p1, p2 = uv1 @ n, uv2 @ n
    h = (p2 * np.cos(t1) - p1 * np.cos(t2)) / s
    alpha = (p1 * np.sin(t2) - p2 * np.sin(t1)) / s
    q = 0.5 * (uv1 @ a + uv2 @ a)
    xy = alpha[:, None] * n + q[:, None] * a
    return np.column_stack([xy, h])

"""COLMAP camera models in numpy: parameter layout, intrinsic matrix, projection with distortion, unprojection.

OPENCV_FISHEYE is the equidistant (Kannala-Brandt) lens of COLMAP and OpenCV's cv2.fisheye: the angle theta of a
ray from the axis maps to the image radius theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)
in normalised units, so the normalised point (x, y) = tan(theta) (cos phi, sin phi) lands at theta_d (cos phi,
sin phi). As in COLMAP, the projection divides by z first: rays at 90 deg or more from the axis have no pixel.

Pixel coordinates follow COLMAP: the centre of the top-left pixel is (0.5, 0.5), so a centred principal point
is (w/2, h/2). OpenCV puts that pixel centre at (0, 0): add 0.5 when moving OpenCV keypoints into COLMAP.
"""

import numpy as np

PARAM_NAMES = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "OPENCV_FISHEYE": ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"),
}
MODELS = tuple(PARAM_NAMES)
# COLMAP's camera model ids as pycolmap 4.2 numbers them, in database blobs and model files alike
# (tests/io/test_formats.py checks them against pycolmap)
CAMERA_MODEL_IDS = {"SIMPLE_PINHOLE": 0, "PINHOLE": 1, "SIMPLE_RADIAL": 2, "RADIAL": 3, "OPENCV": 4,
                    "OPENCV_FISHEYE": 5, "FULL_OPENCV": 6, "FOV": 7, "SIMPLE_RADIAL_FISHEYE": 8, "RADIAL_FISHEYE": 9,
                    "THIN_PRISM_FISHEYE": 10, "RAD_TAN_THIN_PRISM_FISHEYE": 11, "SIMPLE_DIVISION": 12, "DIVISION": 13,
                    "SIMPLE_FISHEYE": 14, "FISHEYE": 15, "EUCM": 16, "EQUIRECTANGULAR": 17}


def num_distortion_terms(model: str) -> int:
    """Lens terms beyond focal and principal point: 0 (pinholes), 1-2 (radial), 4 (OPENCV, OPENCV_FISHEYE)."""
    return sum(name not in ("f", "fx", "fy", "cx", "cy") for name in PARAM_NAMES[model])


def check_model(model: str, params: np.ndarray) -> np.ndarray:
    """Validated float parameter vector for `model`; ValueError names the model and the expected layout."""
    if model not in PARAM_NAMES:
        raise ValueError(f"unknown camera model {model!r}; expected one of {', '.join(MODELS)}")
    params = np.asarray(params, dtype=float).ravel()
    if len(params) != len(PARAM_NAMES[model]):
        raise ValueError(f"{model} takes {len(PARAM_NAMES[model])} parameters "
                         f"({', '.join(PARAM_NAMES[model])}), got {len(params)}")
    return params


def default_params(model: str, focal: float, width: int, height: int) -> np.ndarray:
    """Parameters with the given focal length, centred principal point and no distortion."""
    if model not in PARAM_NAMES:
        check_model(model, [])
    cx, cy = width / 2.0, height / 2.0
    return np.array({
        "SIMPLE_PINHOLE": [focal, cx, cy],
        "PINHOLE": [focal, focal, cx, cy],
        "SIMPLE_RADIAL": [focal, cx, cy, 0.0],
        "RADIAL": [focal, cx, cy, 0.0, 0.0],
        "OPENCV": [focal, focal, cx, cy, 0.0, 0.0, 0.0, 0.0],
        "OPENCV_FISHEYE": [focal, focal, cx, cy, 0.0, 0.0, 0.0, 0.0],
    }[model], dtype=float)


def split(model: str, params: np.ndarray) -> tuple[float, float, float, float, dict[str, float]]:
    """(fx, fy, cx, cy, distortion dict) of a parameter vector."""
    p = check_model(model, params)
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        fx = fy = p[0]
        cx, cy = p[1], p[2]
        dist = {"k1": p[3] if len(p) > 3 else 0.0, "k2": p[4] if len(p) > 4 else 0.0}
    else:
        fx, fy, cx, cy = p[:4]
        dist = dict(zip(PARAM_NAMES[model][4:], p[4:])) if len(p) > 4 else {"k1": 0.0, "k2": 0.0}
    return fx, fy, cx, cy, dist


def calibration_matrix(model: str, params: np.ndarray) -> np.ndarray:
    """3x3 K (COLMAP pixel convention)."""
    fx, fy, cx, cy, _ = split(model, params)
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])


def distortion_coefficients(model: str, params: np.ndarray) -> np.ndarray:
    """OpenCV's distortion vector for the model: (k1, k2, p1, p2) as cv2.projectPoints takes it (zeros for
    pinhole models), and for OPENCV_FISHEYE (k1, k2, k3, k4) as cv2.fisheye takes it."""
    _, _, _, _, d = split(model, params)
    names = PARAM_NAMES[model][4:] if model == "OPENCV_FISHEYE" else ("k1", "k2", "p1", "p2")
    return np.array([d.get(name, 0.0) for name in names])


def distort(model: str, params: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Normalised undistorted image coordinates (N,2) -> normalised distorted coordinates."""
    if model == "OPENCV_FISHEYE":
        return _distort_fisheye(np.asarray(xy, dtype=float), distortion_coefficients(model, params))
    k1, k2, p1, p2 = distortion_coefficients(model, params)
    xy = np.asarray(xy, dtype=float)
    u, v = xy[..., 0], xy[..., 1]
    r2 = u * u + v * v
    radial = k1 * r2 + k2 * r2 * r2
    du = u * radial + 2 * p1 * u * v + p2 * (r2 + 2 * u * u)
    dv = v * radial + 2 * p2 * u * v + p1 * (r2 + 2 * v * v)
    return np.stack([u + du, v + dv], axis=-1)


def undistort_normalized(model: str, params: np.ndarray, xy_distorted: np.ndarray,
                         iterations: int = 30) -> np.ndarray:
    """Invert `distort` by Newton's method with the analytic Jacobian, vectorised over points; only points
    not yet converged are iterated (past the fold of a strong barrel distortion some never converge)."""
    xd = np.asarray(xy_distorted, dtype=float)
    if model == "OPENCV_FISHEYE":  # not an identity even with k = 0: the equidistant lens itself
        flat = xd.reshape(-1, 2)
        return _undistort_fisheye(flat, distortion_coefficients(model, params), iterations).reshape(xd.shape)
    k1, k2, p1, p2 = distortion_coefficients(model, params)
    if not any((k1, k2, p1, p2)):
        return xd.copy()
    flat = xd.reshape(-1, 2)
    if p1 == 0 and p2 == 0:
        return _undistort_radial(flat, k1, k2, iterations).reshape(xd.shape)
    x = flat.copy()
    active = np.arange(len(x))
    for _ in range(iterations):
        u, v = x[active, 0], x[active, 1]
        f = distort(model, params, x[active]) - flat[active]
        r2 = u * u + v * v
        radial = k1 * r2 + k2 * r2 * r2
        g = 2 * (k1 + 2 * k2 * r2)  # d(radial)/d(r2) * 2
        a = 1 + radial + g * u * u + 2 * p1 * v + 6 * p2 * u  # d(u')/du
        b = g * u * v + 2 * p1 * u + 2 * p2 * v  # d(u')/dv
        c = g * u * v + 2 * p2 * v + 2 * p1 * u  # d(v')/du
        d = 1 + radial + g * v * v + 2 * p2 * u + 6 * p1 * v  # d(v')/dv
        det = a * d - b * c
        det = np.where(np.abs(det) < 1e-12, 1e-12, det)
        x[active, 0] = u - (d * f[:, 0] - b * f[:, 1]) / det
        x[active, 1] = v - (-c * f[:, 0] + a * f[:, 1]) / det
        active = active[np.abs(f).max(axis=1) >= 1e-12]
        if len(active) == 0:
            break
    return x.reshape(xd.shape)


def _undistort_radial(xd, k1: float, k2: float, iterations: int) -> np.ndarray:
    """The radial-only models (SIMPLE_RADIAL, RADIAL, and OPENCV without tangential terms) move a point along
    its ray from the centre, so the inverse is a 1-D Newton on the radius: r (1 + k1 r^2 + k2 r^4) = r_d.
    Several times cheaper than the 2-D Newton above, which this runs on every keypoint whenever a bundle
    adjustment changes the focal or the distortion."""
    rd = np.sqrt(xd[:, 0] ** 2 + xd[:, 1] ** 2)
    r = rd.copy()
    for _ in range(iterations):
        r2 = r * r
        f = r * (1 + k1 * r2 + k2 * r2 * r2) - rd
        if not np.abs(f).max(initial=0.0) >= 1e-12:
            break
        df = 1 + 3 * k1 * r2 + 5 * k2 * r2 * r2
        r = r - f / np.where(np.abs(df) < 1e-12, 1e-12, df)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(rd > 0, r / rd, 1.0)
    return xd * scale[:, None]


def _fisheye_theta_d(theta, k) -> np.ndarray:
    t2 = theta * theta
    return theta * (1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))))


def _distort_fisheye(xy, k) -> np.ndarray:
    """COLMAP's OpenCVFisheyeCameraModel::Distortion: the point moves along its ray from the centre to radius
    theta_d(atan(r)); at r = 0 (below machine epsilon, as COLMAP) it stays."""
    r = np.sqrt(xy[..., 0] ** 2 + xy[..., 1] ** 2)
    eps = np.finfo(float).eps
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(r > eps, _fisheye_theta_d(np.arctan(r), k) / r, 1.0)
    return xy * scale[..., None]


def _undistort_fisheye(xd, k, iterations: int) -> np.ndarray:
    """Invert `_distort_fisheye`: Newton on theta for theta_d(theta) = |xd|, started at theta = theta_d, then
    r = tan(theta). The ratio tan(theta) / theta_d is taken only for theta_d > 0 (it tends to 1 at the centre,
    where the point stays); a theta of 90 deg or more, or one where the lens model folds over (d theta_d /
    d theta <= 0, so Newton cannot converge), has no ray in front of the camera: NaN."""
    rd = np.sqrt(xd[:, 0] ** 2 + xd[:, 1] ** 2)
    theta = rd.copy()
    active = np.flatnonzero(rd > 0)
    for _ in range(iterations):
        t = theta[active]
        f = _fisheye_theta_d(t, k) - rd[active]
        t2 = t * t
        df = 1 + t2 * (3 * k[0] + t2 * (5 * k[1] + t2 * (7 * k[2] + t2 * 9 * k[3])))
        theta[active] = t - f / np.where(np.abs(df) < 1e-12, 1e-12, df)
        active = active[np.abs(f) >= 1e-14]
        if len(active) == 0:
            break
    converged = np.abs(_fisheye_theta_d(theta, k) - rd) <= 1e-9 * np.maximum(rd, 1.0)
    ok = converged & (theta >= 0) & (theta < np.pi / 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(rd > 0, np.tan(theta) / rd, 1.0)
    return xd * np.where(ok, scale, np.nan)[:, None]


def project(model: str, params: np.ndarray, points_cam: np.ndarray) -> np.ndarray:
    """Camera-frame points (N,3), z forward -> pixels (N,2). Points behind the camera give NaN."""
    X = np.asarray(points_cam, dtype=float)
    z = X[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = X[..., :2] / np.where(z > 0, z, np.nan)[..., None]
    return normalized_to_pixels(model, params, distort(model, params, xy))


def normalized_to_pixels(model: str, params: np.ndarray, xy_distorted: np.ndarray) -> np.ndarray:
    fx, fy, cx, cy, _ = split(model, params)
    xy = np.asarray(xy_distorted, dtype=float)
    return np.stack([fx * xy[..., 0] + cx, fy * xy[..., 1] + cy], axis=-1)


def pixels_to_normalized(model: str, params: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Pixels (N,2) -> undistorted normalised coordinates (N,2) (the ray is (x, y, 1))."""
    fx, fy, cx, cy, _ = split(model, params)
    uv = np.asarray(uv, dtype=float)
    xd = np.stack([(uv[..., 0] - cx) / fx, (uv[..., 1] - cy) / fy], axis=-1)
    return undistort_normalized(model, params, xd)


def focal_length(model: str, params: np.ndarray) -> float:
    """Mean focal length in pixels."""
    fx, fy, *_ = split(model, params)
    return float((fx + fy) / 2)

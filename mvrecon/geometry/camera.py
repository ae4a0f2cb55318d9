"""COLMAP camera models in numpy: parameter layout, intrinsic matrix, projection with distortion, unprojection.

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
}
MODELS = tuple(PARAM_NAMES)


def check_model(model: str, params) -> np.ndarray:
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
    }[model], dtype=float)


def split(model: str, params):
    """(fx, fy, cx, cy, distortion dict) of a parameter vector."""
    p = check_model(model, params)
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        fx = fy = p[0]
        cx, cy = p[1], p[2]
        dist = {"k1": p[3] if len(p) > 3 else 0.0, "k2": p[4] if len(p) > 4 else 0.0}
    else:
        fx, fy, cx, cy = p[:4]
        dist = {"k1": 0.0, "k2": 0.0} if model == "PINHOLE" else dict(zip(("k1", "k2", "p1", "p2"), p[4:]))
    return fx, fy, cx, cy, dist


def calibration_matrix(model: str, params) -> np.ndarray:
    """3x3 K (COLMAP pixel convention)."""
    fx, fy, cx, cy, _ = split(model, params)
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])


def distortion_coefficients(model: str, params) -> np.ndarray:
    """OpenCV's (k1, k2, p1, p2) for the model; zeros for pinhole models."""
    _, _, _, _, d = split(model, params)
    return np.array([d.get("k1", 0.0), d.get("k2", 0.0), d.get("p1", 0.0), d.get("p2", 0.0)])


def distort(model: str, params, xy) -> np.ndarray:
    """Normalised undistorted image coordinates (N,2) -> normalised distorted coordinates."""
    k1, k2, p1, p2 = distortion_coefficients(model, params)
    xy = np.asarray(xy, dtype=float)
    u, v = xy[..., 0], xy[..., 1]
    r2 = u * u + v * v
    radial = k1 * r2 + k2 * r2 * r2
    du = u * radial + 2 * p1 * u * v + p2 * (r2 + 2 * u * u)
    dv = v * radial + 2 * p2 * u * v + p1 * (r2 + 2 * v * v)
    return np.stack([u + du, v + dv], axis=-1)


def undistort_normalized(model: str, params, xy_distorted, iterations: int = 30) -> np.ndarray:
    """Invert `distort` by Newton's method with the analytic Jacobian, vectorised over points; only points
    not yet converged are iterated (past the fold of a strong barrel distortion some never converge)."""
    xd = np.asarray(xy_distorted, dtype=float)
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


def project(model: str, params, points_cam) -> np.ndarray:
    """Camera-frame points (N,3), z forward -> pixels (N,2). Points behind the camera give NaN."""
    X = np.asarray(points_cam, dtype=float)
    z = X[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = X[..., :2] / np.where(z > 0, z, np.nan)[..., None]
    return normalized_to_pixels(model, params, distort(model, params, xy))


def normalized_to_pixels(model: str, params, xy_distorted) -> np.ndarray:
    fx, fy, cx, cy, _ = split(model, params)
    xy = np.asarray(xy_distorted, dtype=float)
    return np.stack([fx * xy[..., 0] + cx, fy * xy[..., 1] + cy], axis=-1)


def pixels_to_normalized(model: str, params, uv) -> np.ndarray:
    """Pixels (N,2) -> undistorted normalised coordinates (N,2) (the ray is (x, y, 1))."""
    fx, fy, cx, cy, _ = split(model, params)
    uv = np.asarray(uv, dtype=float)
    xd = np.stack([(uv[..., 0] - cx) / fx, (uv[..., 1] - cy) / fy], axis=-1)
    return undistort_normalized(model, params, xd)


def focal_length(model: str, params) -> float:
    """Mean focal length in pixels."""
    fx, fy, *_ = split(model, params)
    return float((fx + fy) / 2)

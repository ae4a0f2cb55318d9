"""Filters run after bundle adjustment: bad observations, weakly triangulated points, degenerate cameras."""

import numpy as np

from ..geometry.triangulation import reaches_triangulation_angle
from .config import MapperConfig


def filter_observations(model, config: MapperConfig, point_ids=None) -> int:
    """Remove observations reprojecting over the threshold or behind the camera (of `point_ids` or all).

    Points left with fewer than two observations are deleted. Returns the number of observations removed.
    """
    obs = model.alive_observations() if point_ids is None else model.observations_of_points(point_ids)
    if len(obs) == 0:
        return 0
    err, depth = model.reprojection_errors(obs)
    bad = obs[~(err <= config.filter_max_reproj_error_px) | ~(depth > 0)]
    model.remove_observations(bad)
    return len(bad)


def filter_small_angle_points(model, config: MapperConfig, point_ids=None) -> int:
    """Delete points whose largest triangulation angle is under the threshold (depth is ill-determined)."""
    pids = model.alive_points() if point_ids is None else np.asarray(point_ids, dtype=np.int64)
    pids = pids[model.point_alive.data[pids]]
    if len(pids) == 0:
        return 0
    uniq, obs, mask = model.padded_observations(pids)
    centers = model.centers()[model.obs_image.data[obs]]
    bad = uniq[~reaches_triangulation_angle(model.xyz.data[uniq], centers, mask, config.filter_min_tri_angle_deg)]
    model.delete_points(bad)
    return len(bad)


def degenerate_cameras(model, max_focal_ratio: float = 10.0, max_distortion: float = 1.0) -> list[int]:
    """Cameras whose refined parameters are implausible (COLMAP's bogus-camera check): a focal length more
    than
    `max_focal_ratio` away from the prior, or a distortion coefficient beyond `max_distortion`."""
    from ..geometry import camera as cammodel

    bad = []
    for cid, cam in model.cameras.items():
        f = cam.focal()
        ratio = f / cam.prior_focal if cam.prior_focal > 0 else 1.0
        dist = np.abs(cammodel.distortion_coefficients(cam.model, cam.params))
        if not np.isfinite(f) or f <= 0 or ratio > max_focal_ratio or ratio < 1 / max_focal_ratio \
                or np.any(dist > max_distortion):
            bad.append(int(cid))
    return bad

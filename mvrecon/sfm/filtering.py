"""Filters run after bundle adjustment: bad observations, weakly triangulated points, degenerate cameras."""

import logging
from collections.abc import Callable

import numpy as np

from ..geometry import camera as cammodel
from ..geometry.triangulation import reaches_triangulation_angle
from .config import MapperConfig
from .model import Reconstruction

log = logging.getLogger(__name__)


def filter_observations(model: Reconstruction, config: MapperConfig,
                        point_ids: np.ndarray | None = None) -> int:
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


def filter_small_angle_points(model: Reconstruction, config: MapperConfig,
                              point_ids: np.ndarray | None = None) -> int:
    """Delete points whose largest triangulation angle is under the threshold (depth is ill-determined)."""
    pids = model.alive_points() if point_ids is None else np.asarray(point_ids, dtype=np.int64)
    pids = pids[model.point_alive.data[pids]]
    if len(pids) == 0:
        return 0
    centers = model.centers()
    bad = np.concatenate([uniq[~reaches_triangulation_angle(model.xyz.data[uniq], centers[model.obs_image.data[obs]],
                                                            mask, config.filter_min_tri_angle_deg)]
                          for uniq, obs, mask in model.padded_groups(pids)])
    model.delete_points(bad)
    return len(bad)


def degenerate_cameras(model: Reconstruction, max_focal_ratio: float = 10.0,
                       max_distortion: float = 1.0) -> list[int]:
    """Cameras whose refined parameters are implausible (COLMAP's bogus-camera check): a focal length more
    than `max_focal_ratio` away from the prior, or a distortion coefficient beyond `max_distortion`. The mapper
    undoes a BA that leaves one, so only what no growing model passes through belongs here: fx / fy is tested at
    a model's end (`non_square_cameras`), as growing fisheye_orbit_small per image passes 520 / 1025."""
    bad = []
    for cid, cam in model.cameras.items():
        f = cam.focal()
        ratio = f / cam.prior_focal if cam.prior_focal > 0 else 1.0
        dist = np.abs(cammodel.distortion_coefficients(cam.model, cam.params))
        if not np.isfinite(f) or f <= 0 or ratio > max_focal_ratio or ratio < 1 / max_focal_ratio \
                or np.any(dist > max_distortion):
            bad.append(int(cid))
    return bad


def non_square_cameras(model: Reconstruction, max_aspect_ratio: float = 1.5) -> list[int]:
    """Cameras of registered images, without a trusted prior, whose fx and fy are more than
    `max_aspect_ratio` apart: a finished model holding one was fitted to wrong matches.

    COLMAP's bogus-camera test bounds each focal by the image size (0.1 to 10 x max(w, h)) and |extra
    params| by 1, never fx against fy, and its mapper applies it only from 20 registered images on, because
    a growing model's calibration still moves a lot. An untrusted camera starts from a guess with fx = fy,
    and pixels are square on nearly every camera (a 10:11 or 1.33 video pixel aspect stays inside 1.5),
    so fx / fy beyond 1.5 is not a lens: fisheye_orbit_small per image left a three-image model with fx / fy
    1597 / 461, 603 / 1137 and 499 / 857 and a 29 deg rotation error. A trusted calibration may be
    anamorphic; it is not second-guessed.
    """
    used = np.unique(model.camera_of[model.registered])
    bad = []
    for cid in used.tolist():
        cam = model.cameras[int(cid)]
        fx, fy, *_ = cammodel.split(cam.model, cam.params)
        with np.errstate(divide="ignore", invalid="ignore"):
            aspect = fx / fy
        if not cam.prior_trusted and not 1 / max_aspect_ratio <= aspect <= max_aspect_ratio:
            bad.append(int(cid))
    return bad


def plausible_bundle(model: Reconstruction, focal: bool, distortion: bool,
                     adjust: Callable[[bool, bool], None], square: bool = False) -> None:
    """`adjust(refine_focal, refine_distortion)`, a bundle adjustment of `model`, undone when it leaves a camera
    implausible (`degenerate_cameras`, and with `square` also `non_square_cameras`) and repeated with the
    distortion fixed, then with all intrinsics fixed: a guessed focal and the distortion can trade off against
    each other in a small model, and dropping the images would not repair the camera they share. Poses, points
    and cameras end as the first plausible adjustment left them, or as they were when none was. `square` is for
    a model that holds all its images from the start (the global mapper's), where fx / fy apart is no passing
    state of a growing model but a fit to wrong poses; neutral or better on every suite set where it fires
    (docs/benchmarks.md, "Global positioning: tracks per image, and a camera's fx / fy")."""
    saved = (model.R.copy(), model.t.copy(), model.xyz.data.copy(),
             {c: cam.params.copy() for c, cam in model.cameras.items()})
    for intr, dist in dict.fromkeys([(focal, distortion), (focal, False), (False, False)]):
        adjust(intr, dist)
        bad = sorted(set(degenerate_cameras(model)) | set(non_square_cameras(model) if square else ()))
        if not bad:
            return
        log.info("bundle adjustment with %s refined left camera(s) %s implausible (%s); undone",
                 "focal and distortion" if dist else "the focal" if intr else "no intrinsics", bad,
                 ", ".join(f"params {np.round(model.cameras[c].params, 3)}" for c in bad))
        model.R[:], model.t[:], model.xyz.data[:] = saved[0], saved[1], saved[2]
        for c, params in saved[3].items():
            model.cameras[c].params = params.copy()

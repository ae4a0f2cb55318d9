"""Bundle adjustment with GTSAM: poses, points and one shared calibration per camera, Huber loss.

Variables: X(i) = world_from_camera Pose3 of each optimised image, L(p) = Point3, K(c) = calibration of
camera c (COLMAP model -> GTSAM: SIMPLE_PINHOLE/SIMPLE_RADIAL/RADIAL -> Cal3Bundler, PINHOLE -> Cal3_S2, OPENCV ->
Cal3DS2, OPENCV_FISHEYE -> Cal3Fisheye, the same equidistant lens with k1..k4 as its distortion). A view of an
optimised image is a GeneralSFMFactor2 (pose, point, calibration); the views of a point in constant images
(outside a local window) are one Gaussian prior on the point alone, so constant cameras add no variables and
their views no factor each (`_held_view_priors`). Calibration entries
COLMAP keeps fixed (principal point, skew, the k2 of SIMPLE_RADIAL) or that are not refined (the distortion, k1..k4
of OPENCV and OPENCV_FISHEYE, in the focal-only stages) are pinned by a tight prior on the calibration.

Gauge: 7 degrees of freedom (similarity) are free in SfM. With two or more constant images the window is
anchored. Otherwise the first registered image is pinned by a tight pose prior and the scale by a prior on one
translation component (along the baseline) of the second image, COLMAP's choice. In the BA of the initial pair
alone that prior is soft (sigma = the baseline's length): with the focal held there, a pair estimated at a
guessed focal changes its depth-to-baseline ratio (templeRing: it doubles), and a tight prior made every point
walk to its new depth, a little each LM step (34 iterations instead of 11). With more images it stays tight: a
soft one there sent imc_reichstag's focal BAs (a camera per image) to higher costs and AUC@5 0.75 -> 0.53.

Camera-centre priors (georef.py): once a model is georeferenced, each optimised image with a position prior gets a
GPSFactor on its pose's translation (the camera centre) with the prior's sigmas under a Cauchy loss, so that a
fix many sigmas off barely pulls; with three or more such images spread in two directions the priors anchor the
gauge and the pose and scale priors above are left out.

The graph is built once per call in a single pass over the observation arrays; `optimizer="sfm"` runs
gtsam.SfmLevenbergMarquardtOptimizer with Schur elimination of the points, "lm" plain Levenberg-Marquardt, its
steps solved by sequential Cholesky, or by conjugate gradients where the factorisation would fill in
(`MapperConfig.ba_iterative_fill`).
"""

import logging
import os
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass

import gtsam
import numpy as np
from scipy.sparse import csr_matrix, triu

from .config import MapperConfig
from .georef import spread_enough
from .model import Reconstruction, sum_rows
from .track_parts import deal_long_tracks, scrambled

log = logging.getLogger("mvrecon.sfm")
_TIGHT = 1e-6
_LOOSE = 1e6
BYTES_PER_BLOCK = 50  # a BA's memory per pair of variable views of one point (_split_long_tracks)
MIN_SUB_VIEWS = 8  # the least views per sub-point a split point's views are shared out to
ORDERED_POSES = 100  # from this many optimised poses a BA eliminates them in `_pose_order`'s order
_SQUARE_SIGMA_PX = 0.01  # how far apart fx and fy may be held by `_add_square_pixels`, pixels
_CERES_LAMBDA = 1e-4  # LM's initial damping (CeresDefaults), except in BAs of shared cameras (MapperConfig)
PCG_ITERATIONS = 500  # conjugate-gradient iterations an LM step may take (`_optimize`'s "pcg")
PCG_TOLERANCE = 1e-3  # the residual, relative to the right-hand side's, at which conjugate gradients stop


@dataclass
class BundleResult:
    initial_error: float
    final_error: float
    iterations: int
    seconds: float
    num_observations: int
    sub_points: int = 0  # variables added by splitting long tracks (_split_long_tracks)


_FOCAL_ENTRIES = {"Cal3Bundler": [0], "Cal3_S2": [0, 1], "Cal3DS2": [0, 1], "Cal3Fisheye": [0, 1]}


def _calibration_layout(model: str, params):
    """(gtsam class name, gtsam calibration vector, mask of the tangent entries that may be refined)."""
    p = np.asarray(params, dtype=float)
    if model == "SIMPLE_PINHOLE":
        return "Cal3Bundler", [p[0], 0.0, 0.0, p[1], p[2]], [True, False, False]
    if model == "SIMPLE_RADIAL":
        return "Cal3Bundler", [p[0], p[3], 0.0, p[1], p[2]], [True, True, False]
    if model == "RADIAL":
        return "Cal3Bundler", [p[0], p[3], p[4], p[1], p[2]], [True, True, True]
    if model == "PINHOLE":
        return "Cal3_S2", [p[0], p[1], 0.0, p[2], p[3]], [True, True, False, False, False]
    if model in ("OPENCV", "OPENCV_FISHEYE"):  # both: fx, fy, s, u0, v0, then the four distortion terms
        return "Cal3DS2" if model == "OPENCV" else "Cal3Fisheye", [p[0], p[1], 0.0, p[2], p[3], *p[4:8]], [
            True, True, False, False, False, True, True, True, True]
    raise ValueError(f"camera model {model} is not supported by bundle adjustment (use one of "
                     "SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL, PINHOLE, OPENCV, OPENCV_FISHEYE)")


def _make_calibration(gtsam, kind, v):
    return getattr(gtsam, kind)(*v)


def _params_from_calibration(model: str, cal) -> np.ndarray:
    if model == "SIMPLE_PINHOLE":
        return np.array([cal.fx(), cal.px(), cal.py()])
    if model == "SIMPLE_RADIAL":
        return np.array([cal.fx(), cal.px(), cal.py(), cal.k1()])
    if model == "RADIAL":
        return np.array([cal.fx(), cal.px(), cal.py(), cal.k1(), cal.k2()])
    if model == "PINHOLE":
        return np.array([cal.fx(), cal.fy(), cal.px(), cal.py()])
    if model == "OPENCV_FISHEYE":
        return np.array([cal.fx(), cal.fy(), cal.px(), cal.py(), cal.k1(), cal.k2(), cal.k3(), cal.k4()])
    k = cal.k()
    return np.array([cal.fx(), cal.fy(), cal.px(), cal.py(), k[0], k[1], k[2], k[3]])


def _keys(char: str, indices) -> list[int]:
    """GTSAM symbol keys (as `gtsam.symbol(char, j)`) of many indices at once: the character in the top byte."""
    return _key_array(char, indices).tolist()


def _key_array(char: str, indices) -> np.ndarray:
    """`_keys` as a uint64 array."""
    return np.uint64(ord(char) << 56) | np.asarray(indices, dtype=np.int64).astype(np.uint64)


def _pose3(gtsam, R, t):
    Rt = np.asarray(R).T
    return gtsam.Pose3(gtsam.Rot3(Rt), -Rt @ np.asarray(t))


@dataclass
class _Window:
    """What one bundle adjustment sees: the observations of its points, and which images' poses it moves."""

    variable: np.ndarray  # per image of the model: its pose is a variable (registered and observed here)
    obs: np.ndarray  # indices of the observations, and their image, point and keypoint
    obs_img: np.ndarray
    obs_pt: np.ndarray
    obs_kp: np.ndarray
    split: np.ndarray | None = None  # per observation: its sub-point (-1: the point itself), see _split_long_tracks

    @property
    def optimised(self) -> list[int]:
        return np.flatnonzero(self.variable).tolist()


def bundle_adjust(model: Reconstruction, variable_images: np.ndarray | list[int], config: MapperConfig, *,
                  point_ids: np.ndarray | None = None, refine_intrinsics: bool = False,
                  refine_distortion: bool = True, max_iterations: int | None = None,
                  relative_tolerance: float | None = None, optimizer: str | None = None,
                  square_pixels: bool = True) -> BundleResult:
    """Optimise the poses of `variable_images`, the points they see (or `point_ids`) and, when asked, the
    intrinsics of cameras whose registered images are all variable (the focal only, without
    `refine_distortion`). Other registered images stay constant. `relative_tolerance` overrides the config's.
    The fx and fy of each refined camera whose calibration is not trusted are held equal (`_add_square_pixels`)
    unless `square_pixels` is False: the lens trials (sfm/lens.py) fit each model free."""
    start = time.perf_counter()
    window = _window(model, variable_images, point_ids)
    if window is None:
        return BundleResult(0.0, 0.0, 0, 0.0, 0)
    optimised = window.optimised
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    var_cams = set(np.unique(model.camera_of[window.variable]).tolist())
    refined_cams = _refined_cameras(model, window.variable, var_cams) if refine_intrinsics else set()
    cal_kind = _add_calibrations(gtsam, graph, values, model, var_cams, refined_cams, refine_distortion)
    if square_pixels:
        _add_square_pixels(gtsam, graph, model, refined_cams, cal_kind)
    for i in optimised:
        values.insert(gtsam.symbol("x", i), _pose3(gtsam, model.R[i], model.t[i]))
    held_images = len(np.unique(window.obs_img[~window.variable[window.obs_img]]))
    points = np.unique(window.obs_pt)
    point_keys, xyz = _keys("l", points), model.xyz.data
    for k, p in zip(point_keys, points.tolist()):
        values.insertPoint3(k, xyz[p])  # `insert` would store a dynamic Vector, cast at every access
    poses, fill = _pose_order(window)
    kind = optimizer or config.optimizer
    if kind == "lm" and 0 < config.ba_iterative_fill <= fill:
        kind = "pcg"
    # conjugate gradients factor nothing: no blocks to bound
    window.split, sub_points = _split_long_tracks(window, 0 if kind == "pcg" else config.ba_memory_mb)
    sub_keys = _keys("s", range(len(sub_points)))
    for k, p in zip(sub_keys, sub_points.tolist()):
        values.insertPoint3(k, xyz[p])
    _add_views(gtsam, graph, model, window, config.huber_px, cal_kind)
    if not _add_center_priors(gtsam, graph, model, window.variable):
        _fix_gauge(gtsam, graph, model, window.variable, held_images)

    iterations = max_iterations or config.global_ba_iterations
    # points first (the Schur complement, and no COLAMD run over the whole graph per call), then poses
    # (`_pose_order`), calibrations last: every reduced factor touches the calibration, so eliminating it before
    # the poses joins them all at once (an LM iteration of templeRing's final BA: 98 ms median against 114)
    ordering = gtsam.Ordering([*point_keys, *sub_keys, *_keys("x", poses), *_keys("k", list(var_cams))])
    lam = config.ba_shared_initial_lambda if model.cameras_shared(optimised) else _CERES_LAMBDA
    tolerance = relative_tolerance or config.ba_relative_tolerance
    result, used, initial, final = _optimize(gtsam, graph, values, kind, iterations, tolerance, ordering, lam)

    focals = _write_back(gtsam, model, result, optimised, points, window, sub_points, refined_cams, cal_kind)
    out = BundleResult(float(initial), float(final), used, time.perf_counter() - start, len(window.obs),
                       len(sub_points))
    log.debug("BA %d images (%d constant), %d points (%d sub-points), %d observations, fill %.3g, %s: cost %.4g -> "
              "%.4g in %d iterations, %.3f s%s", len(optimised), held_images, len(points), len(sub_points),
              len(window.obs), fill, kind, out.initial_error,
              out.final_error, used, out.seconds, "".join(f"; {f}" for f in focals))
    return out


def _window(model, variable_images, point_ids) -> _Window | None:
    """The observations of `point_ids` (default: every point `variable_images` see) and the registered images
    among `variable_images` that have one; None when there is nothing to optimise."""
    variable = np.zeros(len(model.image_ids), bool)
    variable[np.asarray(variable_images, dtype=np.int64)] = True
    variable &= model.registered
    if point_ids is None:
        point_ids = np.unique(model.obs_point.data[model.observations_of_images(np.flatnonzero(variable))])
    obs = model.observations_of_points(point_ids)
    obs_img, obs_pt, obs_kp = model.obs_image.data[obs], model.obs_point.data[obs], model.obs_kp.data[obs]
    variable &= np.isin(np.arange(len(variable)), obs_img)  # a pose with no factor would be a singular variable
    if len(obs) == 0 or not variable.any():
        return None
    return _Window(variable, obs, obs_img, obs_pt, obs_kp)


def _pose_order(window: _Window) -> tuple[list[int], float]:
    """The order in which a BA eliminates its poses, after the points, and the fill of that elimination: from
    ORDERED_POSES poses on, COLAMD's (approximate minimum degree) order of the graph of the images that share a
    point, else image order. Eliminating the points joins every two images that see one, and eliminating a pose
    then joins all its neighbours still to come: a fill-reducing order keeps that fill, and the factorisation's
    work, small, at the same result. Image order is such an order for a sequence, not for two rings of views
    numbered one after the other, nor for a survey's flight lines (docs/benchmarks.md, "Pose order"). The fill
    is the sum over the poses of the square of the number of poses each is joined to when it is eliminated,
    which the factorisation's work grows with; 0 below ORDERED_POSES poses, where it is small."""
    optimised = np.flatnonzero(window.variable)
    if len(optimised) < ORDERED_POSES:
        return optimised.tolist(), 0.0
    column = np.full(len(window.variable), -1, np.int64)
    column[optimised] = np.arange(len(optimised))
    views = column[window.obs_img] >= 0
    points = np.unique(window.obs_pt[views], return_inverse=True)[1]
    seen = csr_matrix((np.ones(int(views.sum()), np.float32), (column[window.obs_img[views]], points)),
                      shape=(len(optimised), int(points.max(initial=-1)) + 1))
    shared = triu(seen @ seen.T, 1).tocoo()
    graph = gtsam.SymbolicFactorGraph()
    for a, b in zip(shared.row.tolist(), shared.col.tolist()):
        graph.push_factor(a, b)
    for a in range(len(optimised)):  # an image sharing no point is still ordered
        graph.push_factor(a)
    order = gtsam.Ordering.ColamdSymbolicFactorGraph(graph)
    eliminated = graph.eliminateSequential(order)
    fill = float(sum(eliminated.at(k).nrParents() ** 2 for k in range(eliminated.size())))
    return optimised[[order.at(k) for k in range(order.size())]].tolist(), fill


def _split_long_tracks(window: _Window, memory_mb: float) -> tuple[np.ndarray | None, np.ndarray]:
    """Bound the BA's memory: eliminating a point leaves a dense block over the variable images that see it,
    held until those poses are eliminated (about BYTES_PER_BLOCK per pair of its variable views, measured on a
    finished model's BA), so the points of a dense orbit's 1,000-image refinement, 38 variable views each on
    average, held 2.5 GB. When the blocks would pass `memory_mb` (0: never), each point with more than K
    variable views becomes ceil(k / K) sub-points, the point and new variables, each taking K / 2 views or more
    drawn across the track (a fixed scramble, not in turn: images must not fall into classes that share no
    variable); K is the largest that fits (at least MIN_SUB_VIEWS). Every view stays in the BA; the sub-points
    of a point are not tied to each other, and it is written back as their mean. Fires on no set of the mapper
    suite; on a 1,000-view dense orbit AUC@1 -0.001 (docs/benchmarks.md, "Mapper rules"). A BA solved by conjugate
    gradients factors nothing and is given 0. Returns, per observation, its sub-point (-1: the point itself; None
    when nothing is split), and the point of each sub-point."""
    none = None, np.zeros(0, np.int64)
    if memory_mb <= 0:
        return none
    points, inverse = np.unique(window.obs_pt, return_inverse=True)
    k = np.bincount(inverse, weights=window.variable[window.obs_img], minlength=len(points)).astype(np.int64)
    dealt = deal_long_tracks(inverse, k, memory_mb * 2 ** 20 / BYTES_PER_BLOCK, MIN_SUB_VIEWS,
                             scrambled(window.obs_pt, window.obs_img))
    if dealt is None:
        return none
    turn, per_point = dealt
    # sub-points numbered point by point; turn 0 keeps the point's own variable
    added = per_point - 1
    first = np.r_[0, np.cumsum(added)[:-1]]
    return np.where(turn > 0, first[inverse] + turn - 1, -1), np.repeat(points, added)


def _refined_cameras(model, variable, cameras) -> set:
    """The cameras among `cameras` whose registered images are all variable: only theirs may be refined."""
    return {c for c in cameras if np.all(variable[model.registered & (model.camera_of == c)])}


def _add_calibrations(gtsam, graph, values, model, cameras, refined_cams, refine_distortion) -> dict:
    """A calibration variable K(c) per camera of a variable image, held by a prior: loose on the entries that
    may be refined (those of `refined_cams`; only the focal without `refine_distortion`), tight on the others.
    Returns each camera's GTSAM calibration class name."""
    cal_kind = {}
    for c in cameras:
        cam = model.cameras[c]
        kind, vec, free = _calibration_layout(cam.model, cam.params)
        cal_kind[c] = kind
        values.insert(gtsam.symbol("k", c), _make_calibration(gtsam, kind, vec))
        free = np.asarray(free) & (c in refined_cams)
        if not refine_distortion:
            free &= np.isin(np.arange(len(free)), _FOCAL_ENTRIES[kind])
        sig = np.where(free, _LOOSE, _TIGHT)
        prior = getattr(gtsam, f"PriorFactor{kind}")
        graph.add(prior(gtsam.symbol("k", c), _make_calibration(gtsam, kind, vec),
                        gtsam.noiseModel.Diagonal.Sigmas(sig)))
    return cal_kind


def _add_square_pixels(gtsam, graph, model, refined_cams, cal_kind: dict) -> None:
    """A factor holding fx = fy (to `_SQUARE_SIGMA_PX`) on each camera of `refined_cams` with two focal entries
    whose calibration is not trusted. Such a camera starts from a guess with fx = fy and pixels are square on
    nearly every camera; left free, the two focals of a guess far off trade off against the poses and the
    distortion and drift apart (wide_orbit_small, OPENCV from 768 px for the true 269: fx / fy 568 / 851 at the
    global mapper's end, every pose wrong; after the incremental mapper's switch to OPENCV on another orbit,
    269.8 / 271.1 and AUC@1 0.80 against 0.95), where held together they find the focal (docs/benchmarks.md,
    "Global mapper: a guessed camera's two focals held equal", "A guessed camera's two focals held equal in
    the incremental mapper")."""
    for c in sorted(refined_cams):
        kind = cal_kind[c]
        if len(_FOCAL_ENTRIES[kind]) < 2 or model.cameras[c].prior_trusted:
            continue
        at = getattr(gtsam.Values, f"at{kind}")
        row = np.zeros((1, getattr(gtsam, kind)().dim()))
        row[0, :2] = 1.0, -1.0

        def equal_focals(factor, values, jacobians, at=at, row=row):
            fx, fy = at(values, factor.keys()[0]).vector()[:2]
            if jacobians is not None:
                jacobians[0] = row
            return np.array([fx - fy])

        graph.add(gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(1, _SQUARE_SIGMA_PX),
                                     [gtsam.symbol("k", c)], equal_focals))


def _add_views(gtsam, graph, model, window: _Window, huber_px: float, cal_kind: dict) -> None:
    """A factor per view of a variable image, in observation order, from the model's cache (building them was
    ~10% of a BA's time); list operations rather than one Python loop doing it all, as a mapping adds ~100,000
    factors. The views in held images become one prior per point (`_held_view_priors`)."""
    obs, obs_img, obs_pt = window.obs, window.obs_img, window.obs_pt
    uv = model.keypoints_at(obs_img, window.obs_kp)
    level = model.view_sigma_levels(obs_img, window.obs_kp)  # each view's sigma is 2^(level / 4) px
    noises = {int(k): gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(huber_px),
                                                     gtsam.noiseModel.Isotropic.Sigma(2, 2.0 ** (k / 4)))
              for k in np.unique(level)}
    variable = window.variable[obs_img]
    _held_view_priors(gtsam, graph, model, window, np.flatnonzero(~variable), uv[~variable],
                      2.0 ** (level[~variable] / 4), huber_px)
    cache = model.ba_factor_cache((huber_px, tuple(model.view_sigma_table)))
    rows = np.flatnonzero(variable).tolist()
    factors = [cache.get(o) for o in obs[rows].tolist()]
    sub = [-1] * len(obs) if window.split is None else window.split.tolist()
    make = {c: getattr(gtsam, f"GeneralSFMFactor2{kind}") for c, kind in cal_kind.items()}
    for k in [k for k, (f, row) in enumerate(zip(factors, rows)) if f is None or sub[row] >= 0]:
        row = rows[k]
        i, p, s = int(obs_img[row]), int(obs_pt[row]), sub[row]
        key = gtsam.symbol("l", p) if s < 0 else gtsam.symbol("s", s)  # a sub-point's view is not cached
        c = int(model.camera_of[i])
        factors[k] = make[c](uv[row], noises[int(level[row])], gtsam.symbol("x", i), key, gtsam.symbol("k", c))
        if s < 0:
            cache[int(obs[row])] = factors[k]
    for f in factors:
        graph.add(f)


def _held_view_priors(gtsam, graph, model, window: _Window, rows: np.ndarray, uv: np.ndarray,
                      sigma: np.ndarray, huber_px: float) -> None:
    """The views `rows` of the window, all in held images, as one Gaussian prior per point (or sub-point): the
    quadratic model of their robust reprojection cost at the point's position, H = sum w J^T J and gradient
    g = sum w J^T r (J the projection's Jacobian by central differences, r the residual, both divided by the
    view's `sigma`, w Huber's weight of r),
    centred at x - H^-1 g. A held camera does not move, so its views bind only the point; as one prior each
    point costs the solver one factor however many held images see it, where a factor per view made a local
    BA's cost grow with the model's track lengths (docs/scale.md, "Held views"). A single held view constrains
    two directions; a millionth of H's trace on each axis keeps the prior proper without pulling the point."""
    if len(rows) == 0:
        return
    img, pt = window.obs_img[rows], window.obs_pt[rows]
    split = np.full(len(rows), -1) if window.split is None else window.split[rows]
    variable_key = np.where(split < 0, _key_array("l", pt), _key_array("s", np.maximum(split, 0)))
    at = model.xyz.data[pt]
    projected, depth = model.project(img, at)
    step = 1e-4 * np.maximum(np.abs(depth), 1e-9)
    J = np.empty((len(rows), 2, 3))
    for axis in range(3):
        offset = np.zeros(3)
        offset[axis] = 1.0
        ahead = model.project(img, at + step[:, None] * offset)[0]
        behind = model.project(img, at - step[:, None] * offset)[0]
        J[:, :, axis] = (ahead - behind) / (2 * step[:, None])
    r = (projected - uv) / sigma[:, None]
    J = J / sigma[:, None, None]
    norm = np.linalg.norm(r, axis=1)
    w = np.where(norm <= huber_px, 1.0, huber_px / np.maximum(norm, 1e-12))
    valid = (depth > 0) & np.isfinite(r).all(axis=1) & np.isfinite(J).all(axis=(1, 2))
    w, J, r = np.where(valid, w, 0.0), np.where(valid[:, None, None], J, 0.0), np.where(valid[:, None], r, 0.0)
    keys, first, owner = np.unique(variable_key, return_index=True, return_inverse=True)
    H = sum_rows(owner, np.einsum("n,nia,nib->nab", w, J, J), len(keys))
    g = sum_rows(owner, np.einsum("n,nia,ni->na", w, J, r), len(keys))
    trace = np.trace(H, axis1=1, axis2=2)
    H += 1e-6 * trace[:, None, None] * np.eye(3)
    proper = trace > 0
    centre = at[first] - np.linalg.solve(np.where(proper[:, None, None], H, np.eye(3)), g[:, :, None])[:, :, 0]
    for key, c, information in zip(keys[proper].tolist(), centre[proper], H[proper]):
        graph.add(gtsam.PriorFactorPoint3(key, c, gtsam.noiseModel.Gaussian.Information(information)))


def _write_back(gtsam, model, result, optimised: list[int], points, window: _Window, sub_points,
                refined_cams: set, cal_kind: dict) -> list[str]:
    """Copy the optimised poses, points (a split point: the mean of its sub-points, weighted by their views)
    and refined calibrations into the model; returns a line per refined camera's focal change (logged: a
    guessed focal walking far in the first BAs is what makes them take 50 iterations)."""
    for i in optimised:
        pose = result.atPose3(gtsam.symbol("x", i))
        R = np.asarray(pose.rotation().matrix()).T
        model.R[i] = R
        model.t[i] = -R @ np.asarray(pose.translation())
    xyz = gtsam.utilities.extractPoint3(result)  # every Point3 in the values in key order: "l" before "s"
    if len(sub_points):
        slot = np.searchsorted(points, window.obs_pt)
        slot = np.where(window.split < 0, slot, len(points) + window.split)  # each view's variable
        views = np.bincount(slot, minlength=len(xyz)).astype(float)
        total = np.zeros((len(points), 3))
        owner = np.r_[np.arange(len(points)), np.searchsorted(points, sub_points)]
        np.add.at(total, owner, xyz * views[:, None])
        xyz = total / np.bincount(owner, weights=views, minlength=len(points))[:, None]
    model.xyz.data[points] = xyz
    focals = []
    for c in sorted(refined_cams):
        before = model.cameras[c].focal()
        cal = getattr(result, f"at{cal_kind[c]}")(gtsam.symbol("k", c))
        model.cameras[c].params = _params_from_calibration(model.cameras[c].model, cal)
        focals.append(f"camera {c} focal {before:.1f} -> {model.cameras[c].focal():.1f}")
    return focals


def _optimize(gtsam, graph, values, kind: str, iterations: int, relative_tolerance: float, ordering,
              initial_lambda: float):
    """(optimised values, iterations, initial cost, final cost); the costs are the optimizer's own, so that
    the graph is not evaluated twice more (~7 ms each for 12,500 observations). Ceres-style LM settings
    (diagonal damping, lambda starting at `initial_lambda`, factor 2): with GTSAM's legacy defaults a tiny
    lambda let the first steps of a two-view problem jump points behind the cameras, which the Sfm optimizer
    reports as an error. Plain LM gets the points-first `ordering` (a COLAMD ordering of the whole graph cost
    ~0.6 s per call on 5000 points) and solves by sequential Cholesky: multifrontal Cholesky, faster on a large
    survey, took far more memory on a dense orbit at no gain there (docs/benchmarks.md, "Pose order: COLAMD's");
    the Sfm optimizer builds its own Schur ordering. "pcg" is plain LM whose steps are solved by conjugate
    gradients preconditioned by the variables' diagonal blocks: where the cameras' system fills in (a dense orbit's
    long tracks join nearly every two of its cameras) a step costs a few products with the Jacobian instead of a
    dense factorisation, at the same cost reached (docs/benchmarks.md, "Bundle adjustment by conjugate
    gradients")."""
    if kind == "sfm":
        params = gtsam.SfmLevenbergMarquardtParams.ceresDefaults()
        params.setEliminationMode(gtsam.SfmEliminationMode.Schur)
        make = gtsam.SfmLevenbergMarquardtOptimizer
    elif kind in ("lm", "pcg"):
        params = gtsam.LevenbergMarquardtParams.CeresDefaults()
        if kind == "lm":
            params.setLinearSolverType("SEQUENTIAL_CHOLESKY")
        else:
            params.setLinearSolver(gtsam.NonlinearOptimizerParams.LinearSolverType.Iterative)
            solver = gtsam.PCGSolverParameters()
            solver.preconditioner = gtsam.BlockJacobiPreconditionerParameters()
            solver.maxIterations, solver.epsilon_rel = PCG_ITERATIONS, PCG_TOLERANCE
            params.setIterativeParams(solver)
        params.setOrdering(ordering)
        make = gtsam.LevenbergMarquardtOptimizer
    else:
        raise ValueError(f"unknown optimizer {kind!r}; use 'sfm', 'lm' or 'pcg'")
    params.setMaxIterations(iterations)
    params.setRelativeErrorTol(relative_tolerance)
    params.setlambdaInitial(initial_lambda)
    try:
        with _native_stdout_silenced():
            opt = make(graph, values, params)
            initial = opt.error()
            result = opt.optimize()
            return result, int(opt.iterations()), initial, opt.error()
    except RuntimeError:
        if kind != "sfm":
            raise
        # the Sfm optimizer raises (with no message) when a trial step puts a point behind a camera
        log.warning("SfmLevenbergMarquardtOptimizer failed; retrying this bundle adjustment with plain LM")
        return _optimize(gtsam, graph, values, "lm", iterations, relative_tolerance, ordering, initial_lambda)


PRIOR_CAUCHY_K = 3.0  # the Cauchy loss's width on a centre prior, in sigmas


def _add_center_priors(gtsam, graph, model, variable) -> bool:
    """A robust centre prior (see the module docstring) for each variable image with one, in a georeferenced
    model; True when they anchor the gauge (three or more, spread in two directions)."""
    if not model.georeferenced or model.priors is None:
        return False
    js, pos, sig = model.priors.in_model(model)
    keep = variable[js]
    js, pos, sig = js[keep], pos[keep], sig[keep]
    loss = gtsam.noiseModel.mEstimator.Cauchy.Create(PRIOR_CAUCHY_K)
    for j, p, s in zip(js.tolist(), pos, sig):
        noise = gtsam.noiseModel.Robust.Create(loss, gtsam.noiseModel.Diagonal.Sigmas(np.asarray(s, float)))
        graph.add(gtsam.GPSFactor(gtsam.symbol("x", j), np.asarray(p, float), noise))
    return spread_enough(pos, sig)


def _fix_gauge(gtsam, graph, model, variable, num_fixed_images) -> None:
    """Anchor the similarity gauge when constant images do not (see the module docstring)."""
    if num_fixed_images >= 2:
        return
    order = [i for i in model.registration_order if variable[i]]
    if not order:
        return
    if num_fixed_images == 0:
        first = order[0]
        pose = _pose3(gtsam, model.R[first], model.t[first])
        graph.add(gtsam.PriorFactorPose3(gtsam.symbol("x", first), pose,
                                         gtsam.noiseModel.Isotropic.Sigma(6, _TIGHT)))
        others = order[1:]
    else:
        others = order
    if not others:
        return
    second = others[0]
    centers = model.centers()
    anchor = model.registration_order[0]
    baseline_in_cam = model.R[second] @ (centers[second] - centers[anchor])
    axis = int(np.argmax(np.abs(baseline_in_cam)))
    sig = np.full(6, _LOOSE)
    pair_alone = num_fixed_images == 0 and len(order) == 2  # soft only there: see the module docstring
    sig[3 + axis] = max(float(np.linalg.norm(baseline_in_cam)), _TIGHT) if pair_alone else _TIGHT
    pose = _pose3(gtsam, model.R[second], model.t[second])
    graph.add(gtsam.PriorFactorPose3(gtsam.symbol("x", second), pose, gtsam.noiseModel.Diagonal.Sigmas(sig)))


@contextmanager
def _native_stdout_silenced():
    """GTSAM's C++ factors print every CheiralityException (a trial step, or a point behind a camera when the
    cost is evaluated) to stdout; the optimizer rejects such steps and the filters remove such points, so the
    lines are noise for the user (and would fill logs of long runs)."""
    sys.stdout.flush()
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)

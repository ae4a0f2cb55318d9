"""The one in-memory reconstruction type: cameras, image poses, 3D points and their observations, as numpy
arrays.

Images are addressed by their internal index (position in `image_ids`), points by a point id (row in the point
arrays), observations by an observation id. Deleted points and observations stay in the arrays with their
`alive` flag cleared, so ids never move while the mapper runs; `compacted()` is for writing out.
Poses are COLMAP's cam_from_world: x_cam = R @ X + t.

The observations of an image (`obs_of_kp`) and of a point (a chain through `obs_next`, from `point_first_obs`)
are indexed, and the observation counts per image and per point kept up to date, so that the queries the mapper
makes per registration cost in proportion to the images and points asked about, never to the whole model (at
300 images, scans of every observation were most of a registration's Python time). `scanned` counts the
entries those queries visit: the mapper's work count (sfm/incremental.py).
"""

from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from ..database import Correspondences
from ..geometry import camera as cammodel

COMPILED_MIN_VIEWS = 100_000  # views from which `Reconstruction.project` runs compiled (projection.py)
_UNDISTORT_TOLERANCE_PX = 1e-3  # a keypoint whose ray reprojects farther than this has no ray (see below)

PADDED_VIEWS = 250_000  # padded views handled at once (`padded_groups`): some 100 MB of arrays


@dataclass
class Camera:
    """One calibration shared by all images that use it. prior_focal: the focal the database started with, or
    the one the view graph calibrated (prior_calibrated: view_graph.calibrate_focals) in place of a guess."""

    model: str
    width: int
    height: int
    params: np.ndarray
    prior_trusted: bool = False
    prior_focal: float = 0.0
    prior_calibrated: bool = False

    @property
    def focal_kept(self) -> bool:
        """Whether the focal is one a single pair's or view's estimate does not replace: trusted (EXIF, given), or
        calibrated from the whole view graph (hundreds of pairs' fundamental matrices against one pair's)."""
        return self.prior_trusted or self.prior_calibrated

    def K(self) -> np.ndarray:
        return cammodel.calibration_matrix(self.model, self.params)

    def focal(self) -> float:
        return cammodel.focal_length(self.model, self.params)

    def set_focal(self, focal: float) -> None:
        """Scale fx and fy (or set f) so the mean focal length becomes `focal`."""
        p = self.params.copy()
        if cammodel.PARAM_NAMES[self.model][:2] == ("fx", "fy"):
            p[:2] *= focal / self.focal()
        else:
            p[0] = focal
        self.params = p


def _read_only(array: np.ndarray) -> np.ndarray:
    """A view of `array` that callers cannot write through: counts the model keeps up to date itself."""
    view = array.view()
    view.flags.writeable = False
    return view


def padded_slices(lengths: np.ndarray) -> Iterator[slice]:
    """Consecutive slices of items of these lengths (tracks, points' views), in the given order, each padded to
    its longest item at most PADDED_VIEWS views; an item longer than that makes a slice of its own."""
    budget, start = PADDED_VIEWS, 0
    while start < len(lengths):
        window = np.maximum.accumulate(lengths[start:start + budget])
        padded = np.arange(1, len(window) + 1) * window
        stop = start + max(1, int(np.searchsorted(padded, budget, side="right")))
        yield slice(start, stop)
        start = stop


def sum_rows(index: np.ndarray, values: np.ndarray, size: int) -> np.ndarray:
    """Rows of `values` summed by `index` into `size` rows: np.add.at's result, by np.bincount, many times
    faster."""
    flat = values.reshape(len(values), -1)
    out = np.stack([np.bincount(index, flat[:, c], minlength=size) for c in range(flat.shape[1])], axis=1)
    return out.reshape((size,) + values.shape[1:])


def images_and_cameras(corr: Correspondences) -> tuple[np.ndarray, list[str], np.ndarray, dict[int, Camera]]:
    """What both mappers start from: the database's image ids in ascending order (a model's internal index is the
    position in it), their names and camera ids, and a `Camera` per database camera whose prior focal is its
    starting one."""
    ids = sorted(corr.images)
    cameras = {cid: Camera(c.model, int(c.width), int(c.height), np.asarray(c.params, float),
                           bool(c.prior_trusted), 0.0) for cid, c in corr.cameras.items()}
    for cam in cameras.values():
        cam.prior_focal = cam.focal()
    return (np.array(ids, dtype=np.int64), [corr.images[i].name for i in ids],
            np.array([corr.images[i].camera_id for i in ids], dtype=np.int64), cameras)


def coverage(models: Iterable["Reconstruction"]) -> tuple[int, int]:
    """(images of the largest model, images of all models): which of two mappings of a set registered more."""
    sizes = [int(m.registered.sum()) for m in models]
    return max(sizes, default=0), sum(sizes)


def image_status(names: Sequence[str], keypoints: Sequence[np.ndarray], pairs: Iterable[tuple[int, int]],
                 models: Sequence["Reconstruction"], reason: Callable[[int], str]) -> dict:
    """Every image's entry of report.json: registered, in the first of `models` holding it, or unregistered with
    the reason. The reasons every mapper shares come first (no keypoints, no verified pair among `pairs`, image
    index pairs); `reason(i)` gives the mapper's own for the rest."""
    model_of = {}
    for k, m in enumerate(models):
        for i in np.flatnonzero(m.registered).tolist():
            model_of.setdefault(i, k)
    paired = np.zeros(len(names), bool)
    for a, b in pairs:
        paired[a] = paired[b] = True
    out = {}
    for i, name in enumerate(names):
        if i in model_of:
            out[name] = {"status": "registered", "model": model_of[i], "reason": None}
            continue
        if len(keypoints[i]) == 0:
            why = "no keypoints: a featureless image (blank, or out of focus)"
        elif not paired[i]:
            why = "no verified pairs with any other image"
        else:
            why = reason(i)
        out[name] = {"status": "unregistered", "model": None, "reason": why}
    return out


class _Buffer:
    """A numpy array that grows by amortised doubling; `.data` is a writable view of the filled rows."""

    def __init__(self, dtype, shape=()):
        self._a = np.zeros((16, *shape), dtype=dtype)
        self.n = 0

    def append(self, values) -> np.ndarray:
        values = np.asarray(values, dtype=self._a.dtype).reshape(-1, *self._a.shape[1:])
        need = self.n + len(values)
        if need > len(self._a):
            grown = np.zeros((max(need, 2 * len(self._a)), *self._a.shape[1:]), dtype=self._a.dtype)
            grown[:self.n] = self._a[:self.n]
            self._a = grown
        self._a[self.n:need] = values
        ids = np.arange(self.n, need)
        self.n = need
        return ids

    @property
    def data(self) -> np.ndarray:
        return self._a[:self.n]

    @classmethod
    def of(cls, array) -> "_Buffer":
        array = np.asarray(array)
        b = cls(array.dtype, array.shape[1:])
        b.append(array)
        return b


def _count(counts: np.ndarray, ids, sign: int) -> None:
    """Add `sign` to counts[k] once per occurrence of k in `ids`."""
    u, c = np.unique(ids, return_counts=True)
    counts[u] += sign * c


# keypoint scale bins of half an octave from 1 px (finer in the first, coarser than 2^4.5 px in the last), and the
# views a bin needs for its median error to count
_SCALE_BINS = 10
_MIN_BIN_VIEWS = 100


def scale_bins(scales: np.ndarray) -> np.ndarray:
    """Bin (0 .. _SCALE_BINS - 1) of each keypoint detection scale, half an octave wide from 1 px."""
    return np.clip(np.floor(2 * np.log2(np.maximum(scales, 1.0))), 0, _SCALE_BINS - 1).astype(np.int64)


class KeypointSet(list):
    """Per image (K_i, 2) pixels, COLMAP convention: views into one array (`flat`, image i's rows from
    `offset[i]`), so that keypoints of many images are gathered in one step. The mapper's models share one."""

    def __init__(self, keypoints: Sequence[np.ndarray], scales: Sequence[np.ndarray] | None = None):
        arrays = [np.asarray(k, dtype=float).reshape(-1, 2) for k in keypoints]
        self.offset = np.r_[0, np.cumsum([len(k) for k in arrays])].astype(np.int64)
        self.flat = np.concatenate(arrays) if arrays else np.zeros((0, 2))
        self.scale_flat = np.zeros(len(self.flat))
        if scales is not None:
            for a, b, s in zip(self.offset[:-1], self.offset[1:], scales):
                if len(s) == b - a:
                    self.scale_flat[a:b] = s
        super().__init__(self.flat[a:b] for a, b in zip(self.offset[:-1], self.offset[1:]))


class Reconstruction:
    """A model under construction. keypoints: per image (K_i, 2) pixels, COLMAP convention (a list, or a
    `KeypointSet` to share)."""

    def __init__(self, image_ids: Sequence[int] | np.ndarray, names: Sequence[str],
                 camera_of: Sequence[int] | np.ndarray,
                 cameras: dict, keypoints: Sequence[np.ndarray], num_tracks: int):
        self.image_ids = np.asarray(image_ids, dtype=np.int64)
        self.names = list(names)
        self.camera_of = np.asarray(camera_of, dtype=np.int64)
        self.cameras = {int(k): Camera(c.model, c.width, c.height, np.array(c.params, float), c.prior_trusted,
                                       c.prior_focal, c.prior_calibrated) for k, c in cameras.items()}
        self.keypoints = keypoints if isinstance(keypoints, KeypointSet) else KeypointSet(keypoints)
        n = len(self.image_ids)
        self.R = np.tile(np.eye(3), (n, 1, 1))
        self.t = np.zeros((n, 3))
        self.registered = np.zeros(n, bool)
        self.registration_order: list[int] = []
        # the observation of each keypoint (-1 for none): one array, `obs_of_kp[i]` a view of image i's part
        self.kp_offset = self.keypoints.offset
        self.obs_of_kp_flat = np.full(int(self.kp_offset[-1]), -1, np.int64)
        self.obs_of_kp = [self.obs_of_kp_flat[a:b] for a, b in zip(self.kp_offset[:-1], self.kp_offset[1:])]
        self.point_of_track = np.full(num_tracks, -1, np.int64)
        # registered views of each track when its retriangulation last failed (sfm/triangulate.py)
        self.tri_failed_views = np.zeros(num_tracks, np.int64)
        self.tri_failed_params = np.zeros(0)  # the cameras' parameters when tri_failed_views was last reset
        self.xyz = _Buffer(float, (3,))
        self.point_track = _Buffer(np.int64)
        self.point_alive = _Buffer(bool)
        self.obs_point = _Buffer(np.int64)
        self.obs_image = _Buffer(np.int64)
        self.obs_kp = _Buffer(np.int64)
        self.obs_alive = _Buffer(bool)
        self.obs_next = _Buffer(np.int64)  # the point's next observation (older), -1 at the end of its chain
        self.point_first_obs = _Buffer(np.int64)  # the newest observation of each point, -1 for none
        self.point_nobs = _Buffer(np.int64)  # alive observations of each point
        self.image_nobs = np.zeros(n, np.int64)  # alive observations of each image
        self.num_points = 0  # alive points
        self.changed_tracks: list = []  # track ids whose point was made or deleted, for `CandidateRanking`
        self.scanned = 0  # entries visited by queries (observations, keypoints, track elements): the work count
        self._normalized_cache: dict = {}
        self._ba_factors: tuple = (None, {})  # (loss width, observation -> GTSAM factor), sfm/bundle.py
        self.priors = None  # georef.CenterPriors of the images, or None
        self.georeferenced = False  # moved into the priors' frame: the BAs hold the centres to them (georef.py)
        self.lens_trials: dict = {}  # camera -> its last lens trial's record (sfm/lens.py), for report.json
        self.view_sigma_table = np.ones(_SCALE_BINS)  # a view's sigma (px) by keypoint scale bin (`scale_bins`)

    # ----- images -----
    def register(self, i: int, R: np.ndarray, t: np.ndarray) -> None:
        self.R[i], self.t[i] = R, t
        if not self.registered[i]:
            self.registered[i] = True
            self.registration_order.append(int(i))

    def registered_images(self) -> np.ndarray:
        return np.flatnonzero(self.registered)

    def deregister_empty_images(self) -> list[int]:
        """Deregister the images the filters left without any observation (their pose is no longer tied to
        the model, and a bundle adjustment cannot hold a variable without factors), as COLMAP's image filter
        does. Returns them."""
        empty = [int(i) for i in np.flatnonzero(self.registered & (self.image_nobs == 0))]
        for i in empty:
            self.registered[i] = False
            self.registration_order.remove(i)
        return empty

    def centers(self) -> np.ndarray:
        return -np.einsum("nji,nj->ni", self.R, self.t)

    def camera(self, i: int) -> Camera:
        return self.cameras[int(self.camera_of[i])]

    def set_camera_model(self, c: int, model: str, params: np.ndarray) -> None:
        """Give camera `c` another model (sfm/lens.py) or parameters; the bundle-adjustment factors stored for
        the old model's calibration class are dropped."""
        cam = self.cameras[int(c)]
        if cam.model != model:
            self._ba_factors = (None, {})
        cam.model, cam.params = model, np.array(params, float)

    def cameras_shared(self, images: np.ndarray | list[int], least: int = 3) -> bool:
        """Whether every camera of `images` is shared by `least` or more registered images: then the observations
        of all of them pin its focal, which the BAs lean on (ba_points_per_image_early,
        ba_shared_initial_lambda)."""
        users = np.bincount(self.camera_of[self.registered], minlength=int(self.camera_of.max()) + 1)
        return bool(np.all(users[self.camera_of[np.asarray(images, dtype=np.int64)]] >= least))

    def normalized_keypoints(self, i: int) -> np.ndarray:
        """Undistorted normalised coordinates of image i's keypoints, cached per camera parameter set.

        NaN where the current distortion has no inverse: past the fold of a strong barrel distortion fitted
        with too few coefficients, no ray projects to the keypoint, and Newton's last iterate is no ray.
        """
        cam = self.camera(i)
        key = (i, cam.model, tuple(np.round(cam.params, 12)))
        hit = self._normalized_cache.get(i)
        if hit is None or hit[0] != key:
            xy = cammodel.pixels_to_normalized(cam.model, cam.params, self.keypoints[i])
            back = cammodel.normalized_to_pixels(cam.model, cam.params,
                                                 cammodel.distort(cam.model, cam.params, xy))
            xy[~(np.linalg.norm(back - self.keypoints[i], axis=1) < _UNDISTORT_TOLERANCE_PX)] = np.nan
            hit = (key, xy)
            self._normalized_cache[i] = hit
        return hit[1]

    def keypoints_at(self, images: np.ndarray, kps: np.ndarray) -> np.ndarray:
        """Pixels (n, 2) of keypoints `kps` of `images` (arrays of one shape, any number of images at once)."""
        return self.keypoints.flat[self.kp_offset[images] + kps]

    def refresh_view_sigmas(self, fit_px: float) -> None:
        """Set `view_sigma_table` from the model's residuals: each scale bin's median reprojection error over
        the smallest bin median, at least 1, never falling from a bin to the next coarser one, on a grid of
        2^(1/4) steps. Why: a keypoint's position error grows with its detection scale, by a factor that depends
        on the images (steeply on rendered scenes, mildly on JPEG photos); weighting its view by its own bin's
        error is the weight the data shows, not a constant chosen on some scenes. Every view weighs alike (a
        table of ones) while the smallest bin median exceeds `fit_px`: then the residuals measure the model's
        misfit, not the keypoints. The mappers call it once a model has stopped growing, before its final
        refinement: weights during growth changed the global mapper's focal calibration from a guess
        (docs/benchmarks.md, "Views weighted by keypoint scale")."""
        obs = self.alive_observations()
        error, _ = self.reprojection_errors(obs)
        bins = scale_bins(self.keypoints.scale_flat[self.kp_offset[self.obs_image.data[obs]] + self.obs_kp.data[obs]])
        ok = np.isfinite(error)
        median = np.full(_SCALE_BINS, np.nan)
        for b in range(_SCALE_BINS):
            e = error[ok & (bins == b)]
            if len(e) >= _MIN_BIN_VIEWS:
                median[b] = np.median(e)
        if not np.isfinite(median).any() or not 0 < np.nanmin(median) <= fit_px:
            self.view_sigma_table = np.ones(_SCALE_BINS)
            return
        ratio = median / np.nanmin(median)
        for b in range(_SCALE_BINS):  # a bin with too few views takes its finer neighbour's value
            if not np.isfinite(ratio[b]):
                ratio[b] = ratio[b - 1] if b else 1.0
        ratio = np.maximum.accumulate(np.maximum(ratio, 1.0))
        self.view_sigma_table = 2.0 ** (np.round(4 * np.log2(ratio)) / 4)

    def view_sigma_levels(self, images: np.ndarray, kps: np.ndarray) -> np.ndarray:
        """(n,) standard deviation of keypoints `kps` of `images` in a bundle adjustment, their scale bin's entry of
        `view_sigma_table`, as integer quarter octaves (sigma = 2^(level/4) px, the table's grid) so that a BA's
        views share a few noise models; zeros, without reading the scales, while the table is all ones."""
        if (self.view_sigma_table == 1.0).all():
            return np.zeros(np.shape(images), np.int64)
        bins = scale_bins(self.keypoints.scale_flat[self.kp_offset[images] + kps])
        return np.round(4 * np.log2(self.view_sigma_table[bins])).astype(np.int64)

    def normalized_at(self, images: np.ndarray, kps: np.ndarray) -> np.ndarray:
        """`normalized_keypoints` (n, 2) of keypoints `kps` of `images`: grouped by image with one sort, as a mask
        per image over a global step's million observations cost images x observations."""
        images, kps = np.asarray(images, dtype=np.int64), np.asarray(kps, dtype=np.int64)
        out = np.empty((len(images), 2))
        order = np.argsort(images, kind="stable")
        uniq, start = np.unique(images[order], return_index=True)
        for i, a, b in zip(uniq.tolist(), start.tolist(), [*start[1:].tolist(), len(order)]):
            rows = order[a:b]
            out[rows] = self.normalized_keypoints(i)[kps[rows]]
        return out

    def ba_factor_cache(self, loss_width: float) -> dict:
        """Observation -> its bundle-adjustment factor, kept across calls: an observation's image, point,
        keypoint and camera never change, so only the loss width could make a stored factor stale."""
        if self._ba_factors[0] != loss_width:
            self._ba_factors = (loss_width, {})
        return self._ba_factors[1]

    # ----- points and observations -----
    def add_points(self, xyz: np.ndarray, tracks: np.ndarray, obs_point_local: np.ndarray,
                   obs_image: np.ndarray, obs_kp: np.ndarray) -> np.ndarray:
        """Add points with their observations; obs_point_local indexes into the new points. Returns point
        ids."""
        pids = self.xyz.append(xyz)
        self.point_track.append(tracks)
        self.point_alive.append(np.ones(len(pids), bool))
        self.point_first_obs.append(np.full(len(pids), -1, np.int64))
        self.point_nobs.append(np.zeros(len(pids), np.int64))
        self.num_points += len(pids)
        self.point_of_track[np.asarray(tracks, dtype=np.int64)] = pids
        self.changed_tracks.append(np.asarray(tracks, dtype=np.int64))
        self.add_observations(pids[np.asarray(obs_point_local, dtype=np.int64)], obs_image, obs_kp)
        return pids

    def add_observations(self, points: np.ndarray, images: np.ndarray, kps: np.ndarray) -> None:
        points, images, kps = (np.asarray(a, dtype=np.int64).ravel() for a in (points, images, kps))
        oids = self.obs_point.append(points)
        self.obs_image.append(images)
        self.obs_kp.append(kps)
        self.obs_alive.append(np.ones(len(oids), bool))
        self.obs_next.append(np.full(len(oids), -1, np.int64))
        self._chain(points, oids)
        _count(self.point_nobs.data, points, 1)
        _count(self.image_nobs, images, 1)
        self.obs_of_kp_flat[self.kp_offset[images] + kps] = oids

    def _chain(self, points, oids) -> None:
        """Put the new observations `oids` of `points` at the head of their points' chains."""
        order = np.argsort(points, kind="stable")
        p, o = points[order], oids[order]
        nxt = np.empty(len(o), np.int64)
        last = np.r_[p[1:] != p[:-1], True] if len(p) else np.zeros(0, bool)
        first = np.r_[True, p[1:] != p[:-1]] if len(p) else np.zeros(0, bool)
        nxt[:-1] = o[1:]
        nxt[last] = self.point_first_obs.data[p[last]]
        self.obs_next.data[o] = nxt
        self.point_first_obs.data[p[first]] = o[first]

    def remove_observations(self, obs: np.ndarray) -> None:
        """Drop observations; points that keep fewer than two are deleted with their remaining observation."""
        obs = np.asarray(obs, dtype=np.int64)
        obs = obs[self.obs_alive.data[obs]]
        if len(obs) == 0:
            return
        self._clear_observations(obs)
        touched = np.unique(self.obs_point.data[obs])
        self.delete_points(touched[self.point_nobs.data[touched] < 2])

    def _clear_observations(self, obs) -> None:
        self.obs_alive.data[obs] = False
        images, kps = self.obs_image.data[obs], self.obs_kp.data[obs]
        _count(self.point_nobs.data, self.obs_point.data[obs], -1)
        _count(self.image_nobs, images, -1)
        self.obs_of_kp_flat[self.kp_offset[images] + kps] = -1

    def delete_points(self, pids: np.ndarray) -> None:
        pids = np.asarray(pids, dtype=np.int64)
        pids = pids[self.point_alive.data[pids]]
        if len(pids) == 0:
            return
        pids = np.unique(pids)
        obs = self.observations_of_points(pids)
        self.point_alive.data[pids] = False
        self.num_points -= len(pids)
        self.point_of_track[self.point_track.data[pids]] = -1
        self.changed_tracks.append(self.point_track.data[pids])
        self._clear_observations(obs)

    def alive_observations(self) -> np.ndarray:
        self.scanned += self.obs_alive.n
        return np.flatnonzero(self.obs_alive.data)

    def observations_changed(self, refine: Callable[[], None]) -> tuple[int, int]:
        """(observations `refine()` added or removed, observations alive before it): the measure of a refinement
        round's change that COLMAP's iterative global refinement stops on."""
        alive_before, n_before = self.obs_alive.data.copy(), self.obs_alive.n
        refine()
        changed = (self.obs_alive.n - n_before) + int((alive_before & ~self.obs_alive.data[:n_before]).sum())
        return changed, int(alive_before.sum())

    def alive_points(self) -> np.ndarray:
        self.scanned += self.point_alive.n
        return np.flatnonzero(self.point_alive.data)

    def point_num_observations(self) -> np.ndarray:
        """Alive observations of every point (a read-only view of the kept counts)."""
        return _read_only(self.point_nobs.data)

    def image_num_observations(self) -> np.ndarray:
        """Alive observations of every image, 0 for one not registered (a read-only view of the kept counts)."""
        return _read_only(self.image_nobs)

    def observations_of_images(self, images: np.ndarray | list[int]) -> np.ndarray:
        """Alive observation ids made in any of `images`, ascending."""
        images = np.unique(np.asarray(images, dtype=np.int64))
        if len(images) == 0:
            return np.zeros(0, np.int64)
        ids = np.concatenate([self.obs_of_kp[i] for i in images.tolist()])
        self.scanned += len(ids)
        return np.sort(ids[ids >= 0])

    def observations_of_points(self, pids: np.ndarray) -> np.ndarray:
        """Alive observation ids of the points `pids`, ascending: their chains, followed in steps over all of
        them at once (as many steps as the longest chain)."""
        cur = self.point_first_obs.data[np.unique(np.asarray(pids, dtype=np.int64))]
        cur = cur[cur >= 0]
        found = []
        while len(cur):
            self.scanned += len(cur)
            found.append(cur[self.obs_alive.data[cur]])
            cur = self.obs_next.data[cur]
            cur = cur[cur >= 0]
        return np.sort(np.concatenate(found)) if found else np.zeros(0, np.int64)

    def padded_observations(self, pids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(points, obs, mask): the given points that have alive observations, and their observation ids as
        rows of an (n, k) array padded where `mask` is False (the layout of geometry.triangulation)."""
        obs = self.observations_of_points(pids)
        op = self.obs_point.data[obs]
        order = np.argsort(op, kind="stable")
        obs, op = obs[order], op[order]
        points, start, count = np.unique(op, return_index=True, return_counts=True)
        kmax = int(count.max()) if len(count) else 0
        rows = np.repeat(np.arange(len(points)), count)
        cols = np.arange(len(op)) - np.repeat(start, count)
        padded = np.zeros((len(points), kmax), np.int64)
        mask = np.zeros((len(points), kmax), bool)
        padded[rows, cols] = obs
        mask[rows, cols] = True
        return points, padded, mask

    def padded_groups(self, pids: np.ndarray) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """`padded_observations` of `pids` in groups of at most PADDED_VIEWS padded views (one group for a point
        longer than that), the points ordered by track length: padded together, one long track makes every
        point as long, which in a long forward-moving sequence is hundreds of views for every point."""
        pids = np.asarray(pids, dtype=np.int64)
        lengths = self.point_num_observations()[pids]
        order = np.argsort(lengths, kind="stable")
        pids, lengths = pids[order], lengths[order]
        for part in padded_slices(lengths):
            yield self.padded_observations(pids[part])

    # ----- errors and statistics -----
    def project(self, images: np.ndarray, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (n,2) and depths (n,) of points xyz (n,3) in images (n,), with each image's camera model. From
        `COMPILED_MIN_VIEWS` views on, in a model without a fisheye, in one compiled pass (projection.py), numba
        loaded at the first such call: below that the numpy passes cost less than loading numba, which a small
        set's whole run never needs (docs/benchmarks.md, "Every view projected in one compiled pass, and the BA
        points chosen by two sorts")."""
        images = np.asarray(images, dtype=np.int64)
        if len(images) >= COMPILED_MIN_VIEWS:
            ids = sorted(self.cameras)
            lenses = [(self.cameras[c].model, self.cameras[c].params) for c in ids]
            if all(model != "OPENCV_FISHEYE" for model, _ in lenses):
                from .projection import project_views  # noqa: PLC0415 - numba, for large models only

                return project_views(self.R, self.t, images, xyz, np.searchsorted(ids, self.camera_of), lenses)
        Xc = np.einsum("nij,nj->ni", self.R[images], xyz) + self.t[images]
        uv = np.full((len(images), 2), np.nan)
        cams = self.camera_of[images]
        for cid in np.unique(cams):
            m = cams == cid
            cam = self.cameras[int(cid)]
            uv[m] = cammodel.project(cam.model, cam.params, Xc[m])
        return uv, Xc[:, 2]

    def reprojection_errors(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Reprojection error (px; inf behind the camera) and depth of each observation id."""
        obs = np.asarray(obs, dtype=np.int64)
        images = self.obs_image.data[obs]
        uv, depth = self.project(images, self.xyz.data[self.obs_point.data[obs]])
        kp = self.keypoints_at(images, self.obs_kp.data[obs])
        err = np.linalg.norm(uv - kp, axis=1)
        err[~np.isfinite(err) | (depth <= 0)] = np.inf
        return err, depth

    def stats(self) -> dict:
        """Counts and errors. The mean reprojection error is COLMAP's (the mean over points of each point's
        mean error), so it is the number pycolmap reports for the written model; a mean over observations
        weighs long tracks more and came out 15% higher on the demo scene."""
        obs = self.alive_observations()
        pts = self.alive_points()
        err = self.reprojection_errors(obs)[0] if len(obs) else np.zeros(0)
        mean_error = float("nan")
        if len(err):
            pid = self.obs_point.data[obs]
            per_point = np.bincount(pid, weights=err)[pts] / np.bincount(pid)[pts]
            mean_error = float(np.mean(per_point))
        return {"registered": int(self.registered.sum()), "points": int(len(pts)),
                "observations": int(len(obs)),
                "mean_track_length": float(len(obs) / len(pts)) if len(pts) else 0.0,
                "mean_reprojection_error_px": mean_error}

    # ----- snapshots -----
    _ARRAYS = ("image_ids", "camera_of", "R", "t", "registered", "point_of_track", "tri_failed_views",
               "tri_failed_params")
    _BUFFERS = ("xyz", "point_track", "point_alive", "obs_point", "obs_image", "obs_kp", "obs_alive")

    def state(self) -> dict:
        """Everything needed to rebuild the model (see `from_state`), as plain arrays and lists."""
        s = {k: getattr(self, k).copy() for k in self._ARRAYS}
        s.update({k: getattr(self, k).data.copy() for k in self._BUFFERS})
        s["names"] = list(self.names)
        s["registration_order"] = list(self.registration_order)
        s["priors"], s["georeferenced"] = self.priors, self.georeferenced
        s["lens_trials"] = dict(self.lens_trials)
        s["view_sigma_table"] = self.view_sigma_table.copy()
        s["cameras"] = {k: (c.model, c.width, c.height, c.params.copy(), c.prior_trusted, c.prior_focal,
                            c.prior_calibrated) for k, c in self.cameras.items()}
        return s

    def restore(self, s: dict) -> None:
        """Return to an earlier `state()` of this model (a trial undone)."""
        self.__dict__.update(type(self).from_state(s, self.keypoints).__dict__)

    @classmethod
    def from_state(cls, s: dict, keypoints: list[np.ndarray]) -> "Reconstruction":
        cams = {k: Camera(*v) for k, v in s["cameras"].items()}
        m = cls(s["image_ids"], s["names"], s["camera_of"], cams, keypoints, len(s["point_of_track"]))
        for k in cls._ARRAYS:
            if k in s:  # a snapshot from before tri_failed_views keeps the zeros (every track retried once)
                setattr(m, k, s[k].copy())
        for k in cls._BUFFERS:
            setattr(m, k, _Buffer.of(s[k]))
        m.registration_order = list(s["registration_order"])
        m.priors, m.georeferenced = s.get("priors"), bool(s.get("georeferenced", False))
        m.lens_trials = dict(s.get("lens_trials", {}))
        m.view_sigma_table = np.array(s.get("view_sigma_table", np.ones(_SCALE_BINS)), float)
        # the indexes of the alive observations (`add_observations` keeps them up to date)
        m.obs_next = _Buffer.of(np.full(m.obs_point.n, -1, np.int64))
        m.point_first_obs = _Buffer.of(np.full(m.xyz.n, -1, np.int64))
        m.point_nobs = _Buffer.of(np.zeros(m.xyz.n, np.int64))
        m.num_points = int(m.point_alive.data.sum())
        obs = m.alive_observations()
        points, images = m.obs_point.data[obs], m.obs_image.data[obs]
        m._chain(points, obs)
        _count(m.point_nobs.data, points, 1)
        _count(m.image_nobs, images, 1)
        m.obs_of_kp_flat[m.kp_offset[images] + m.obs_kp.data[obs]] = obs
        return m

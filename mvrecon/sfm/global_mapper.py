"""The global mapper (`--mapper global`): all cameras at once from the view graph, then the points and a global BA.

GLOMAP's pipeline on GTSAM and the incremental mapper's own parts:
1. View graph (view_graph.py): guessed focal lengths calibrated from the pairs' fundamental matrices, then one
   relative pose per verified pair (pair_poses.py); a guessed focal the pairs cannot tell is refined by coarse
   global models first (where those from the guess keep few images, from a wide lens's focal too, `lens.WIDE_TRY`:
   from the 768 px guess for a 100 deg lens's 269 they kept 5-7 of 12), and in a set of `_SUBSET_LENS_MIN_IMAGES`
   images or more by a model of a subset of them too, focal and distortion (`_lens_from_subset`). A set where half
   the images or more are each the only image of their camera is mapped with those focals at the guess and again
   with them calibrated too, and the calibrated mapping is kept unless the other fits clearly more observations
   within the BAs' Huber width (`_single_cameras_calibrated`).
2. Rotation averaging (rotation_averaging.py): robust initialisation, L1-IRLS, `gtsam.ShonanAveraging3`;
   pairs whose rotation disagrees by more than 5 degrees are outliers; the largest consistent component is a
   model.
3. Camera centres: global positioning (global_positioning.py, GLOMAP's): centres and points at once from the
   tracks' rays turned into the world frame, from a random start, from centres placed in turn and, where those
   leave a camera out, from translation averaging's centres (only then computed), the solution of lowest cost
   kept. The coarse models that calibrate a guessed focal take theirs from
   translation averaging (translation_averaging.py: the pairs' directions, `gtsam.MFAS`,
   `gtsam.TranslationRecovery`) instead: tracks fit a focal far off as well as the right one (on templeSparseRing,
   768 px for the true 1520, a coarse model from tracks moved the focal by 1%, one from pairs to 1100). Measured
   on the same databases, tracks against pairs for the final model (AUC@5): templeSparseRing 0.741 against
   0.156, herzjesu 0.940 and 0.940, templeRing 0.847 and 0.849, street (a camera moving straight ahead) 0.994
   and 0.994, object_orbit_small 0.988 and 0.993.
4. Tracks (tracks.py) triangulated (triangulate.py) in rounds with the reprojection gate narrowing from 8 px to
   the config's, each round followed by a global bundle adjustment (bundle.py: the incremental mapper's factors,
   intrinsics refined as there) and the filters (filtering.py), the last rounds repeated until the model stops
   changing. The bundle adjustments optimise the points seen
   by three images or more, as GLOMAP's (`ba_points.long_points`); the two-view points are re-fitted to their
   poses. A loop whose two ends met apart (sfm/loop_closure.py) is closed by a similarity pose graph after the
   first round or, where that round's filters took out the images at the gap, once they are registered again,
   the rotations held; and again before the final rounds, the rotations free (`_close_open_loop`).
5. Catastrophic poses: a camera whose rays miss the points of its tracks after global positioning
   (`global_positioning.outlier_cameras`), and an image that keeps too few observations fitting within the gate
   after the rounds (fewer than abs_pose_min_inliers, or under abs_pose_min_inlier_ratio of its triangulated
   matches, or fewer than `_BA_MIN_HOLD` of points two other images see too), are taken out of the model with
   that reason and the model is refined again, rather than written at a flipped or far-away pose; each may come
   back by absolute pose against the points.
6. While the first models' bundle adjustment moves the calibration the view graph was estimated at by more than
   a pair's inlier threshold in the image and its focal by more than `_RECALIBRATION_FOCAL_CHANGE` (a guessed
   focal found only near), the view graph is estimated again at the refined calibration and the models are made
   again from it (at most `_RECALIBRATIONS` times).
7. The camera model chosen from the data (`choose_lens`, the model left open; sfm/lens.py): each
   finished model tries its cameras with the richer models, and a switch maps everything again from the chosen
   lens, as every pose came from relative poses at the old one (fisheye_orbit_small: AUC@5 0.00 -> 0.99); that
   mapping is kept unless it registers fewer images.
A consistent view graph of fewer than three images (a single pair) is no model: its images say so.
The images the first model leaves (other components of the view graph, or images whose pairs were outliers)
are mapped again as the next model, as the incremental mapper starts new models; every image left
unregistered gets a reason.
"""

import logging
import time
from dataclasses import replace

import numpy as np

from ..database import Correspondences
from ..progress import progress
from . import filtering, lens
from .ba_points import held_observations, long_points, select_points
from .bundle import bundle_adjust
from .config import MapperConfig
from .georef import CenterPriors, georeference
from .global_positioning import global_positions, outlier_cameras
from .incremental import MappingResult
from .loop_closure import close_open_loop
from .model import KeypointSet, Reconstruction, coverage, image_status, images_and_cameras
from .pair_poses import COARSE_SAMPLE, relative_poses
from .register import register_image
from .rotation_averaging import average_rotations
from .tracks import build_tracks
from .translation_averaging import average_translations
from .triangulate import continue_points, refine_existing_points, retriangulate, triangulate_tracks
from .view_graph import (
    calibratable_cameras,
    calibrate_focals,
    calibration_shift_px,
    dense_subset,
    matches_per_image,
    oriented_pairs,
)

log = logging.getLogger("mvrecon.sfm")
# reprojection gate of the first round, before the config's own (4 px), and of the coarse models: with a wider
# start (16 px, then 8) facade_small ended at AUC@5 0.80 instead of 0.89, facade_bricks_small 0.39 instead of 0.48
_GATES_PX = (8.0,)
_COARSE_GATE_PX = 16.0
# views of the points a bundle adjustment optimises (GLOMAP's min_track_length), except in an image with fewer
# than `_BA_MIN_HOLD` observations of such points, which keeps its two-view points too (`ba_points.long_points`):
# a pose held by fewer views is all but free. facade_bricks_small AUC@5 0.43 with 6, 0.30 with 30
# (abs_pose_min_inliers)
_BA_MIN_VIEWS = 3
_BA_MIN_HOLD = 6
_COARSE_ITERATIONS = 15  # LM iterations of a coarse model's BA
_FINAL_ROUNDS = 5  # final rounds of retriangulation, BA and filtering (`_refine`): COLMAP's iterative global
_FINAL_MIN_CHANGE = 0.0005  # refinement, until a round adds and removes under this share of the observations
_START_HUBER_PX = 1.0  # Huber width of the BAs from the averaging's poses, pixels off (`_bundle`)
_FINAL_ITERATIONS = 1  # LM iterations of the BA over every point, from converged subset poses (`_refine`)
# images from which a model's first round takes _START_POINTS_PER_IMAGE and its final BA over every point is brief
# (`_refine`): the savings are at scale, and a 16-image sparse ring's AUC@5 moved by 0.02-0.06 with either
_LARGE_MODEL = 100
# points per image of a large model's first BA (`_bundle`'s `early`): it takes most of the LM iterations, each costing
# about in proportion to its points, and only brings the poses near; the next rounds take ba_points_per_image
# (docs/benchmarks.md, "Global mapper: a large model's first BA on 50 points an image")
_START_POINTS_PER_IMAGE = 50
_CALIBRATION_PASSES = 3  # coarse models that refine a guessed focal (`_calibrate_by_bundle`)
_CALIBRATION_IMAGES = 60  # images of the coarse models (`_calibration_pairs`)
_SUBSET_LENS_MIN_IMAGES = 3 * _CALIBRATION_IMAGES  # a set this large gets its lens from a subset's model first
_MAX_ROTATION_ERROR_DEG = 5.0  # GLOMAP's threshold on a pair's rotation residual
_MIN_VIEWS = 3  # images of a consistent view graph the mapper makes a model of
_RECALIBRATIONS = 2  # view graphs again at a model's refined calibration (`_recalibrated`)
# share of its observations by which the mapping with one-image cameras held at their guess must fit more within the
# Huber width than the one the view graph calibrates to be kept (`_single_cameras_calibrated`): the seed alone moves
# one mapping's count by a standard deviation of 0.3% (imc_reichstag, seeds 0-7)
_HELD_FIT_MARGIN = 0.005
_REGISTRATION_ROUNDS = 5  # absolute-pose registration rounds of the images a model leaves (`_refine`)
# ... only when the refined focal is this far (relative) from the view graph's: where it moved 8-15% (toy_object_small,
# opensfm_lund twice) the view graph again gained 0.10-0.36 AUC@5; where it moved 2-3% (aerial_survey 300,
# street_long_small) it gained nothing and cost 1.8x the mapping (aerial_survey 300: 327 CPU s against 180, AUC@5
# 0.9971 either way)
_RECALIBRATION_FOCAL_CHANGE = 0.05
_LOOP_GAP = 10.0  # camera spacings between a hinge's two poses: the ends of a loop met apart (`_close_open_loop`)
_LOOP_VIEWS_TOLERANCE = 0.02  # share of the views a first-round loop closure may lose (`_close_open_loop`)
_MAX_DIRECTION_ERROR_DEG = 10.0  # a translation direction this far off the solved baseline is dropped
# where the final model's centres come from: "tracks" (global_positioning.py) or "pairs" (translation
# averaging, which the coarse models that calibrate a guessed focal always use); "pairs" is kept for
# tools/bench_global_mapper.py's comparison of the two
POSITIONS = "tracks"


class GlobalMapper:
    def __init__(self, corr: Correspondences, config: MapperConfig = MapperConfig(), workers: int = 1,
                 choose_lens: bool = False):
        self.config = config
        self.choose_lens = choose_lens  # the cameras' models were left open: sfm/lens.py may change them
        self.workers = workers  # processes of the view graph's relative poses, threads of global positioning's starts
        self.image_ids, self.names, self.camera_of, self.cameras = images_and_cameras(corr)
        ids = self.image_ids.tolist()
        self.keypoints = KeypointSet([np.asarray(corr.keypoints.get(i, np.zeros((0, 2))), float) for i in ids],
                                     [corr.keypoint_scales.get(i, np.zeros(0)) for i in ids])
        self.pairs = oriented_pairs(self.image_ids, corr.pairs)
        self.tracks = build_tracks(self.image_ids, [len(k) for k in self.keypoints], corr.pairs)
        self.reasons: dict[int, str] = {}
        self.priors = CenterPriors.of(corr.priors)  # camera position priors (georef.py), None without
        self.ba_calls, self.ba_seconds = 0, 0.0
        self.seconds: dict[str, float] = {}
        self.calibrate_single = False  # the view graph calibrates the cameras of a single image too (`run`)

    def _clock(self, name: str, start: float) -> float:
        now = time.perf_counter()
        self.seconds[name] = self.seconds.get(name, 0.0) + now - start
        return now

    def run(self) -> MappingResult:
        bar = progress(total=len(self.image_ids), desc="mapping", unit="img")
        models, graph = self._map_all(self.cameras, bar)
        if self._mostly_single_cameras():
            bar.close()
            bar = progress(total=len(self.image_ids), desc="mapping with one-image cameras calibrated", unit="img")
            models, graph = self._single_cameras_calibrated(models, graph, bar)
        chosen = lens.switched_cameras(models) if self.choose_lens else {}
        if chosen:  # the view graph and the averaged poses came from the old model's undistortion: again
            cameras = {c: replace(cam) for c, cam in self.cameras.items()}
            for c, (model, params, _) in chosen.items():
                cameras[c] = replace(cameras[c], model=model, params=params, prior_trusted=True)
                cameras[c].prior_focal = cameras[c].focal()
                log.info("camera %d: mapped again as %s (%s)", c, model, np.round(params, 4).tolist())
            first = (models, graph, self.reasons)
            self.reasons, self.choose_lens = {}, False
            bar.close()
            bar = progress(total=len(self.image_ids), desc="mapping with the lens chosen", unit="img")
            models, graph = self._map_all(cameras, bar)
            for m in models:
                for c in np.unique(m.camera_of[m.registered]).tolist():
                    if c in chosen:
                        m.cameras[c].prior_trusted = False  # calibrated here, as the first mapping left it
                        m.lens_trials[c] = chosen[c][2]
            if coverage(models) < coverage(first[0]):
                log.info("mapped again with the lens chosen: %s images against %s; the first models are kept",
                         coverage(models), coverage(first[0]))
                models, graph, self.reasons = first
        bar.close()
        models.sort(key=lambda m: -int(m.registered.sum()))
        return MappingResult(models, self._status(models),
                             {"tracks": len(self.tracks), "split_inconsistent_tracks": self.tracks.split_inconsistent,
                              "ba_calls": self.ba_calls, "ba_seconds": self.ba_seconds,
                              "view_graph_edges": len(graph.edges),
                              "seconds": {k: round(v, 3) for k, v in self.seconds.items()}})

    def _mostly_single_cameras(self) -> bool:
        """Whether half the images or more are each the only image of a camera with a guessed focal (photos from
        many cameras), where `_single_cameras_calibrated` maps the set again: with fewer such images the choice
        moves few poses, and a large set with one odd image (a screenshot, a crop) is not mapped twice."""
        single = calibratable_cameras(self.cameras, self.camera_of, single=True) \
            - calibratable_cameras(self.cameras, self.camera_of)
        return len(single) > 0 and 2 * len(single) >= len(self.image_ids)

    def _single_cameras_calibrated(self, models: list[Reconstruction], graph, bar) -> tuple[list, object]:
        """The models and view graph of the set mapped again with the view graph calibrating the guessed focals
        of the cameras of a single image too (`calibrate_single`), unless `models` (mapped with those focals at
        their guess) register more images, or as many with more observations within the BAs' Huber width
        (`_fitted_observations`) by over `_HELD_FIT_MARGIN` of their observations. Neither start wins
        everywhere: a camera per photo from a ring of views at a zoom of 0.5-2x misplaced two images when
        calibrated, at 0.4-2.5x twelve when held. A focal a fifth off costs an image few observations but shifts
        its residuals, so half a pixel tells the two mappings apart where the count of observations does not;
        a difference within what the seed alone moves is no evidence, and there the calibration, GLOMAP's way,
        is kept: over 31 mappings of imc_reichstag and the ring's variants, the kept model's AUC@5 fell short of
        the better one's by 0.015 in all with the margin, 0.114 without (one left out, where the images
        registered decide, wrongly either way; docs/benchmarks.md, "Global mapper: the calibrated mapping
        unless the held one fits clearly more"). Such a set is mapped twice."""
        reasons = self.reasons
        self.reasons, self.calibrate_single = {}, True
        again, again_graph = self._map_all(self.cameras, bar)
        fit, first_fit = [(*coverage(ms), self._fitted_observations(ms)) for ms in (again, models)]
        margin = int(_HELD_FIT_MARGIN * sum(len(m.alive_observations()) for m in models))
        kept = fit[:2] > first_fit[:2] or (fit[:2] == first_fit[:2] and fit[2] + margin >= first_fit[2])
        log.info("mapped again with the cameras of one image calibrated by the view graph: %s images and %d "
                 "observations within %g px against %s and %d; %s", fit[:2], fit[2], self.config.global_huber_px,
                 first_fit[:2], first_fit[2], "kept" if kept else "the first models are kept")
        if kept:
            return again, again_graph
        self.reasons, self.calibrate_single = reasons, False
        return models, graph

    def _fitted_observations(self, models: list[Reconstruction]) -> int:
        """The observations of `models` whose reprojection error is within the BAs' Huber width (the config's
        global_huber_px): those the bundle adjustment fits as exact."""
        return sum(int((m.reprojection_errors(m.alive_observations())[0] <= self.config.global_huber_px).sum())
                   for m in models)

    def _map_all(self, cameras: dict, bar) -> tuple[list[Reconstruction], object]:
        """(models, view graph) of every image from the starting `cameras`: the view graph calibrated and
        estimated, then a model per consistent component (see the module docstring)."""
        scratch = self._calibrated(cameras)
        start = time.perf_counter()
        reasons = dict(self.reasons)
        graph = relative_poses(scratch, self.pairs, self.config, workers=self.workers)
        start = self._clock("view_graph", start)
        models = self._models(scratch.cameras, graph)
        # the view graph again at the calibration the models' bundle adjustment found, while it moves the image
        # points more than a pair's inlier threshold and the focal by over 5% (`_recalibrated`): relative poses at
        # a focal that far off hold biases that averaging turns into drift (toy_object_small, a guessed focal the
        # coarse models left at 788 px for the true 667: AUC@5 0.66 without this, 0.76 with it; about 2x the
        # mapping time)
        for _ in range(_RECALIBRATIONS):
            if self.choose_lens and lens.switched_cameras(models):
                break  # `run` maps everything again from the lens chosen, and may recalibrate there
            changed = self._recalibrated(scratch.cameras, models)
            if not changed:
                break
            for c, cam in changed.items():
                log.info("camera %d: the view graph again at %s %s (was %s)", c, cam.model,
                         np.round(cam.params, 4).tolist(), np.round(scratch.cameras[c].params, 4).tolist())
                scratch.cameras[c] = cam
            start = time.perf_counter()
            graph = relative_poses(scratch, self.pairs, self.config, workers=self.workers)
            start = self._clock("view_graph", start)
            self.reasons = dict(reasons)
            models = self._models(scratch.cameras, graph)
        bar.update(sum(int(m.registered.sum()) for m in models))
        self._clock("models", start)
        return models, graph

    def _calibrated(self, cameras: dict) -> Reconstruction:
        """An empty model of the starting `cameras` with the guessed focals calibrated for the view graph: by the
        pairs' fundamental matrices, then where they cannot tell by coarse models, and in a large set the lens
        from a subset's model (see the module docstring); its time counts as the calibration's."""
        start = time.perf_counter()
        scratch = self._new_model(cameras)
        found = calibrate_focals(scratch, self.pairs, self.config.seed, self.calibrate_single)
        # a focal the view graph could not calibrate is found by coarse models first, from rougher relative poses
        # of the pairs of a bounded, well-connected set of images (`_calibration_pairs`); not a camera of a single
        # image, which no coarse model refines (`_calibrate_by_bundle`)
        uncalibrated = sorted(calibratable_cameras(scratch.cameras, self.camera_of) - set(found))
        if uncalibrated:
            sample = self._calibration_pairs(uncalibrated)
            fit = self._calibrate(scratch, sample)
            # a guessed focal may be a wide lens's: when the guess's coarse model kept few of the images, one from a
            # wide focal too, kept where it fits better, whichever model the lens has (a lens named OPENCV or
            # OPENCV_FISHEYE with no focal is as likely wide as one left open)
            if fit[0] < lens.WIDE_TRY * len(np.unique(np.array(list(sample)))):
                other = self._new_model(cameras)
                for c in uncalibrated:
                    other.cameras[c].set_focal(lens.WIDE_FOCAL * max(other.cameras[c].width, other.cameras[c].height))
                wide_fit = self._calibrate(other, sample)
                better = lens.fits_better(wide_fit, fit)
                log.info("coarse model from a wide focal: %d images, %d observations within the gate, against %d "
                         "and %d from the guess; %s", *wide_fit, *fit, "kept" if better else "not kept")
                for c in uncalibrated if better else []:
                    scratch.cameras[c] = other.cameras[c]
        if len(self.image_ids) >= _SUBSET_LENS_MIN_IMAGES:
            self._lens_from_subset(scratch)
        self._clock("calibration", start)
        return scratch

    def _models(self, cameras, graph) -> list[Reconstruction]:
        """The models of the view graph, largest first: the largest consistent component, then the largest of
        the images it leaves, as the incremental mapper starts new models."""
        for (a, b), why in graph.rejected.items():
            for i in (a, b):
                self.reasons.setdefault(i, f"its pairs gave no relative pose: the pair with "
                                           f"{self.names[b if i == a else a]} has {why}")
        models = []
        left = np.ones(len(self.image_ids), bool)
        while len(models) < self.config.max_models:
            keys = [k for k in graph.edges if left[k[0]] and left[k[1]]]
            if not keys:
                break
            m, used = self._map_component(cameras, graph, keys, left)
            left[used] = False
            if m is None:
                continue
            if int(m.registered.sum()) >= self.min_model_size():
                models.append(m)
            else:
                for i in m.registered_images().tolist():
                    self.reasons[i] = (f"its model stayed at {int(m.registered.sum())} images, under "
                                       f"min_model_size {self.min_model_size()}, and was discarded")
        models.sort(key=lambda m: -int(m.registered.sum()))
        return models

    def _recalibrated(self, cameras: dict, models: list[Reconstruction]) -> dict:
        """Camera id -> the calibration the largest model holding `focal_min_images` of its images refined it to,
        for the cameras whose refined calibration moves a point of the image by more than two_view_max_error_px
        (a pair's inlier threshold) from where the view graph's calibration put it, and whose focal moved by more
        than `_RECALIBRATION_FOCAL_CHANGE`."""
        out = {}
        for c, before in cameras.items():
            for m in models:
                if int((m.registered & (m.camera_of == c)).sum()) >= self.config.focal_min_images:
                    if calibration_shift_px(before, m.cameras[c]) > self.config.two_view_max_error_px and \
                            abs(m.cameras[c].focal() / before.focal() - 1) > _RECALIBRATION_FOCAL_CHANGE:
                        out[c] = replace(m.cameras[c], params=m.cameras[c].params.copy())
                    break
        return out

    def min_model_size(self) -> int:
        """As the incremental mapper's: min(min_model_size, 0.8 x the number of images, rounded down)."""
        return min(self.config.min_model_size, int(0.8 * len(self.image_ids)))

    def _new_model(self, cameras) -> Reconstruction:
        return Reconstruction(self.image_ids, self.names, self.camera_of, cameras, self.keypoints, len(self.tracks))

    def _calibration_pairs(self, cameras: list[int]) -> dict:
        """The pairs among a bounded set of images (view_graph.dense_subset, `_CALIBRATION_IMAGES` around the
        best-connected image, and as many around one of each camera in `cameras` it holds too few images of)
        that the coarse models calibrating those cameras' focals are built from."""
        n = len(self.image_ids)
        inside = dense_subset(self.pairs, n, _CALIBRATION_IMAGES)
        degree = matches_per_image(self.pairs, n)
        for c in cameras:
            mine = np.flatnonzero(self.camera_of == c)
            if len(mine) >= self.config.focal_min_images and \
                    np.count_nonzero(inside[mine]) < min(len(mine), _CALIBRATION_IMAGES // 2):
                inside |= dense_subset(self.pairs, n, _CALIBRATION_IMAGES, [int(mine[np.argmax(degree[mine])])])
        return {k: v for k, v in self.pairs.items() if inside[k[0]] and inside[k[1]]}

    def _calibrate(self, scratch: Reconstruction, sample: dict) -> tuple[int, int]:
        """The guessed focal lengths of `scratch`'s cameras refined by coarse models of the pairs `sample`
        (`_calibrate_by_bundle`, up to `_CALIBRATION_PASSES`); returns the last coarse model's fit (registered
        images, observations within the filters' gate), (0, 0) without one."""
        graph = relative_poses(scratch, sample, self.config, COARSE_SAMPLE, self.workers)
        fit = (0, 0)
        for k in range(_CALIBRATION_PASSES if graph.edges else 0):
            calibrated, fit = self._calibrate_by_bundle(scratch.cameras, graph)
            for c, params in calibrated.items():
                log.info("camera %d: focal %.1f px from a coarse global model (was %.1f)", c, params[0],
                         scratch.cameras[c].params[0])
                scratch.cameras[c].params = params
            if not calibrated:
                break
            if k + 1 < _CALIBRATION_PASSES:
                graph = relative_poses(scratch, sample, self.config, COARSE_SAMPLE, self.workers)
        return fit

    def _lens_from_subset(self, scratch: Reconstruction) -> None:
        """Give each guessed camera of `scratch` the lens, focal and distortion, that a model of the calibration
        subset (`_calibration_pairs`: its view graph at full matches, then `_map_component`'s rounds) refines,
        for the cameras holding distortion_min_images images of that model. Relative rotations estimated at a
        focal a few percent off and without the lens's distortion are biased where the camera turns, and rotation
        averaging sums those biases round a long loop: on a 1,000-frame street loop, the coarse models' 462 or 482
        px for the true 450 (k 0 for -0.02) gave rotations 0.6 and 5.6 deg from the truth (medians), the subset
        model's 450.0 px, k -0.020, 0.4 deg (the mapping's AUC@5 at that seed 0.30 -> 0.95: docs/benchmarks.md,
        "Global mapper: the lens from a subset's model"). Only in a set of `_SUBSET_LENS_MIN_IMAGES` images or
        more, where the subset costs a small share of the mapping: at 100 images it added a third to half of the
        mapping time and changed no model by more than 0.001 of AUC@5; in the smaller sets `_recalibrated` maps
        again from the models' lens where it moved far. The subset's model keeps the cameras' models (no lens
        choice: the whole set's mapping chooses), and its steps' time counts as the calibration's."""
        cams = sorted(calibratable_cameras(scratch.cameras, self.camera_of))
        if not cams:
            return
        sample = self._calibration_pairs(cams)
        inside = np.zeros(len(self.image_ids), bool)
        inside[np.array(list(sample), dtype=np.int64).ravel()] = True
        graph = relative_poses(scratch, sample, self.config, workers=self.workers)
        if not graph.edges:
            return
        reasons, choose_lens, seconds = self.reasons, self.choose_lens, dict(self.seconds)
        self.reasons, self.choose_lens = {}, False
        try:
            m, _ = self._map_component(scratch.cameras, graph, list(graph.edges), inside)
        finally:
            self.reasons, self.choose_lens, self.seconds = reasons, choose_lens, seconds
        if m is None:
            return
        for c in cams:
            if int((m.registered & (m.camera_of == c)).sum()) >= self.config.distortion_min_images:
                log.info("camera %d: lens %s from a model of %d images (was %s)", c,
                         np.round(m.cameras[c].params, 4).tolist(), int(m.registered.sum()),
                         np.round(scratch.cameras[c].params, 4).tolist())
                scratch.cameras[c] = replace(m.cameras[c], params=m.cameras[c].params.copy())

    def _calibrate_by_bundle(self, cameras, graph) -> tuple[dict, tuple[int, int]]:
        """Camera id -> parameters with the focal refined by a coarse global model (one round of triangulation
        and BA at a loose gate), for the guessed cameras it holds `focal_min_images` images of, where the focal
        moved more than 5% (a coarse model finds it within a few percent; orbit150: 671, 550, 569 px for the true
        550): relative poses estimated at a focal far off give rotations and directions that no averaging makes
        consistent (object_orbit_small from the 768 px guess, 560 true: AUC@5 0.55, and 0.99 after this pass).
        Only the focal: the coarse model's poses are too rough to tell distortion from focal (the temple's: k1
        -0.43 beside a focal of 920 for the true 1520, 0). Run again (up to `_CALIBRATION_PASSES`) while the
        focal moves, as a focal far off is found only part of the way."""
        m, _ = self._map_component(cameras, graph, list(graph.edges), np.ones(len(self.image_ids), bool),
                                   coarse=True)
        if m is None:
            return {}, (0, 0)
        err, _ = m.reprojection_errors(m.alive_observations())
        fit = (int(m.registered.sum()), int(np.count_nonzero(err <= self.config.filter_max_reproj_error_px)))
        out = {}
        for c in np.unique(m.camera_of[m.registered]).tolist():
            before, cam = cameras[c], m.cameras[c]
            users = int((m.registered & (m.camera_of == c)).sum())
            if not before.prior_trusted and users >= self.config.focal_min_images \
                    and abs(cam.focal() / before.focal() - 1) > 0.05:
                out[c] = cam.params.copy()
        return out, fit

    # ----- one model -----
    def _map_component(self, cameras, graph, keys, pool, coarse: bool = False):
        """(model or None, images it took from the pool): the largest consistent component of the edges `keys`,
        joined by the images of `pool` that register to its points (`_refine`); with `coarse` only one round of
        triangulation and BA (for `_calibrate_by_bundle`)."""
        n, cfg = len(self.image_ids), self.config
        start = time.perf_counter()
        ij = np.array(keys, dtype=np.int64)
        Rij = np.array([graph.edges[k].R for k in keys])
        weights = np.array([graph.edges[k].inliers for k in keys], float)
        rot = average_rotations(n, ij, Rij, weights, _MAX_ROTATION_ERROR_DEG, cfg.seed)
        start = self._clock("rotation_averaging", start)
        component = rot.solved.copy()
        touched = np.zeros(n, bool)
        touched[ij.ravel()] = True
        for i in np.flatnonzero(touched & ~component).tolist():
            self.reasons.setdefault(i, f"its relative rotations disagree with those of its model's images by more "
                                       f"than {_MAX_ROTATION_ERROR_DEG:g} deg (outlier pairs), or link it to no "
                                       "model")
        if component.sum() < 2:
            return None, touched
        # translation directions of the consistent pairs with a baseline, in the world frame: C_j - C_i ~ -R_j^T t_ij
        with_baseline = [k for k, ok in zip(keys, rot.inliers)
                         if ok and graph.edges[k].angle_deg >= cfg.min_tri_angle_deg]
        if not with_baseline:
            for i in np.flatnonzero(component).tolist():
                self.reasons[i] = (f"no baseline: all its consistent pairs are rotations about the camera centre "
                                   f"(median triangulation angle < {cfg.min_tri_angle_deg:g} deg): a camera turning "
                                   "in place, whose camera positions the global mapper cannot find")
            return None, component
        if component.sum() < _MIN_VIEWS:
            for i in np.flatnonzero(component).tolist():
                self.reasons.setdefault(i, f"its consistent view graph is a single pair: the global mapper places "
                                           f"cameras from {_MIN_VIEWS} or more images linked by pairs, and one pair "
                                           "is only a two-view model; map it with --mapper incremental")
            return None, component
        tij = np.array(with_baseline, dtype=np.int64)
        d = -np.einsum("mji,mj->mi", rot.R[tij[:, 1]], np.array([graph.edges[k].t for k in with_baseline]))

        def pairs_centres():
            """Translation averaging: the coarse models' centres, and global positioning's start where placing
            in turn leaves a camera out (only then computed). Its time is on its own clock, not on the step's
            that asked for it."""
            nonlocal start
            begin = time.perf_counter()
            out = average_translations(n, tij, d, _MAX_DIRECTION_ERROR_DEG, cfg.seed)
            start += self._clock("translation_averaging", begin) - begin
            return out

        if not coarse and POSITIONS == "tracks":
            pos = global_positions(self._new_model(cameras), rot.R, component, self.tracks, cfg.seed,
                                   initial=lambda: pairs_centres().centers, workers=self.workers)
            start = self._clock("global_positioning", start)
            for i, why in outlier_cameras(pos).items():
                pos.solved[i] = False
                self.reasons[i] = why
        else:
            pos = pairs_centres()
        unplaced = ("its pairs with a baseline do not link it to the model's other cameras (too few, too short, or "
                    "their translation directions are outliers)" if coarse or POSITIONS == "pairs" else
                    "too few observations of tracks it shares with the model's other cameras")
        for i in np.flatnonzero(component & ~pos.solved).tolist():
            self.reasons.setdefault(i, f"no position: {unplaced}")
        placed = pos.solved & component
        if placed.sum() < 2:
            return None, component
        m = self._new_model(cameras)
        for i in np.flatnonzero(placed).tolist():
            m.register(i, rot.R[i], -rot.R[i] @ pos.centers[i])
        if coarse:
            triangulate_tracks(m, self.tracks, np.arange(len(self.tracks)), self._gated(_COARSE_GATE_PX), cfg.seed)
            m.deregister_empty_images()  # a camera is refined only when all its registered images are observed
            self._bundle(m, intrinsics=True, distortion=False, subset=True, coarse=True)
            return m, component
        self._refine(m, pool)
        self._clock("bundle_adjustment", start)
        log.info("global model: %d images (%d from averaging), %d points", int(m.registered.sum()),
                 int(component.sum()), len(m.alive_points()))
        held = int(np.count_nonzero(m.image_num_observations()[m.registered] >= cfg.abs_pose_min_inliers))
        if m.registered.any() and held < _MIN_VIEWS:
            # a panorama's pairs can give a model of many images and a handful of points (a few pairs with a
            # sliver of baseline), every pose held by nothing: a model where fewer than `_MIN_VIEWS` images see
            # abs_pose_min_inliers of its points is no model
            for i in m.registered_images().tolist():
                self.reasons[i] = (f"its model's poses rest on too few points: {held} of its "
                                   f"{int(m.registered.sum())} images see abs_pose_min_inliers "
                                   f"({cfg.abs_pose_min_inliers}) or more of them (a camera turning in place, "
                                   "whose pairs hold no baseline, or too few matches)")
            log.info("global model of %d images and %d points discarded: %d of its images see %d points or more",
                     int(m.registered.sum()), len(m.alive_points()), held, cfg.abs_pose_min_inliers)
            return None, component | m.registered
        return m, component | m.registered

    def _refine(self, m: Reconstruction, pool) -> None:
        """Triangulation, global BA and filtering rounds at narrowing gates, a loop whose ends met apart closed
        after the first of them and, once closed, after the last (`_close_open_loop`); then the poses too few
        matches support are taken out, and the images of `pool` left out (poses lost to the filters, or never
        placed by the averaging) are registered by absolute pose against the points, as the incremental mapper
        does, in rounds while images join (an image next to one just registered needs that one's points: a
        12-view wide orbit whose averaging placed 6 ended in models of 9 and 3 with one round); a loop whose gap
        the first round's filters hid (the images at the gap fit neither end and lost every view) is looked for
        again there, once those images are back, each beside its own end; then final rounds
        of retriangulation, BA and filtering until a round changes under `_FINAL_MIN_CHANGE` of the observations
        (COLMAP's iterative global refinement): on a facade of identical windows one round left the poses short
        of where the next rounds took them, each filtering the views the sharper poses no longer explain
        (docs/benchmarks.md, "Global mapper: final rounds until the model settles"). Every BA but the final
        rounds' optimises a point subset (`_bundle`), the others re-fitted to its poses: on a 150-view
        orbit BA took 1016 s of a 1625 s mapping, and three of its eight BAs were over every point. In a model
        of `_LARGE_MODEL` images or more the first round takes the early quota and each final round is a subset
        BA to convergence, then a BA over every point of `_FINAL_ITERATIONS` from there: on a 300-image survey
        (555,000 observations) each of its iterations cost as much as 8 of the subset's, and the poses it moves
        were already fixed by the subset's 300 points per image (cost 1.12e4 -> 1.10e4 in its first three). From
        final_ba_subset_min_images images (MapperConfig, shared with the incremental mapper) that BA over every
        point is left out: the subset BA to convergence is the last, its points re-fitted, as at the incremental
        mapper's end; a BA over every point holds a dense block per point over the cameras that see it.
        With position priors, the first BA and the final rounds' hold the centres to them (georef.py). The first
        takes out the bend of the whole block that the view graph's pairs, estimated without the lens's
        distortion, leave: in a survey of parallel views it trades off against the shared focal and distortion,
        and the images alone take out a little of it per LM iteration. The BAs between go by the images alone:
        the priors held throughout cost accuracy (docs/benchmarks.md, "Global mapper: position priors in
        the first bundle adjustment")."""
        cfg = self.config
        large = int(m.registered.sum()) >= _LARGE_MODEL
        m.priors = self.priors  # the first BA and the final rounds' hold the centres to them (`_bundle`)
        closed = False  # a gap closed after the first round (`_close_open_loop`)
        for k, gate in enumerate([*_GATES_PX, cfg.max_reproj_error_px]):
            loose = self._gated(gate)
            if k == 0:
                triangulate_tracks(m, self.tracks, np.arange(len(self.tracks)), loose, cfg.seed)
            else:
                retriangulate(m, self.tracks, loose, cfg.seed)
            self._note_lost(m)
            self._bundle(m, intrinsics=True, subset=True, early=large and k == 0, start=k == 0)
            m.priors = None  # the next BAs go by the images alone
            self._filter(m, loose)
            if k == 0:
                closed = self._close_open_loop(m, loose, rotations_held=True)
        if closed:
            self._close_open_loop(m, cfg, rotations_held=False)
        dropped = self._drop_unsupported(m)
        added = self._register_left(m, pool)
        out = np.zeros(len(self.image_ids), bool)  # images taken out after a round: not registered again
        for k in range(_REGISTRATION_ROUNDS):
            if not (added or (dropped and k == 0)):
                break
            retriangulate(m, self.tracks, cfg, cfg.seed)
            self._bundle(m, intrinsics=True, subset=True)
            self._filter(m, cfg)
            dropped = self._drop_unsupported(m)
            if dropped:
                self._bundle(m, intrinsics=True, subset=True)
                self._filter(m, cfg)
            out[dropped] = True
            added = self._register_left(m, pool & ~out) if added else []
        if not closed and self._close_open_loop(m, cfg, rotations_held=True):
            self._close_open_loop(m, cfg, rotations_held=False)
        m.priors = self.priors  # held again from the final rounds on
        if cfg.view_sigmas_by_scale:
            m.refresh_view_sigmas(cfg.global_huber_px)
        final_subset = 0 < cfg.final_ba_subset_min_images <= int(m.registered.sum())

        def final_round() -> None:
            retriangulate(m, self.tracks, cfg, cfg.seed)
            if large or final_subset:
                self._bundle(m, intrinsics=True, subset=True)
            if not final_subset:
                self._bundle(m, intrinsics=True, iterations=_FINAL_ITERATIONS if large else None)
            self._filter(m, cfg)

        for k in range(_FINAL_ROUNDS):
            changed, alive = m.observations_changed(final_round)
            log.debug("global model: final round %d changed %d of %d observations", k + 1, changed, alive)
            if changed < _FINAL_MIN_CHANGE * max(alive, 1):
                break
        if self.choose_lens and cfg.refine_intrinsics and lens.choose_models(
                m, lambda: self._bundle(m, intrinsics=True, subset=True), cfg.filter_max_reproj_error_px):
            retriangulate(m, self.tracks, cfg, cfg.seed)  # the views the old model's filters dropped
            self._bundle(m, intrinsics=True, subset=final_subset)
            self._filter(m, cfg)

    def _close_open_loop(self, m: Reconstruction, config: MapperConfig, rotations_held: bool) -> bool:
        """Close an open loop of the model (sfm/loop_closure.py); True if a closure was kept. With
        `rotations_held` (after the first round at its gate, or once the images it took out are registered
        again), where the two ends of the cameras placed in turn round a loop met apart (a hinge whose other
        pose lies `_LOOP_GAP` camera spacings or more from its own): the pose graph at every hinge spreads the
        gap over the centres and scales with the rotations held (rotation averaging solved them for the whole
        loop at once), the points are joined and triangulated again, and the closure is kept unless the model
        then holds under `1 - _LOOP_VIEWS_TOLERANCE` of the views it holds triangulated again without it (the
        scale it spreads moves some views past the gate; a closure that bends the model loses far more); the
        rounds that follow adjust the model. Without (before the final rounds, once a gap was closed): where
        those rounds' bundle adjustments left the loop open at its weakest links (the corners of a street
        loop, a street turned 3 deg against the next), the pose graph with the rotations free, the views
        joined, a bundle adjustment and the filters, kept when the model then holds more views, as the
        incremental mapper closes its loops. A street loop of 1,000 frames: AUC@5 0.54 -> 0.95
        (docs/benchmarks.md, "Global mapper: a loop whose ends met apart")."""

        def settle() -> None:
            continue_points(m, self.tracks, config)
            if rotations_held:
                retriangulate(m, self.tracks, config, config.seed)
            else:
                self._bundle(m, intrinsics=True, subset=True)
            self._filter(m, config)

        if rotations_held:
            return bool(close_open_loop(m, self.tracks, self.config, settle, hold_rotations=True, min_gap=_LOOP_GAP,
                                        settled_baseline=True, tolerance=_LOOP_VIEWS_TOLERANCE))
        return bool(close_open_loop(m, self.tracks, self.config, settle))

    def _note_lost(self, m: Reconstruction) -> None:
        for i in m.deregister_empty_images():
            self.reasons[i] = "no track triangulated with its global pose (the filters removed them all)"

    def _register_left(self, m: Reconstruction, pool) -> list[int]:
        """Register by absolute pose (register.register_image) the images of `pool` not in the model; each gets
        its observations from the next retriangulation. Returns those registered."""
        cfg = self.config
        added = []
        for i in np.flatnonzero(pool & ~m.registered).tolist():
            reg = register_image(m, self.tracks, i, cfg, seed=cfg.seed + i, decide=True)
            if reg.ok:
                added.append(i)
                self.reasons.pop(i, None)
            elif i in self.reasons and "absolute pose" not in self.reasons[i]:  # once, for the first model
                self.reasons[i] += f"; and its absolute pose against the model failed: {reg.reason}"
        if added:
            log.info("global model: %d image(s) registered by absolute pose: %s", len(added),
                     ", ".join(self.names[i] for i in added))
        return added

    def _gated(self, gate: float) -> MapperConfig:
        """The config with its triangulation and filtering gates widened to `gate` pixels."""
        cfg = self.config
        return replace(cfg, max_reproj_error_px=max(gate, cfg.max_reproj_error_px),
                       filter_max_reproj_error_px=max(gate, cfg.filter_max_reproj_error_px))

    def _bundle(self, m: Reconstruction, intrinsics: bool, distortion: bool = True, subset: bool = False,
                coarse: bool = False, early: bool = False, iterations: int | None = None,
                start: bool = False) -> None:
        """Global BA of every registered image; intrinsics as in the incremental mapper's global BA: the focal
        from focal_min_images images on, the distortion (unless not `distortion`) from distortion_min_images on,
        and a BA that leaves a camera implausible undone and repeated with less refined; the fx and fy of a
        camera model with two focals are held equal unless its calibration is trusted (`bundle_adjust`'s
        `square_pixels`): a model that holds all its images from the start refines a guessed focal from poses
        fitted at the guess, and left free the two drift apart. Not while the lens is chosen (`choose_lens`):
        there the models tried are fitted free, as in the incremental mapper's trials (held equal, the trials
        of wide_orbit_small at seed 0 chose OPENCV_FISHEYE for its OPENCV lens, AUC@5 0.946 against 0.992), and
        the mapping again from the chosen lens starts from a trusted calibration. With `subset`, as the
        incremental mapper's BAs during growth, only ba_points_per_image well-spread points per image are
        optimised and the others re-fitted to the poses (ba_points.py): the rounds at loose gates only need the
        poses and the focal near. `coarse` (the calibration's models) takes ba_points_per_image_early points
        per image and stops after `_COARSE_ITERATIONS`: the next pass goes on from where it stopped. `early`
        (the first round, from global positioning's poses, where most LM iterations are spent: 18 of 25 on a
        100-image survey) takes `_START_POINTS_PER_IMAGE` points per image, to convergence.
        `iterations` caps the LM iterations (default the config's global_ba_iterations). Except in the coarse
        models, only the points seen by three images or more are optimised (`ba_points.long_points`), the others
        re-fitted to the poses after. Its Huber width is `_START_HUBER_PX` in the coarse models and with `start` (the
        first round's BA, from global positioning's poses, pixels off), else the config's global_huber_px. A model whose
        `priors` are set is moved into their frame first, once they allow it (georef.py), and the BA holds each
        centre to its prior: `_refine` sets them for its first BA and its final rounds'."""
        cfg = replace(self.config, huber_px=_START_HUBER_PX if coarse or start else self.config.global_huber_px)
        georeference(m, cfg.seed)  # into the priors' frame once they allow it (georef.py; no-op without priors)
        n = int(m.registered.sum())
        focal = intrinsics and cfg.refine_intrinsics and n >= cfg.focal_min_images
        distortion = distortion and n >= cfg.distortion_min_images

        def adjust(intr: bool, dist: bool) -> None:
            points = m.alive_points()
            quota = (_START_POINTS_PER_IMAGE if early else cfg.ba_points_per_image_early if coarse
                     else cfg.ba_points_per_image)
            if subset and quota > 0:
                points = select_points(m, m.registered_images(), quota)
            if not coarse:  # a coarse model at a focal far off holds few three-view tracks: it needs them all
                points = long_points(m, points, _BA_MIN_VIEWS, _BA_MIN_HOLD)
            out = bundle_adjust(m, m.registered_images(), cfg, point_ids=points, refine_intrinsics=intr,
                                refine_distortion=dist, square_pixels=not self.choose_lens,
                                max_iterations=_COARSE_ITERATIONS if coarse else iterations or cfg.global_ba_iterations)
            if len(points) < len(m.alive_points()):
                refine_existing_points(m, np.setdiff1d(m.alive_points(), points))
            self.ba_calls += 1
            self.ba_seconds += out.seconds

        filtering.plausible_bundle(m, focal, distortion, adjust, square=True)

    def _filter(self, m: Reconstruction, config: MapperConfig) -> None:
        filtering.filter_observations(m, config)
        filtering.filter_small_angle_points(m, config)
        for i in m.deregister_empty_images():
            self.reasons[i] = "lost all its observations to the filters after bundle adjustment"

    def _drop_unsupported(self, m: Reconstruction) -> list[int]:
        """Deregister the images whose pose too few of their matches support (see the module docstring). The floor
        is what an image registered by absolute pose needs, also for a pose the averaging placed: a handful of
        matches can all fit a pose that is wrong, as on a symmetric object seen from one side. An image that
        fewer than `_BA_MIN_HOLD` points seen by two other images too hold (`ba_points.held_observations`) goes
        as well, however many two-view points fit it: a point of this image and one other fits it wherever along
        their baseline it lies, and the BAs' point choice (`ba_points.long_points`) counts such a pose all but
        free (toy_object rendered from another seed: an image held by 45 two-view points and 2 others, 7.7 deg
        off, which absolute pose then placed right). Held to abs_pose_min_inliers such points, as an image
        registered by absolute pose is, three right images of a 30-view toy with short tracks went out."""
        cfg = self.config
        count = m.image_num_observations()
        shared = held_observations(m, m.alive_points(), _BA_MIN_VIEWS)
        dropped = []
        for i in m.registered_images().tolist():
            t = self.tracks.track_of[i]
            with_point = int(np.count_nonzero(m.point_of_track[t[t >= 0]] >= 0))
            ratio = count[i] / with_point if with_point else 0.0
            few = count[i] < cfg.abs_pose_min_inliers or ratio < cfg.abs_pose_min_inlier_ratio
            if few or shared[i] < _BA_MIN_HOLD:
                dropped.append(i)
                self.reasons[i] = (f"its global pose was an outlier: {count[i]} of the {with_point} matches to "
                                   f"the model's points fit it within {cfg.filter_max_reproj_error_px:g} px after "
                                   "bundle adjustment " + (
                                       f"(< abs_pose_min_inliers {cfg.abs_pose_min_inliers} or under "
                                       f"abs_pose_min_inlier_ratio {cfg.abs_pose_min_inlier_ratio:g})" if few else
                                       f"but {shared[i]} of them to points two other images see (< {_BA_MIN_HOLD}: "
                                       "its place along its pairs' baselines left free)"))
        if dropped and len(dropped) < int(m.registered.sum()) - 1:
            m.remove_observations(m.observations_of_images(dropped))
            for i in dropped:
                m.registered[i] = False
                if i in m.registration_order:
                    m.registration_order.remove(i)
            log.info("global model: %d image(s) with unsupported poses taken out: %s", len(dropped),
                     ", ".join(self.names[i] for i in dropped))
            return dropped
        return []

    # ----- report -----
    def _status(self, models: list[Reconstruction]) -> dict:
        return image_status(self.names, self.keypoints, self.pairs, models,
                            lambda i: self.reasons.get(i, "not part of any model's consistent view graph"))


def map_correspondences_globally(corr: Correspondences, config: MapperConfig = MapperConfig(),
                                 workers: int = 1, choose_lens: bool = False) -> MappingResult:
    """Run the global mapper on a database's correspondences (see `database.read_correspondences`), the view
    graph's relative poses in `workers` processes (a script that asks for more than one needs the
    `if __name__ == "__main__":` guard that Python's process start methods require). With `choose_lens` (the
    user left the camera model open) each camera's model is chosen from the data (sfm/lens.py)."""
    return GlobalMapper(corr, config, workers, choose_lens).run()

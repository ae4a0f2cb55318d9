"""The incremental mapper: initial pair, then register / triangulate / bundle-adjust image by image.

Loop per model (COLMAP's IncrementalMapper): pick the best next images by visibility score, register one with
robust absolute pose, continue existing points into it and triangulate its new tracks, run a local BA over it
and its most connected neighbours, filter; whenever the model has grown by 10% run a global BA with
intrinsics, retriangulate and filter, and write a snapshot (also written when the last is 5 minutes old). When
no image can be added, the model is finished (a last global refinement) and a new model is started from the
images that are left, so scenes that do not connect give several models. What one registration costs does not
grow with the model (the model's indexes, sfm/model.py; `CandidateRanking`): only the global steps, at growth
ratios, pass over all of it. A model needs `min_model_size()` images; when none reaches it, the largest smaller one is
kept (COLMAP keeps its first model whatever its size, which locks a first pair that did not grow away from the
model its images belong in). Every image that ends unregistered gets a reason.
"""

import hashlib
import logging
import pickle
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..config import config_hash
from ..database import Correspondences
from ..geometry.camera import num_distortion_terms
from ..io.files import replace_whole
from ..progress import progress
from ..startup import hand_back_freed_memory
from . import filtering, lens
from .ba_points import select_points
from .bundle import bundle_adjust as _bundle_adjust
from .config import MapperConfig
from .georef import CenterPriors, georeference
from .initialize import evaluate_pair, find_initial_pair, initial_pair_rejections, rejected_for_few_inliers
from .loop_closure import close_open_loop
from .model import KeypointSet, Reconstruction, image_status, images_and_cameras
from .register import CandidateRanking, correspondences_2d3d, rank_candidates, register_image
from .tracks import build_tracks
from .triangulate import continue_points, refine_existing_points, retriangulate, tracks_of_image, triangulate_tracks
from .view_graph import calibrate_focals

log = logging.getLogger("mvrecon.sfm")
SNAPSHOT_VERSION = 4  # 2: small models kept as candidates (1 dropped them); 3: only the largest of them;
# 4: registration trials keyed on the model's state (size, refined after a stall)
# a snapshot is also written after a registration when the last is this old: the growth-ratio snapshots come
# ever further apart as a model grows (after 100 images, 10 registrations later; after 1000, 100), and a Ctrl-C
# should not lose more than a few minutes, while writing one costs in proportion to the model
SNAPSHOT_SECONDS = 300.0
_FOCAL_SCALES = (1.0, 0.25, 0.35, 0.5, 0.7, 1.4, 2.0, 3.0)  # of a guessed focal, tried at initialisation


@dataclass
class MappingResult:
    models: list  # Reconstruction, largest first
    status: dict  # image name -> {"status", "model", "reason"}
    stats: dict = field(default_factory=dict)


class _Snapshot:
    """Pickled mapper state; refused when the config or the input correspondences differ."""

    def __init__(self, path, signature):
        self.path = Path(path) if path else None
        self.signature = signature

    def save(self, state: dict) -> None:
        if self.path is None:
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        data = pickle.dumps({"version": SNAPSHOT_VERSION, "signature": self.signature, "state": state})
        replace_whole(self.path, lambda tmp: tmp.write_bytes(data))

    def load(self) -> dict | None:
        if self.path is None or not self.path.is_file():
            return None
        try:
            with open(self.path, "rb") as f:
                data = pickle.load(f)
            data.get("version")
        except Exception as exc:  # cut off or overwritten: what it held is lost either way, so map afresh
            log.warning("%s: unreadable snapshot (%s: %s); starting over", self.path, type(exc).__name__, exc)
            return None
        if data.get("version") != SNAPSHOT_VERSION:
            log.warning("%s: snapshot from another version of the mapper; starting over", self.path)
            return None
        if data.get("signature") != self.signature:
            log.warning("%s: snapshot from a different config or database; starting over", self.path)
            return None
        return data["state"]


def _signature(corr, config: MapperConfig) -> tuple:
    """What a snapshot was mapped from: the config and a hash of all the input (cameras with their model,
    parameters and trusted flag, images, keypoints, verified pairs), so that one made before the features or
    matches were redone, or the cameras changed, is never resumed."""
    h = hashlib.sha256()

    def add(*values):
        h.update(repr(values).encode())

    for cid in sorted(corr.cameras):
        c = corr.cameras[cid]
        add("camera", int(cid), c.model, int(c.width), int(c.height), bool(c.prior_trusted),
            np.asarray(c.params, np.float64).tolist())
    for iid in sorted(corr.images):
        im = corr.images[iid]
        kp = np.ascontiguousarray(corr.keypoints.get(iid, np.zeros((0, 2))), np.float64)
        add("image", int(iid), im.name, int(im.camera_id), kp.shape)
        h.update(kp.tobytes())
    for p in corr.pairs:
        inl = np.ascontiguousarray(p.inliers, np.int64)
        add("pair", int(p.image_id1), int(p.image_id2), p.config, inl.shape)
        h.update(inl.tobytes())
    for iid, prior in sorted(corr.priors.items()):  # none without priors: the signature stays as it was
        add("prior", int(iid), prior.coordinate_system, prior.position.tolist(), prior.covariance.tolist())
    return (config_hash(config), len(corr.images), len(corr.pairs), h.hexdigest())


class IncrementalMapper:
    def __init__(self, corr: Correspondences, config: MapperConfig = MapperConfig(),
                 snapshot_path: Path | str | None = None, choose_lens: bool = False):
        self.config = config
        self.choose_lens = choose_lens  # the cameras' models were left open: sfm/lens.py may change them
        self.image_ids, self.names, self.camera_of, self.cameras = images_and_cameras(corr)
        ids = self.image_ids.tolist()
        self.keypoints = KeypointSet([corr.keypoints.get(i, np.zeros((0, 2))) for i in ids],
                                     [corr.keypoint_scales.get(i, np.zeros(0)) for i in ids])
        index_of = {int(i): k for k, i in enumerate(ids)}
        self.pairs = {}
        for p in corr.pairs:
            a, b = index_of.get(p.image_id1), index_of.get(p.image_id2)
            if a is not None and b is not None and len(p.inliers):
                self.pairs[(a, b) if a < b else (b, a)] = p if a < b else _swapped(p)
        self.tracks = build_tracks(self.image_ids, [len(k) for k in self.keypoints], corr.pairs)
        self._calibrate_guessed_focals()
        self.snapshot = _Snapshot(snapshot_path, _signature(corr, config))
        self.priors = CenterPriors.of(corr.priors)  # camera position priors (georef.py), None without
        self.finished: list[Reconstruction] = []
        # the largest model finished under min_model_size (the first of equals), kept only if no model reaches it
        self.small: Reconstruction | None = None
        self.tried_init: set = set()
        # the initial-pair criteria in force: config's, with init_min_inliers halved while no model could start
        self.init_config = config
        # what a model was started from (`_start_key`) when the model was discarded: starting it again from
        # the same pair and state would only build the same model again
        self.dropped_starts: set = set()
        self.start_key = None  # that of the current model
        self.init_rejections: dict[int, str] = {}  # image -> its best pair's miss, when no model could start
        self.evaluated_init: dict = {}  # pair -> evaluate_pair result, for this run only
        self.evaluated_with: dict = {}  # the trusted calibrations evaluated_init was computed with
        self.reasons: dict[int, str] = {}
        self.current: Reconstruction | None = None
        self.last_global = 0
        self.since_global: set[int] = set()  # images registered since the current model's last global refinement
        self.full_at = 0  # registered images at the current model's last global refinement of every image
        self.attempts: dict[int, tuple] = {}  # image -> (failed trials, the model's state at the last one)
        self.stalled_at = -1  # the size at which the current model last stopped growing (`_grow`)
        self.ba_calls, self.ba_seconds = 0, 0.0
        self.undecided: dict[int, str] = {}  # image -> why its pose was ambiguous when it was registered (`_grow`)
        self.ranking = CandidateRanking(self.tracks)
        # per registration: (images, points, seconds since the previous one, entries scanned, global refinement)
        self.registrations: list[tuple[int, int, float, int, bool]] = []
        self._since = (time.perf_counter(), 0)  # (time, model.scanned) at the end of the last registration
        self.saved_at = time.monotonic()  # when the last snapshot was written

    def _bundle(self, m, images, **kwargs):
        out = _bundle_adjust(m, images, self.config, **kwargs)
        self.ba_calls += 1
        self.ba_seconds += out.seconds
        return out

    def _bundle_points(self, m, images, points, subset: bool, keep=(), **kwargs):
        """BA of `images` over `points`. With `subset` (while the model grows) only the grid-selected points
        and those in `keep` are optimised (see ba_points) and the others re-fitted to the moved poses;
        ba_points_per_image 0 turns that off."""
        quota = self._points_quota(m, images) if subset else 0
        if quota <= 0:
            return self._bundle(m, images, point_ids=points, **kwargs)
        chosen = np.intersect1d(np.union1d(select_points(m, images, quota), keep), points)
        out = self._bundle(m, images, point_ids=chosen, **kwargs)
        refine_existing_points(m, np.setdiff1d(points, chosen))
        return out

    def _points_quota(self, m, images) -> int:
        """Points per image of a BA during growth: ba_points_per_image_early while the model is small and
        every camera of `images` is shared by at least 3 registered images (see config.py)."""
        cfg = self.config
        n = int(m.registered.sum())
        if n >= cfg.distortion_min_images or cfg.ba_points_per_image <= 0:
            return cfg.ba_points_per_image
        if m.cameras_shared(images):
            return cfg.ba_points_per_image_early
        return cfg.ba_points_per_image

    def _calibrate_guessed_focals(self) -> None:
        """Start each guessed focal from the one the verified pairs' fundamental matrices support together
        (view_graph.calibrate_focals, as the global mapper does), where they observe it (not in an orbit, whose
        cameras keep the guess and the initial pair's estimate). One pair's estimate can be far off: a
        200-image part of a nadir survey started from 807 px for 500, its BAs drove it to 6,098 px and no pose
        came out right; the view graph gave 519 px. Neutral or better on every set where it fires
        (docs/benchmarks.md, "Mapper rules")."""
        scratch = Reconstruction(self.image_ids, self.names, self.camera_of, self.cameras, self.keypoints, 0)
        found = calibrate_focals(scratch, {k: p.inliers for k, p in self.pairs.items()}, self.config.seed)
        for c, (_, focal) in found.items():
            cam = self.cameras[c]
            cam.set_focal(focal)
            cam.prior_focal, cam.prior_calibrated = focal, True

    # ----- state -----
    def _new_model(self) -> Reconstruction:
        """An empty model. A camera that a finished model calibrated starts from that calibration, trusted:
        a later model of the same camera would otherwise start again from the guess, and its few images
        cannot correct it (templeSparseRing's 3-image model: 768 px guessed, 1216 px after its BAs, 50
        iterations to get there, against 1630 px in the 13-image model)."""
        m = Reconstruction(self.image_ids, self.names, self.camera_of, self.cameras, self.keypoints,
                           len(self.tracks))
        m.priors = self.priors
        for cid, (model, params) in self._calibrated_cameras().items():
            m.set_camera_model(cid, model, params)  # with the model it was calibrated in (sfm/lens.py)
            cam = m.cameras[cid]
            cam.prior_trusted, cam.prior_focal = True, cam.focal()
        return m

    def _calibrated_cameras(self) -> dict:
        """camera id -> (model, parameters), from the largest finished model holding at least
        distortion_min_images images of that camera (so that its focal and distortion were both refined)."""
        out = {}
        for f in sorted(self.finished, key=lambda f: -int(f.registered.sum())):
            for c in np.unique(self.camera_of[f.registered]).tolist():
                users = int((f.registered & (self.camera_of == c)).sum())
                if c not in out and users >= self.config.distortion_min_images:
                    out[c] = (f.cameras[c].model, f.cameras[c].params)
        return out

    def _save(self) -> None:
        self.saved_at = time.monotonic()
        self.snapshot.save({"finished": [m.state() for m in self.finished],
                            "small": self.small.state() if self.small is not None else None,
                            "current": self.current.state() if self.current is not None else None,
                            "tried_init": set(self.tried_init), "reasons": dict(self.reasons),
                            "last_global": self.last_global, "attempts": dict(self.attempts),
                            "since_global": set(self.since_global), "full_at": self.full_at,
                            "stalled_at": self.stalled_at, "undecided": dict(self.undecided),
                            "dropped_starts": set(self.dropped_starts), "start_key": self.start_key,
                            "init_min_inliers": self.init_config.init_min_inliers})

    def _restore(self, s: dict) -> None:
        self.finished = [Reconstruction.from_state(m, self.keypoints) for m in s["finished"]]
        self.small = Reconstruction.from_state(s["small"], self.keypoints) if s.get("small") else None
        self.current = Reconstruction.from_state(s["current"], self.keypoints) if s["current"] else None
        self.tried_init, self.reasons = s["tried_init"], s["reasons"]
        self.last_global, self.attempts, self.stalled_at = s["last_global"], s["attempts"], s["stalled_at"]
        self.undecided = s["undecided"]
        self.since_global, self.full_at = s.get("since_global", set()), s.get("full_at", 0)
        self.dropped_starts, self.start_key = s.get("dropped_starts", set()), s.get("start_key")
        self.init_config = replace(self.config, init_min_inliers=s.get("init_min_inliers",
                                                                        self.config.init_min_inliers))

    # ----- main loop -----
    def run(self, resume: bool = False) -> MappingResult:
        state = self.snapshot.load() if resume else None
        if state is not None:
            self._restore(state)
            log.info("resuming from %s: %d finished models, current model with %d images", self.snapshot.path,
                     len(self.finished), int(self.current.registered.sum()) if self.current else 0)
        bar = progress(total=len(self.image_ids), desc="mapping", unit="img")
        self._show_progress(bar)
        while len(self.finished) < self.config.max_models:
            if self.current is None and not self._start_model():
                break
            self._show_progress(bar)
            self._grow(self.current, bar)
            self._finish_model(self.current)
            self.current = None
            self._show_progress(bar)
            self._save()
        self._keep_a_small_model()
        self._show_progress(bar)
        bar.close()
        self.finished.sort(key=lambda m: -int(m.registered.sum()))
        return MappingResult(self.finished, self._status(),
                             {"tracks": len(self.tracks),
                              "split_inconsistent_tracks": self.tracks.split_inconsistent,
                              "ba_calls": self.ba_calls, "ba_seconds": self.ba_seconds,
                              "undecided_registrations": len(self.undecided)})

    def _show_progress(self, bar) -> None:
        """The bar counts the images registered now, in the finished models and the current one: each image
        once, and a discarded model's images (or an image the filters deregistered) no longer; after it, the
        current model's images and points and the mean seconds of its last 10 registrations."""
        n = len(self._excluded()) + (int(self.current.registered.sum()) if self.current is not None else 0)
        bar.update(n - bar.n)
        if self.current is not None:
            recent = [r[2] for r in self.registrations[-10:]]
            pace = f", {sum(recent) / len(recent):.1f} s/img" if recent else ""
            bar.set_postfix_str(f"model {len(self.finished)}: {int(self.current.registered.sum())} img, "
                                f"{self.current.num_points} pts{pace}")

    def _excluded(self) -> set:
        out = set()
        for m in self.finished:
            out.update(np.flatnonzero(m.registered).tolist())
        return out

    def _start_model(self) -> bool:
        """Start the next model from the first initial pair accepted (and that keeps enough points after its
        BA); False when there is none, with each left image's reason in init_rejections."""
        while True:
            scratch = self._new_model()
            calibration = {c: cam.params.tobytes() for c, cam in scratch.cameras.items() if cam.prior_trusted}
            if calibration != self.evaluated_with:  # pairs evaluated before a camera was calibrated are stale
                self.evaluated_init, self.evaluated_with = {}, calibration
            init = find_initial_pair(scratch, self.pairs, self._excluded(), self.init_config, self.tried_init,
                                     self.evaluated_init)
            if init is None and self._relax_initial_pair():
                continue
            if init is None:
                self._explain_no_initial_pair(scratch)
                return False
            key = self._start_key(init, scratch)
            if key in self.dropped_starts:
                # the pair passes a lower angle threshold too, but with everything else as when its model was
                # discarded the same model would be built and discarded again
                log.debug("initial pair %s / %s: its model was discarded before; not built again",
                          self.names[init.image1], self.names[init.image2])
                continue
            init = self._focal_from_third_view(init, scratch)
            m = scratch
            n_init = self._seed_model(m, init)
            log.info("initial pair %s / %s: %d points, median triangulation angle %.1f deg",
                     self.names[init.image1], self.names[init.image2], n_init, init.median_angle_deg)
            self._global_refine(m)
            points, least = m.stats()["points"], self.config.abs_pose_min_inliers
            if points < least:
                self.dropped_starts.add(key)
                pair = (init.image1, init.image2)
                for i, j in (pair, pair[::-1]):
                    self.reasons[i] = (f"its two-view model with {self.names[j]} kept {points} points after "
                                       f"bundle adjustment, < abs_pose_min_inliers {least}, and was dropped")
                log.info("dropped the two-view model of %s / %s: %d points < abs_pose_min_inliers %d",
                         self.names[init.image1], self.names[init.image2], points, least)
                continue
            self.current, self.last_global, self.attempts, self.start_key = m, 2, {}, key
            self.since_global, self.full_at = set(), 0
            self.stalled_at = -1
            self._save()
            return True

    @property
    def _relaxed(self) -> bool:
        """Whether the initial pair's inlier count is in force below the config's (`_relax_initial_pair`)."""
        return self.init_config.init_min_inliers < self.config.init_min_inliers

    def _relax_initial_pair(self) -> bool:
        """Halve init_min_inliers (up to init_relaxations times) while no model could start because no pair
        has that many inliers, as COLMAP's pipeline relaxes it; the pairs rejected for too few inliers are then
        assessed again. Pairs that have the inliers but were refused (a panorama's rotations, a baseline too
        short) are not a reason to accept weaker ones: a panorama's far pairs, verified as F on 20-40 chance
        matches, made a 2-image model."""
        base, now = self.config.init_min_inliers, self.init_config.init_min_inliers
        if self.finished or now <= base >> self.config.init_relaxations or now < 2:
            return False
        if any(len(p.inliers) >= now for p in self.pairs.values()):
            return False
        self.init_config = replace(self.config, init_min_inliers=now // 2)
        stale = {key for key, found in self.evaluated_init.items() if rejected_for_few_inliers(found)}
        self.evaluated_init = {k: v for k, v in self.evaluated_init.items() if k not in stale}
        self.tried_init = {t for t in self.tried_init if t[0] not in stale}
        log.info("no initial pair with %d inliers or more; trying again with %d, as COLMAP relaxes its own",
                 now, now // 2)
        return True

    def _start_key(self, init, scratch: Reconstruction) -> tuple:
        """Everything the model started from `init` depends on: the pair's pose, every camera of the scratch
        model (a guessed focal of another camera may have been moved by the pairs evaluated before), and the
        finished models (their images are left out, their calibrations reused). Building is deterministic, so
        equal keys give equal models."""
        cams = tuple((c, cam.params.tobytes(), cam.prior_trusted, cam.prior_focal)
                     for c, cam in sorted(scratch.cameras.items()))
        return (init.image1, init.image2, init.R.tobytes(), init.t.tobytes(), cams, len(self.finished),
                frozenset(self._excluded()))

    def _explain_no_initial_pair(self, scratch: Reconstruction) -> None:
        """Why no model could start from the images left: per image, what the nearest miss among its pairs
        with other images left missed (for `_status`, which gives it to the images without another reason), and
        the nearest miss of all in the log."""
        rejected = initial_pair_rejections(scratch, self.pairs, self._excluded(), self.init_config,
                                           self.evaluated_init, {key[:2] for key in self.dropped_starts})
        best = {}
        for r in rejected.values():
            for i in (r.image1, r.image2):
                if i not in best or r.closeness > best[i].closeness:
                    best[i] = r
        relaxed = (f" (relaxed from {self.config.init_min_inliers}, as no model could start)" if self._relaxed
                   else "")
        self.init_rejections = {i: f"its best pair ({self.names[r.image1]} / {self.names[r.image2]}) has "
                                   f"{r.text}{relaxed if rejected_for_few_inliers(r) else ''}"
                                for i, r in best.items()}
        if best:
            r = max(best.values(), key=lambda r: r.closeness)
            log.info("no initial pair accepted%s: the best pair (%s / %s) has %s",
                     " among the images left" if self.finished else "", self.names[r.image1],
                     self.names[r.image2], r.text)

    def _seed_model(self, m: Reconstruction, init) -> int:
        """Register the initial pair in `m` and triangulate every track the two images share; returns the
        points made."""
        m.register(init.image1, np.eye(3), np.zeros(3))
        m.register(init.image2, init.R, init.t)
        shared = np.intersect1d(tracks_of_image(m, self.tracks, init.image1),
                                tracks_of_image(m, self.tracks, init.image2))
        return triangulate_tracks(m, self.tracks, shared, self.config, self.config.seed)

    def _focal_from_third_view(self, init, model: Reconstruction):
        """When the pair's shared focal is only a guess (1.2 x the image size, say) that the pair could not
        correct (Bougnoux's estimate degenerates when the optical axes meet, as in an orbit), try the initial
        pair at several focal lengths and keep the one under which the next image fits the pair's points best:
        most of its 2D-3D matches within 4 px after absolute pose. A two-view model built with a focal 3x off
        is skewed so that later images register wrongly and the BA cannot recover (a 100 deg lens: the
        guess was 768 px for 269, and 139 of 321 matches fitted). The guess is tried first and kept when half
        the matches fit it, or when no other focal fits >= 10% more. Essential on wide_orbit (AUC@5 0.998,
        0.860 without); within +-0.02 AUC@1 elsewhere (docs/benchmarks.md, "Mapper rules")."""
        cam_id = int(self.camera_of[init.image1])
        cam = model.cameras[cam_id]
        if cam.focal_kept or int(self.camera_of[init.image2]) != cam_id:
            return init
        if not np.isclose(cam.focal(), cam.prior_focal):  # the pair's F gave a plausible focal: not a guess
            return init
        guess = cam.focal()  # what the pair was estimated with
        at_guess = self._third_view_fit(init, cam_id, guess)
        fits = at_guess[0] if at_guess else 0
        if at_guess and fits >= 0.5 * at_guess[1]:
            return init
        best = (fits, 1.0, init)
        for scale in _FOCAL_SCALES:
            if scale == 1.0:
                continue
            found = self._third_view_fit(init, cam_id, guess * scale, estimate=True)
            if found and found[0] > best[0]:
                best = (found[0], scale, found[2])
        count, scale, found = best
        if scale == 1.0 or count < 1.1 * fits:
            return init
        log.info("focal length %.0f px (guessed %.0f): the third image fits %d of its matches within "
                 "%.0f px, %d at the guess", guess * scale, guess, count, self.config.max_reproj_error_px,
                 fits)
        model.cameras[cam_id].set_focal(guess * scale)
        return found

    def _third_view_fit(self, init, cam_id: int, focal: float, estimate: bool = False):
        """In a scratch model whose camera `cam_id` has `focal`: seed the initial pair (its pose `init`, or
        re-estimated at this focal with `estimate`), register the best next image and count its 2D-3D
        matches within the 4 px gate. Returns (fits, matches, the pair's pose), or None when a step fails."""
        cfg, m = self.config, self._new_model()
        m.cameras[cam_id].set_focal(focal)
        if estimate:
            init = evaluate_pair(m, self.pairs[(init.image1, init.image2)], init.image1, init.image2,
                                 self.init_config, focal_from_pair=False)
            if init is None:
                return None
        self._seed_model(m, init)
        excluded = self._excluded()
        ranked = rank_candidates(m, self.tracks, [i for i in range(len(self.image_ids))
                                                  if not m.registered[i] and i not in excluded])
        if not ranked or not register_image(m, self.tracks, ranked[0][2], cfg, seed=cfg.seed).ok:
            return None
        third = ranked[0][2]
        kps, pids = correspondences_2d3d(m, self.tracks, third)
        uv, depth = m.project(np.full(len(pids), third), m.xyz.data[pids])
        err = np.linalg.norm(uv - m.keypoints[third][kps], axis=1)
        fits = int(((err <= cfg.max_reproj_error_px) & (depth > 0)).sum())
        return fits, len(err), init

    def _grow(self, m: Reconstruction, bar) -> None:
        """Register images one at a time until none can be added: every candidate is tried, the best-scored
        first, and when none registers, a global refinement and one more round (COLMAP's incremental pipeline
        does both; the same models on every shared set and catalog scene, docs/benchmarks.md).

        An image whose pose is ambiguous (repeated structure, sfm/register.py) waits while other images can
        be registered; once none can, the first of the waiting images is registered with the pose its
        registered views support most. So waiting can reorder registration but never hold an image out of
        the model, where two images waiting for each other would start a second model."""
        cfg = self.config
        excluded = self._excluded()
        self._since = (time.perf_counter(), m.scanned)
        while True:
            num_reg = int(m.registered.sum())
            state = (num_reg, self.stalled_at == num_reg)  # an image is tried once per state of the model
            pool = [i for i in range(len(self.image_ids))
                    if not m.registered[i] and i not in excluded
                    and self.attempts.get(i, (0, None))[0] < cfg.max_register_trials
                    and self.attempts.get(i, (0, None))[1] != state]
            ranked = [r for r in self.ranking.rank(m, pool) if r[1] > 0]
            waiting = []
            added = False
            for _, _, i in ranked:
                reg = register_image(m, self.tracks, i, cfg, seed=cfg.seed + i)
                # a pose that waits for the model to grow (ambiguous) does not use up a trial
                self.attempts[i] = (self.attempts.get(i, (0, None))[0] + (not reg.wait), state)
                if reg.wait:
                    waiting.append(i)
                added = self._registered(m, i, reg, bar)
                if added:
                    break
            if not added and ranked and self.stalled_at != num_reg:
                # as COLMAP: when no image can be registered, a global refinement and one more round
                self.stalled_at = num_reg
                self._global_refine(m, growing=True)
                self.last_global = num_reg
                continue
            for i in waiting if not added else ():
                why = self.reasons.get(i)
                reg = register_image(m, self.tracks, i, cfg, seed=cfg.seed + i, decide=True)
                self.attempts[i] = (self.attempts[i][0] + (not reg.ok), state)
                if reg.ok:
                    log.info("%s: registered with the pose its registered views support most, as no other "
                             "image could be registered (%s)", self.names[i], why)
                    self.undecided[i] = why
                added = self._registered(m, i, reg, bar)
                if added:
                    break
            if not added:
                return

    def _registered(self, m: Reconstruction, i: int, reg, bar) -> bool:
        """Book `register_image`'s outcome for image i; when it registered, triangulate and adjust (True)."""
        if not reg.ok:
            self.reasons[i] = reg.reason
            log.debug("%s: %s", self.names[i], reg.reason)
            return False
        self.reasons.pop(i, None)
        self.since_global.add(i)
        adjusted = self._after_registration(m, i)
        now, (since, scanned) = time.perf_counter(), self._since
        self.registrations.append((int(m.registered.sum()), m.num_points, now - since, m.scanned - scanned, adjusted))
        self._since = (now, m.scanned)
        self._show_progress(bar)
        return True

    def _after_registration(self, m: Reconstruction, i: int) -> bool:
        """Triangulate the new image's tracks, then a local BA, or a global one when the model grew enough
        (a local BA right before a global one would optimise nearly the same problem twice); True after a global
        one."""
        cfg = self.config
        continue_points(m, self.tracks, cfg, images=[i])
        triangulate_tracks(m, self.tracks, tracks_of_image(m, self.tracks, i), cfg, cfg.seed + i)
        log.debug("registered %s (%d images, %d points)", self.names[i], int(m.registered.sum()),
                  m.num_points)
        if m.registered.sum() >= cfg.global_ba_growth * self.last_global:
            self._global_refine(m, growing=True)
            self._choose_lenses(m)
            self.last_global = int(m.registered.sum())
            self._save()
            return True
        window = self._local_window(m, i)
        pts = np.unique(m.obs_point.data[m.observations_of_images(window)])
        self._bundle_points(m, window, pts, True, max_iterations=cfg.local_ba_iterations)
        continue_points(m, self.tracks, cfg, images=window)
        self._filter(m, pts)
        if time.monotonic() - self.saved_at >= SNAPSHOT_SECONDS:
            self._save()
        return False

    def _choose_lenses(self, m: Reconstruction) -> None:
        """When the user left the camera model open, each camera due a trial (`lens.due_cameras`) is tried
        with the richer models (`lens.try_richer_models`, a BA of every image per model); after a switch, a
        global refinement brings back the views the old model's filters dropped."""
        cfg = self.config
        if not self.choose_lens or not cfg.refine_intrinsics:
            return
        if lens.choose_models(m, lambda: self._bundle(
                m, m.registered_images(), square_pixels=False, refine_intrinsics=True, refine_distortion=True,
                max_iterations=cfg.global_ba_iterations), cfg.filter_max_reproj_error_px):
            self._global_refine(m)

    def _filter(self, m: Reconstruction, point_ids=None) -> None:
        """The filters after a BA (of `point_ids`, or all points); an image they leave without observations
        is deregistered with a reason, and may be registered again as the model grows."""
        filtering.filter_observations(m, self.config, point_ids=point_ids)
        filtering.filter_small_angle_points(m, self.config, point_ids=point_ids)
        for i in m.deregister_empty_images():
            self.reasons[i] = "lost all its 2D-3D matches to the filters after bundle adjustment"
            log.info("%s: %s; deregistered", self.names[i], self.reasons[i])

    def _local_window(self, m: Reconstruction, i: int) -> np.ndarray:
        """The new image and the registered images sharing the most points with it."""
        pts = m.obs_point.data[m.observations_of_images([i])]
        others = m.obs_image.data[m.observations_of_points(np.unique(pts))]
        counts = np.bincount(others, minlength=len(m.image_ids))
        counts[i] = 0
        best = [int(j) for j in np.argsort(-counts, kind="stable")[:self.config.local_ba_images - 1]
                if counts[j] > 0]
        return np.array([i, *best], dtype=np.int64)

    def _global_refine(self, m: Reconstruction, rounds: int = 1, growing: bool = False,
                       min_change: float = 0.0, relative_tolerance=None, keep=()) -> None:
        """Up to `rounds` of global BA (while `growing`: on a point subset, and of `_growth_images` once the
        model is large; LM to `relative_tolerance` when given), retriangulation and filtering (of the
        optimised images' tracks and points); stops early once a round adds and removes fewer than `min_change`
        of the observations (COLMAP's iterative global refinement). A large model's refinement of every image
        optimises a point subset too (`_final_subset`), plus the points `keep`."""
        cfg = self.config
        images = self._growth_images(m) if growing else None
        subset = growing or self._final_subset(m)

        def one_round() -> None:
            self._global_bundle(m, subset, keep, relative_tolerance=relative_tolerance, images=images)
            retriangulate(m, self.tracks, cfg, cfg.seed, images=images)
            self._filter(m, None if images is None else self._points_of(m, images))

        for _ in range(rounds):
            changed, alive = m.observations_changed(one_round)
            log.debug("global refinement changed %d of %d observations", changed, alive)
            if changed < min_change * max(alive, 1):
                break
        self.since_global = set()
        if images is None:
            self.full_at = int(m.registered.sum())
        hand_back_freed_memory()

    def _final_subset(self, m: Reconstruction) -> bool:
        """Whether a BA of every image (the model's final refinement) optimises a point subset, as the BAs during
        growth do, and re-fits the other points to its poses: from final_ba_subset_min_images registered images.
        A BA of every point holds, per point, a dense block over the cameras that see it: it held the run's peak
        memory at scale, while the poses are pinned as well by the well-spread subset. Smaller models keep
        the BA of every point."""
        least = self.config.final_ba_subset_min_images
        return least > 0 and int(m.registered.sum()) >= least

    def _growth_images(self, m: Reconstruction) -> np.ndarray | None:
        """The images a global BA during growth optimises: None (every image) up to growth_ba_max_images
        registered images; beyond, that many: the images registered since the last global refinement (the
        latest registered when there are none, or too many) and the registered images sharing the most points
        with them. The others are held, so the BA, its retriangulation and its filters cost in proportion to the
        subset (intrinsics too are held: `bundle_adjust` refines a camera only when all its images move), and
        the model's end still refines every image (`_finish_model`). Each time the model has doubled since its last
        BA of every image, the BA moves every image again (intrinsics included): on a 120-view wall bounded to 40
        images, holding them from 40 views on cost 0.017 in AUC@5; the doublings keep the total cost linear."""
        cap = self.config.growth_ba_max_images
        n = int(m.registered.sum())
        if cap <= 0 or n <= cap or n >= 2 * self.full_at:
            return None
        recent = [i for i in m.registration_order if i in self.since_global] or m.registration_order
        chosen = np.array(recent[-cap:], np.int64)
        if len(chosen) < cap:
            counts = np.bincount(m.obs_image.data[m.observations_of_points(self._points_of(m, chosen))],
                                 minlength=len(m.image_ids))
            counts[chosen] = 0
            best = np.argsort(-counts, kind="stable")[:cap - len(chosen)]
            chosen = np.r_[chosen, best[counts[best] > 0]]
        return np.sort(chosen)

    @staticmethod
    def _points_of(m: Reconstruction, images) -> np.ndarray:
        return np.unique(m.obs_point.data[m.observations_of_images(images)])

    def _global_bundle(self, m: Reconstruction, subset: bool, keep=(), relative_tolerance=None,
                       images: np.ndarray | None = None) -> None:
        """Global BA of every registered image (or of `images`, the others held). One that leaves a camera
        implausible (focal 10x off its prior or |k| > 1, COLMAP's bogus-camera test) is undone and repeated with
        the distortion fixed, then with all intrinsics fixed: in a small model a guessed focal and the
        distortion trade off against each other (templeRing blurred: k1 -1.7 as the focal doubled), and dropping
        the images would not repair the camera they share. Fires only on the degraded temples: a plausible
        camera (blurred: f 1599, k1 0 for the true 1520, 0; without: 1669, -1.26) for poses 0.004-0.024 lower
        in AUC@5 ("Mapper rules"). The focal is refined from focal_min_images images on, and from the initial
        pair on where its two images have guessed cameras of their own (`_own_guessed_cameras`)."""
        cfg = self.config
        n = int(m.registered.sum())
        intrinsics = cfg.refine_intrinsics and (n >= cfg.focal_min_images or self._own_guessed_cameras(m))
        distortion = n >= cfg.distortion_min_images
        variable = m.registered_images() if images is None else images
        points = m.alive_points() if images is None else self._points_of(m, images)

        def adjust(intr: bool, dist: bool) -> None:
            self._bundle_points(m, variable, points, subset, keep,
                                refine_intrinsics=intr, refine_distortion=dist,
                                max_iterations=cfg.global_ba_iterations, relative_tolerance=relative_tolerance)

        georeference(m, cfg.seed)  # into the priors' frame once they allow it (no-op without priors)
        filtering.plausible_bundle(m, intrinsics, distortion, adjust)
        hand_back_freed_memory()  # else the next global BA stacks on its fragments

    @staticmethod
    def _own_guessed_cameras(m: Reconstruction) -> bool:
        """Whether no two registered images share a camera and no camera's focal is trusted: a pair of two
        cameras each of one image, both focals guesses (1.2 x the image size, up to 2.5x off), as in photos from
        many cameras. COLMAP refines them from its initial pair's BA; held there until a third image, the first
        BAs that free them can settle on focals 2-3x off that the later images then fit (visitor_photos_small at
        a zoom of 0.4-2.5x: 13 of 13 images misplaced; freed: 13 right, AUC@5 0.836). Neutral or better on
        every set where it fires but at one seed of seven of imc_reichstag (docs/benchmarks.md, "Mapper
        rules")."""
        cams = m.camera_of[m.registered]
        return len(np.unique(cams)) == len(cams) and not any(m.cameras[int(c)].prior_trusted for c in cams)

    def _close_loops(self, m: Reconstruction) -> np.ndarray:
        """Views of existing points that the drift of growth left past the 4 px gate rejoin through the loose
        angular gate, when their point can be re-fitted to them or their image sees them displaced together
        (`triangulate.continue_points`); returns the ids of the points that gained views, for the BA that pulls
        the loop together (`_finish_model`), whose filters then drop the views it could not bring within 4 px.
        Not neutral everywhere it fires (docs/benchmarks.md, "Mapper rules"): AUC@5 up to +0.026 (imc_reichstag,
        templeSparseRing, blurred temple), down to -0.014 (noisy and blurred temples). A loop left open at a
        hinge, past both gates, is closed first (`_close_open_loop`)."""
        self._close_open_loop(m)
        first = m.obs_point.n
        continue_points(m, self.tracks, self.config, loose=True, seed=self.config.seed)
        return np.unique(m.obs_point.data[first:m.obs_point.n])

    def _close_open_loop(self, m: Reconstruction) -> None:
        """Where images see the other end of an open loop (sfm/loop_closure.py), spread the gap over the loop
        with the pose graph, let the hinge's views join their points through the 4 px gate, and bundle-adjust
        them with the usual subset; undone when the model then holds no more views than before
        (`loop_closure.close_open_loop`)."""
        cfg = self.config
        first = m.obs_point.n

        def settle() -> None:
            continue_points(m, self.tracks, cfg)
            self._global_bundle(m, True, keep=np.unique(m.obs_point.data[first:m.obs_point.n]))
            self._filter(m)

        close_open_loop(m, self.tracks, cfg, settle)

    def _finish_model(self, m: Reconstruction) -> None:
        # loops closed, then global BA with every point (those during growth used a subset; so does a large
        # model's, `_final_subset`, which adds the points that loop closing gave views), retriangulation and
        # filtering, a second round only when the first still changed final_min_change of the observations;
        # LM run further for a four-term lens (config.py). On a large model that BA also settles the loops: a
        # BA of their own was the costliest of all there; a smaller model gets one, with its filters, before
        # the final one, which its AUC needs (docs/benchmarks.md, "Loops settled by the final BA")
        joined = self._close_loops(m)
        if len(joined) and not self._final_subset(m):
            self._global_bundle(m, True, keep=joined)
            self._filter(m)
        cfg = self.config
        if cfg.view_sigmas_by_scale:
            m.refresh_view_sigmas(cfg.huber_px)
        four_terms = any(num_distortion_terms(m.cameras[c].model) == 4 for c in set(m.camera_of[m.registered].tolist()))
        self._global_refine(m, rounds=2, min_change=cfg.final_min_change,
                            relative_tolerance=cfg.four_term_final_tolerance if four_terms else None, keep=joined)
        self._drop_non_square_cameras(m)
        n, least = int(m.registered.sum()), self.min_model_size()
        if n >= least:
            self.finished.append(m)
            self.small = None  # a model reached min_model_size: no small one will be kept
            log.info("model %d: %d images, %d points", len(self.finished) - 1, n, len(m.alive_points()))
            return
        log.info("discarded a model of %d images (< %d)", n, least)
        if self.start_key is not None:
            self.dropped_starts.add(self.start_key)
        # a model started from a pair under the relaxed inlier count must grow to be kept: two images on a few
        # dozen matches are weak evidence of anything
        largest = int(self.small.registered.sum()) if self.small is not None else 0
        if not self.finished and not self._relaxed and n > largest:
            self.small = m
        started = (f", started from a pair under init_min_inliers {self.config.init_min_inliers} (relaxed to "
                   f"{self.init_config.init_min_inliers}), " if self._relaxed else ", ")
        for i in np.flatnonzero(m.registered).tolist():
            self.reasons[i] = f"its model stayed at {n} images{started}under min_model_size {least}, and was discarded"

    def finish(self, m: Reconstruction) -> None:
        """Finish a model assembled outside this mapper on its images, tracks and cameras (the merge of a
        partitioned mapping, sfm/merge.py) as the mapper finishes its own: loops closed, the final global
        refinement and filters, cameras checked; kept in `finished`, or discarded with a reason per image."""
        self._finish_model(m)

    def _drop_non_square_cameras(self, m: Reconstruction) -> None:
        """Deregister the images of cameras whose fx / fy ended more than 1.5x apart (`non_square_cameras`: wrong
        matches, not a lens), then refine what is left once more; COLMAP deregisters the images of bogus cameras
        the same way (from 20 registered images on). It fires on no shared set or catalog scene at the
        default settings, only once the focal search is switched off ("Mapper rules")."""
        bogus = filtering.non_square_cameras(m)
        if not bogus:
            return
        aspects = ", ".join(f"{m.cameras[c].params[0]:.0f} / {m.cameras[c].params[1]:.0f}" for c in bogus)
        m.remove_observations(m.observations_of_images(
            [i for i in m.registered_images().tolist() if int(m.camera_of[i]) in bogus]))
        dropped = m.deregister_empty_images()
        log.info("deregistered %d image(s): camera(s) %s ended with fx / fy %s", len(dropped), bogus, aspects)
        for i in dropped:
            self.reasons[i] = (f"deregistered: its camera's fx / fy ended at {aspects}, more than 1.5x apart (a "
                               "bundle adjustment fitted to wrong matches, not a lens)")
        if m.registered.sum() >= 2:
            self._global_refine(m)

    def _keep_a_small_model(self) -> None:
        """When no model reached min_model_size, the largest smaller one (the first of equals) is kept: a set where
        only a small model can be built still gives it. Until then its images stay free for later models, where
        COLMAP's keeping of its first model at any size would hold them in a pair that did not grow."""
        if self.finished or self.small is None:
            return
        m = self.small
        self.finished.append(m)
        log.info("model 0: %d images, %d points (kept under min_model_size %d: no model reached it)",
                 int(m.registered.sum()), len(m.alive_points()), self.min_model_size())

    def min_model_size(self) -> int:
        """The images a model needs, as COLMAP's IncrementalPipeline: min(min_model_size, 0.8 x the number of
        images, rounded down)."""
        return min(self.config.min_model_size, int(0.8 * len(self.image_ids)))

    # ----- report -----
    def _status(self) -> dict:
        in_tracks = np.array([np.any(t >= 0) for t in self.tracks.track_of], bool)

        def reason(i: int) -> str:
            if not in_tracks[i]:
                return "no consistent feature tracks (all its matches conflict)"
            if i in self.reasons:
                return self.reasons[i]
            if i in self.init_rejections and not self.finished:
                return f"no initial pair accepted: {self.init_rejections[i]}"
            if i in self.init_rejections:
                return ("too few 2D-3D matches: it shares no triangulated points with a model, and no "
                        f"initial pair was accepted among the images left: {self.init_rejections[i]}")
            return "too few 2D-3D matches: it shares no triangulated points with a model"

        out = image_status(self.names, self.keypoints, self.pairs, self.finished, reason)
        for i, why in self.undecided.items():
            if out[self.names[i]]["status"] == "registered":
                out[self.names[i]]["note"] = (f"registered when no other image could be, with the pose its "
                                              f"registered views support most: {why}")
        return out

def _swapped(p):
    return replace(p, image_id1=p.image_id2, image_id2=p.image_id1, inliers=p.inliers[:, ::-1].copy(),
                   F=None if p.F is None else p.F.T, E=None if p.E is None else p.E.T, H=None if p.H is None
                   else np.linalg.inv(p.H))


def map_correspondences(corr: Correspondences, config: MapperConfig = MapperConfig(),
                        snapshot_path: Path | str | None = None, resume: bool = False,
                        choose_lens: bool = False) -> MappingResult:
    """Run the incremental mapper on a database's correspondences (see `database.read_correspondences`); with
    `choose_lens` (the user left the camera model open) each camera's model is chosen from the data
    (sfm/lens.py)."""
    return IncrementalMapper(corr, config, snapshot_path, choose_lens=choose_lens).run(resume=resume)

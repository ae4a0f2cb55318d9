"""The mapper's settings: one frozen dataclass whose defaults follow COLMAP's incremental mapper."""

import hashlib
import json
from dataclasses import asdict, dataclass

from ..config import bounded
from ..errors import InputError

OPTIMIZERS = ("lm", "sfm")  # MapperConfig.optimizer's choices


@dataclass(frozen=True)
class MapperConfig:
    """Incremental mapping options. Pixel thresholds are in pixels of the (distorted) image. Values from a
    --config file or a flag are checked against each field's `bounded` range (config.py).

    Initial pair (COLMAP: init_min_num_inliers=100, init_min_tri_angle=16, init_max_error=4):
    init_min_inliers: verified matches a pair needs to be tried as the initial pair.
    init_min_tri_angles_deg: median triangulation angles tried in order; the first pair meeting one wins, so a
        scene without a 16 degree baseline still starts (COLMAP relaxes its thresholds the same way).
    init_relaxations: while no model could start at all and no pair has init_min_inliers, it is halved this
        many times (100, 50, 25), each time with every angle again: COLMAP's pipeline relaxes its inlier count
        the same way, and small or weakly textured images (templeRing at 160 x 120: 43-66 inliers a pair) start
        a model. Such a model is kept only when it reaches min_model_size.
    init_max_pairs: at most this many candidate pairs are tried per angle threshold.
    two_view_max_error_px: epipolar inlier threshold for the relative pose.

    Registration (COLMAP: abs_pose_max_error=12, abs_pose_min_num_inliers=30, abs_pose_min_inlier_ratio=0.25):
    abs_pose_*: RANSAC threshold, minimum inliers and inlier ratio of the absolute pose.
    max_register_trials: how many times an image is tried before it is given up (it is retried only after
        the model has changed since its last trial). Every candidate is tried, best-scored first, before the
        mapper gives up growing a model, as COLMAP does.

    Triangulation and filtering (COLMAP: tri_min_angle=1.5, tri_continue_max_angle_error=2,
    filter_max_reproj_error=4, filter_min_tri_angle=1.5):
    min_tri_angle_deg, max_reproj_error_px (creating and continuing points), filter_max_reproj_error_px,
    filter_min_tri_angle_deg; tri_max_angle_error_deg: the loose angular gate of the one continuation before
    the final refinement that closes loops (COLMAP's continue_max_angle_error; a view it lets in must also pass
    COLMAP's test for merging tracks, sfm/triangulate.py).

    Bundle adjustment (COLMAP: ba_local_num_images=6, ba_global_images_ratio=1.1,
    ba_local_max_num_iterations=25):
    local_ba_images: the new image plus its most connected neighbours that are optimised.
    global_ba_growth: a global BA runs when the registered count grows by this factor.
    ba_relative_tolerance: LM stops when the cost falls by less than this fraction in an iteration (1e-3:
        the same models as 1e-4 on templeRing and lund_door, in 30% less BA time; the final global BAs
        still run to it, but for four-term lenses, and the next BA continues from where this one stopped).
    four_term_final_tolerance: ba_relative_tolerance of a finished model's final refinement when one of its
        cameras is a four-term lens (OPENCV, OPENCV_FISHEYE). Focal and k1..k4 trade off along a shallow valley
        where LM at 1e-3 stops wherever the path of the seed's model left it: on the fisheye catalog scene,
        seeds 0-7 ended at median rotation errors of 0.019-0.075 deg (AUC@1 0.897-0.966); at 1e-5 they end at
        0.017-0.039 deg (AUC@1 0.941-0.967), for 0.2-0.6 s more mapping on 10-12 images. With a two-term or no
        lens the same 1e-5 was worse (templeSparseRing AUC@1 0.122 -> 0.099), so it applies to these only.
    ba_shared_initial_lambda: LM's initial damping in a BA whose cameras are each shared by 3 or more registered
        images (1e-4, Ceres's, otherwise). Every camera's focal is pinned by many images there, and the damped
        first steps only cost iterations: 3e-5 cut templeSparseRing's BA work (observations x iterations) by 11%
        with the same AUC@5 over seeds 0-2. A camera of one or two images keeps 1e-4: 1e-5 for every BA took
        imc_reichstag (a camera per image) from AUC@5 0.750 / 0.658 / 0.701 to 0.688 / 0.647 / 0.633
        (docs/speed-log.md, session 40).
    ba_points_per_image: while the model grows, BAs optimise up to this many well-spread points per image
        and re-fit the others (sfm/ba_points.py); 0 optimises every point. The final BAs use every point.
    ba_points_per_image_early: the same quota while the model has fewer than distortion_min_images images,
        for images whose camera at least 3 registered images share. Those BAs mostly move a guessed focal,
        which the observations of all its images pin, and they can take 50 iterations (templeRing's four-
        and five-image BAs: 0.8 s with 300, 0.26-0.35 s with 100). A camera of one or two images keeps
        ba_points_per_image: with 100, imc_reichstag (a camera per image) fell to AUC@5 0.62-0.67 from
        0.66-0.75 (seeds 0-2).
    final_min_change: a finished model gets a global BA with every point, retriangulation and filtering, and a
        second such round only when the first added or removed this fraction of its observations (COLMAP: up to
        5 rounds while one changes 0.05%). On the A/B sets the first round changes 0.1-0.8% (1.7% and 5%
        on imc_reichstag and wide_orbit_small, which keep their second round): 1% instead of 0.1% cut the BA
        work (observations x iterations) by 4-20% on 8 of the 11 sets, with the same registered images, AUC@5
        within 0.001 and AUC@1 at most 0.003 lower (3 seeds each; docs/speed-log.md, session 32).
    huber_px: Huber loss width (pixels); refine_intrinsics: focal and distortion refined in global BA.
    focal_min_images: intrinsics stay fixed in the two-view BA of the initial pair, where the focal length is
        not observable (it collapses towards zero with the depths).
    distortion_min_images: below this many registered images only the focal is refined: two or three views
        fit a wrong distortion that then pushes the periphery of the next image past the PnP threshold.
    optimizer: "lm" for plain Levenberg-Marquardt with a points-first elimination ordering (the Schur order
        by construction), "sfm" for gtsam.SfmLevenbergMarquardtOptimizer; LM measured about 30% faster at equal
        tolerance on templeRing and lund_door with the same models (tools/bench_ba.py).

    Models: a model needs min(min_model_size, 0.8 x the number of images) registered images (COLMAP's
        threshold); when none reaches it, the largest smaller one is kept. max_models bounds how many are
        started.
    seed: every random choice (RANSAC) is seeded from it, so equal inputs give equal models.
    """

    init_min_inliers: int = bounded(100, 0)
    init_min_tri_angles_deg: tuple = bounded((16.0, 8.0, 4.0, 2.0), 0.0, 180.0)
    init_relaxations: int = bounded(2, 0)
    init_max_pairs: int = bounded(40, 1)
    two_view_max_error_px: float = bounded(4.0, 0.0, low_open=True)
    abs_pose_max_error_px: float = bounded(12.0, 0.0, low_open=True)
    abs_pose_min_inliers: int = bounded(30, 4)
    abs_pose_min_inlier_ratio: float = bounded(0.25, 0.0, 1.0)
    max_register_trials: int = bounded(3, 1)
    min_tri_angle_deg: float = bounded(1.5, 0.0, 90.0)
    tri_max_angle_error_deg: float = bounded(2.0, 0.0, low_open=True)
    max_reproj_error_px: float = bounded(4.0, 0.0, low_open=True)
    filter_max_reproj_error_px: float = bounded(4.0, 0.0, low_open=True)
    filter_min_tri_angle_deg: float = bounded(1.5, 0.0, 90.0)
    local_ba_images: int = bounded(6, 1)
    local_ba_iterations: int = bounded(25, 1)
    global_ba_iterations: int = bounded(50, 1)
    global_ba_growth: float = bounded(1.1, 1.0, low_open=True)
    ba_relative_tolerance: float = bounded(1e-3, 0.0, 1.0, low_open=True)
    four_term_final_tolerance: float = bounded(1e-5, 0.0, 1.0, low_open=True)
    ba_shared_initial_lambda: float = bounded(3e-5, 0.0, low_open=True)
    ba_points_per_image: int = bounded(300, 0)
    ba_points_per_image_early: int = bounded(100, 0)
    final_min_change: float = bounded(0.01, 0.0, 1.0)
    huber_px: float = bounded(1.0, 0.0, low_open=True)
    refine_intrinsics: bool = True
    focal_min_images: int = bounded(3, 2)
    distortion_min_images: int = bounded(6, 2)
    optimizer: str = "lm"
    min_model_size: int = bounded(3, 2)
    max_models: int = bounded(10, 1)
    seed: int = bounded(0, 0)

    def validate(self, source) -> None:
        """An InputError naming `source` (the config file that set it) for an optimizer the mapper lacks."""
        if self.optimizer not in OPTIMIZERS:
            raise InputError(f"{source}: mapper optimizer must be one of {', '.join(OPTIMIZERS)}, "
                             f"not {self.optimizer!r}")

    def hash(self) -> str:
        """Short stable hash of the settings, stored in reports and snapshots to refuse mixing configs."""
        return hashlib.sha1(json.dumps(asdict(self), sort_keys=True).encode()).hexdigest()[:12]

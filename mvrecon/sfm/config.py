"""The mapper's settings: one frozen dataclass whose defaults follow COLMAP's incremental mapper."""

from dataclasses import dataclass

from ..config import bounded
from ..errors import InputError

OPTIMIZERS = ("lm", "sfm")  # MapperConfig.optimizer's choices
MAPPERS = ("incremental", "global")  # MapperConfig.mapper's choices
MIN_PARTITION_SIZE = 10  # MapperConfig.partition_size's least (but 0): smaller parts are too small to map
FRAMES = ("enu", "ecef")  # MapperConfig.frame's choices: the frame of a model with position priors


@dataclass(frozen=True)
class MapperConfig:
    """Mapping options (the incremental mapper's, which the global mapper's triangulation, bundle adjustment
    and filters share); the defaults follow COLMAP's incremental mapper, and each field's comment
    names COLMAP's option where there is one. Pixel thresholds are in pixels of the (distorted) image. Values
    from a --config file or a flag are checked against each field's `bounded` range (config.py).
    """

    # verified matches a pair needs to be tried as the initial pair (COLMAP: init_min_num_inliers)
    init_min_inliers: int = bounded(100, 0)
    # median triangulation angles tried in order, the first pair meeting one wins (COLMAP: init_min_tri_angle)
    init_min_tri_angles_deg: tuple = bounded((16.0, 8.0, 4.0, 2.0), 0.0, 180.0)
    # times init_min_inliers is halved while no model could start (templeRing at 160 x 120: 43-66 a pair)
    init_relaxations: int = bounded(2, 0)
    # candidate initial pairs tried per angle threshold
    init_max_pairs: int = bounded(40, 1)
    # epipolar inlier threshold of the initial pair's relative pose (COLMAP: init_max_error)
    two_view_max_error_px: float = bounded(4.0, 0.0, low_open=True)
    # RANSAC threshold of an image's absolute pose (COLMAP: abs_pose_max_error)
    abs_pose_max_error_px: float = bounded(12.0, 0.0, low_open=True)
    # inliers an absolute pose needs to register its image (COLMAP: abs_pose_min_num_inliers)
    abs_pose_min_inliers: int = bounded(30, 4)
    # inlier ratio an absolute pose needs (COLMAP: abs_pose_min_inlier_ratio)
    abs_pose_min_inlier_ratio: float = bounded(0.25, 0.0, 1.0)
    # trials before an image is given up, each after the model changed (COLMAP: max_reg_trials)
    max_register_trials: int = bounded(3, 1)
    # smallest triangulation angle of a new point (COLMAP: tri_min_angle)
    min_tri_angle_deg: float = bounded(1.5, 0.0, 90.0)
    # angular gate of the loop-closing continuation (COLMAP: tri_continue_max_angle_error)
    tri_max_angle_error_deg: float = bounded(2.0, 0.0, low_open=True)
    # points of its tracks an image must see elsewhere, fitted by one other pose, to close an open loop there
    # (sfm/loop_closure.py; 0: never)
    loop_min_inliers: int = bounded(50, 0)
    # reprojection error allowed when creating and continuing points (COLMAP: tri_merge_max_reproj_error)
    max_reproj_error_px: float = bounded(4.0, 0.0, low_open=True)
    # observations above this reprojection error are filtered out (COLMAP: filter_max_reproj_error)
    filter_max_reproj_error_px: float = bounded(4.0, 0.0, low_open=True)
    # points whose largest triangulation angle is below this are filtered out (COLMAP: filter_min_tri_angle)
    filter_min_tri_angle_deg: float = bounded(1.5, 0.0, 90.0)
    # the new image plus its most connected neighbours optimised in a local BA (COLMAP: ba_local_num_images)
    local_ba_images: int = bounded(6, 1)
    # iteration cap of a local BA (COLMAP: ba_local_max_num_iterations)
    local_ba_iterations: int = bounded(25, 1)
    # iteration cap of a global BA (COLMAP: ba_global_max_num_iterations)
    global_ba_iterations: int = bounded(50, 1)
    # a global BA runs when the registered count grows by this factor (COLMAP: ba_global_images_ratio)
    global_ba_growth: float = bounded(1.1, 1.0, low_open=True)
    # above this many registered images a global BA during growth optimises this many: those registered
    # since the last one and the images sharing the most points with them, the others held (0: every image)
    growth_ba_max_images: int = bounded(100, 0)
    # LM stops when an iteration lowers the cost by less than this (1e-4: same models, 30% more BA time)
    ba_relative_tolerance: float = bounded(1e-3, 0.0, 1.0, low_open=True)
    # the final refinement's tolerance when a camera is a four-term lens, whose focal and k1..k4 trade off
    four_term_final_tolerance: float = bounded(1e-5, 0.0, 1.0, low_open=True)
    # LM's initial damping when every camera is shared by 3+ registered images (1e-4 otherwise, Ceres's)
    ba_shared_initial_lambda: float = bounded(3e-5, 0.0, low_open=True)
    # well-spread points per image a growing model's BAs optimise, the rest re-fit (sfm/ba_points.py); 0: all
    ba_points_per_image: int = bounded(300, 0)
    # the same quota below distortion_min_images images, for cameras 3+ registered images share
    ba_points_per_image_early: int = bounded(100, 0)
    # from this many registered images the final refinement's BAs optimise ba_points_per_image well-spread points
    # per image and re-fit the others to the poses, as the BAs during growth do (0: every point at any size)
    final_ba_subset_min_images: int = bounded(100, 0)
    # a second final refinement round runs when the first changed this fraction of observations
    # (COLMAP: ba_global_max_refinement_change, 0.05%, up to 5 rounds)
    final_min_change: float = bounded(0.01, 0.0, 1.0)
    # Huber loss width of BA residuals, in pixels: views more than half a pixel off (a coarse-scale keypoint, a
    # match a pixel or two astray) weigh less; against 1 px it raised AUC@1 on 24 of the suite's 31 sets and cost
    # at most 0.002 on 4 (docs/benchmarks.md, "Huber width")
    huber_px: float = bounded(0.5, 0.0, low_open=True)
    # the same for the global mapper's BAs after its first round; the BAs from the averaging's poses, pixels off,
    # keep 1 px (global_mapper._START_HUBER_PX): 0.5 px there too lost a 12-view wide orbit (docs/benchmarks.md,
    # "Global mapper: Huber width 0.5 px after the first round")
    global_huber_px: float = bounded(0.5, 0.0, low_open=True)
    # the final refinement weighs each view by its keypoint scale's error, measured on the model's residuals
    # (Reconstruction.refresh_view_sigmas); off by default: on the mapper suite it raised AUC@1 on some sets
    # and lowered it on others (docs/benchmarks.md, "Views weighted by keypoint scale")
    view_sigmas_by_scale: bool = False
    # focal and distortion refined in global BA (COLMAP: ba_refine_focal_length, ba_refine_extra_params)
    refine_intrinsics: bool = True
    # below this many images intrinsics stay fixed: the initial pair cannot observe the focal length
    focal_min_images: int = bounded(3, 2)
    # below this many images only the focal is refined: a few views fit a wrong distortion
    distortion_min_images: int = bounded(6, 2)
    # when the user left the camera model open (no --camera-model, no --camera-params), a SIMPLE_RADIAL camera
    # becomes OPENCV or OPENCV_FISHEYE where that fits its views clearly better (sfm/lens.py; the incremental
    # mapper only); on every shared set and catalog scene it either kept SIMPLE_RADIAL (the models unchanged) or
    # chose the lens's own model (docs/benchmarks.md, "Lens chosen from the data")
    choose_camera_model: bool = True
    # "incremental": image by image (sfm/incremental.py); "global": all poses at once (sfm/global_mapper.py)
    mapper: str = "incremental"
    # when the incremental mapper's largest model holds under half the images, or it made several models, the
    # global mapper maps them too and its models are kept if their largest holds more (stages/mapping.py)
    global_fallback: bool = True
    # images per part of a partitioned mapping (sfm/partition.py: parts mapped alone, then merged); 0: no parts
    partition_size: int = bounded(0, 0)
    # MB a bundle adjustment's point blocks may take; past it the longest tracks are split (sfm/bundle.py; 0: never)
    ba_memory_mb: float = bounded(1000.0, 0.0)
    # a BA whose cameras' elimination would fill in this much (sfm/bundle.py, `_pose_order`) solves its LM steps by
    # conjugate gradients instead of a factorisation (0: never)
    ba_iterative_fill: float = bounded(5e7, 0.0)
    # "lm": Levenberg-Marquardt with points eliminated first; "sfm": gtsam.SfmLevenbergMarquardtOptimizer
    optimizer: str = "lm"
    # images a model needs, at most 0.8 x the images, else the largest one stays (COLMAP: min_model_size)
    min_model_size: int = bounded(3, 2)
    # at most this many models are started (COLMAP: max_num_models)
    max_models: int = bounded(10, 1)
    # seeds every random choice (RANSAC), so equal inputs give equal models (COLMAP: random_seed)
    seed: int = bounded(0, 0)
    # with camera position priors (GPS, --pose-priors): the model's frame, "enu" (metres east, north, up of the
    # origin in report.json) or "ecef" (earth-centred metres); sfm/georef.py
    frame: str = "enu"
    # an image whose centre ends farther than this many sigmas from its position prior is flagged in the report
    prior_max_sigmas: float = bounded(4.0, 0.0, low_open=True)

    def validate(self, source: str | None) -> None:
        """An InputError naming `source` (the config file that set it) for an optimizer or mapper that does not
        exist."""
        if self.mapper not in MAPPERS:
            raise InputError(f"{source}: mapper must be one of {', '.join(MAPPERS)}, not {self.mapper!r}")
        if 0 < self.partition_size < MIN_PARTITION_SIZE:
            raise InputError(f"{source or '--partition-size'}: partition size must be 0 (no parts) or at "
                             f"least {MIN_PARTITION_SIZE}, not {self.partition_size}")
        if self.frame not in FRAMES:
            raise InputError(f"{source}: mapper frame must be one of {', '.join(FRAMES)}, not {self.frame!r}")
        if self.optimizer not in OPTIMIZERS:
            raise InputError(f"{source}: mapper optimizer must be one of {', '.join(OPTIMIZERS)}, "
                             f"not {self.optimizer!r}")

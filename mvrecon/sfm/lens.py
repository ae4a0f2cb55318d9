"""The camera model chosen from the data: a lens the default SIMPLE_RADIAL cannot describe becomes OPENCV.

SIMPLE_RADIAL has one radial term. A wide lens (k1 -0.22 and k2 0.05 with tangential terms, say) leaves its
image corners several pixels off under it: the filters drop those views, and the poses settle on what is left
(AUC@1 0.40 on wide_orbit_small, against 0.95 once OPENCV). So when the user left the model open
(`CameraConfig.model_left_open`) and `MapperConfig.choose_camera_model` is on, each SIMPLE_RADIAL camera is
tried with the richer models once it has MIN_IMAGES registered images, and again each time their count doubles
while its last trial came near a switch: a bundle adjustment of the whole model with the camera as it is, then
one from the same start per candidate with its parameters converted (f, f, cx, cy, k, 0, 0, 0 for OPENCV), and
the best candidate is kept when it brings the camera's reprojection error under MAX_ERROR_RATIO of
SIMPLE_RADIAL's. The error is the mean over the camera's observations, each capped at the filters' threshold,
so a few outliers cannot decide. The global mapper tries the cameras of each finished model the same way
(`choose_models`) and, where one switched, maps again from the chosen models (`switched_cameras`): its view
graph's relative poses and the averaged poses all came from the old model's undistortion.
"""

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..cameras import fold_radius
from ..geometry import camera as cammodel
from .filtering import degenerate_cameras
from .model import Reconstruction

log = logging.getLogger("mvrecon.sfm")

MODEL = "SIMPLE_RADIAL"  # the model a camera may be moved from (the default)
CANDIDATES = ("OPENCV", "OPENCV_FISHEYE")  # the richer models tried, in order
MIN_IMAGES = 8  # registered images of a camera before its first trial (distortion is refined from 6)
MAX_TRIALS = 3  # at 8, 16 and 32 images: the corners are seen by then; a trial costs 1 + CANDIDATES BAs
# a camera is tried again only when its last trial came this close to a switch: the SIMPLE_RADIAL lenses of
# the suite score 0.99-1.0 at their first trial, and each retry cost 15% more mapping time (templeRing)
RETRY_RATIO = 0.9
# a candidate is kept below this share of SIMPLE_RADIAL's error; measured (docs/benchmarks.md, "Lens chosen
# from the data"): 0.30-0.44 on the wide lenses, 0.99-1.0 on the SIMPLE_RADIAL lenses of the suite
MAX_ERROR_RATIO = 0.8
# the global mapper's second start for a focal its view graph cannot calibrate, as a share of max(width, height)
# (about 100 deg across): from the 1.2 guess, coarse models of a 100 deg lens kept 2 of 12 images at 643 px,
# for the lens's 269
WIDE_FOCAL = 0.42
# tried only when the guess's coarse model kept under this share of its images: 2-4 of 12-24 on the wide lenses,
# 17-19 of 19-20 on the lenses SIMPLE_RADIAL describes (where the wide start cost 22% more mapping time)
WIDE_TRY = 0.8
MIN_GAIN = 1.2  # `fits_better`: observations a coarse model of as many images needs, as a share of the other's


@dataclass
class LensTrial:
    """One trial of a camera: its registered images, each model's error (px) after its BA, the model kept."""

    camera_id: int
    images: int
    trials: int  # this camera's trials so far, this one included
    errors: dict = field(default_factory=dict)
    chosen: str = MODEL

    def record(self) -> dict:
        """The trial as report.json lists it beside the camera (`Reconstruction.lens_trials`)."""
        return {"images": self.images, "trials": self.trials, "chosen": self.chosen,
                "max_error_ratio": MAX_ERROR_RATIO,
                "mean_error_px": {k: round(v, 4) for k, v in self.errors.items()}}

    def text(self) -> str:
        base = self.errors[MODEL]
        shown = ", ".join(f"{k} {v:.3f} px" for k, v in self.errors.items())
        verdict = (f"switched to {self.chosen}" if self.chosen != MODEL else
                   f"kept {MODEL} (a richer model must bring the error under {MAX_ERROR_RATIO:g}x "
                   f"{base:.3f} px)")
        return f"camera {self.camera_id} at {self.images} images: {shown}; {verdict}"


def due_cameras(m: Reconstruction) -> list[int]:
    """The cameras of `m` to try now: SIMPLE_RADIAL, not trusted (known intrinsics), with MIN_IMAGES
    registered images, or twice as many as at their last trial (`m.lens_trials`) when that one's best ratio
    was under RETRY_RATIO, and fewer than MAX_TRIALS trials."""
    users = np.bincount(m.camera_of[m.registered], minlength=int(m.camera_of.max()) + 1)
    out = []
    for c, cam in m.cameras.items():
        last = m.lens_trials.get(c)
        if cam.model != MODEL or cam.prior_trusted:
            continue
        if last is None:
            due = users[c] >= MIN_IMAGES
        else:
            errors = last["mean_error_px"]
            ratio = min(v for k, v in errors.items() if k != MODEL) / max(errors[MODEL], 1e-12)
            due = last["trials"] < MAX_TRIALS and ratio < RETRY_RATIO and users[c] >= 2 * last["images"]
        if due:
            out.append(int(c))
    return out


def converted_params(model: str, params: np.ndarray, width: int, height: int) -> np.ndarray:
    """SIMPLE_RADIAL parameters (f, cx, cy, k) as `model`'s with the same projection over the image: OPENCV's
    k1 is the same term, its k2, p1 and p2 start at zero; OPENCV_FISHEYE's focal, k1 and k2 are fitted by
    least squares to the pixel radius of rays out to the farthest corner (or short of where the lens
    flattens)."""
    f, cx, cy, k = np.asarray(params, float)
    if model == "OPENCV":
        return np.array([f, f, cx, cy, k, 0.0, 0.0, 0.0])
    if model != "OPENCV_FISHEYE":
        raise ValueError(f"no conversion from {MODEL} to {model}")
    corner = max(np.hypot(u - cx, v - cy) for u in (0.0, width) for v in (0.0, height)) / f
    reach = cammodel.undistort_normalized(MODEL, params, np.array([[corner, 0.0]]))[0, 0]
    if k < 0:  # r (1 + k r^2) grows at half its first rate at r^2 = -1 / (6k), and stops at -1 / (3k): past
        # there it is no lens a fisheye polynomial fits (the fitted focal came out negative on a 149 deg lens)
        flat = np.sqrt(-1.0 / (6.0 * k))
        reach = min(reach, flat) if 0 < reach else flat  # past the fold Newton may end anywhere (NaN, < 0)
    r = np.linspace(0.0, reach, 200)[1:]
    theta = np.arctan(r)
    rho = f * r * (1.0 + k * r * r)  # pixel radius, to be f' (theta + k1 theta^3 + ... + k4 theta^9)
    # k3 and k4 start at zero: fitted too, they trade off with k1 and k2 into coefficients past the
    # bogus-camera bound |k| <= 1 (`filtering.degenerate_cameras`)
    a = np.linalg.lstsq(np.stack([theta, theta ** 3, theta ** 5], axis=1), rho, rcond=None)[0]
    return np.array([a[0], a[0], cx, cy, a[1] / a[0], a[2] / a[0], 0.0, 0.0])


def camera_error(m: Reconstruction, obs: np.ndarray, cap: float) -> float:
    """Mean reprojection error (px) of observations `obs`, each capped at `cap`."""
    err, _ = m.reprojection_errors(obs)
    return float(np.mean(np.minimum(err, cap))) if len(err) else float("nan")


def _state(m: Reconstruction) -> tuple:
    return (m.R.copy(), m.t.copy(), m.xyz.data.copy(),
            {c: (cam.model, cam.params.copy()) for c, cam in m.cameras.items()})


def _restore(m: Reconstruction, state: tuple) -> None:
    m.R[:], m.t[:], m.xyz.data[:] = state[0], state[1], state[2]
    for c, (model, params) in state[3].items():
        m.set_camera_model(c, model, params)


def _plausible(m: Reconstruction, c: int, obs: np.ndarray) -> bool:
    """Not a bogus camera (`degenerate_cameras`), and a lens that does not fold over out to the farthest of the
    camera's observations `obs`. Past them the fit is unconstrained: keypoints a SIMPLE_RADIAL start could not
    undistort (its fold) are not in the model yet, and the mapping with the lens chosen refines it there. Judged
    out to the image's corners, a fisheye lens's right fit was refused (docs/benchmarks.md, "A fit that folds
    only beyond the observations")."""
    cam = m.cameras[c]
    if c in degenerate_cameras(m):
        return False
    fx, fy, cx, cy, _ = cammodel.split(cam.model, cam.params)
    uv = m.keypoints_at(m.obs_image.data[obs], m.obs_kp.data[obs])
    reach = float(np.hypot((uv[:, 0] - cx) / fx, (uv[:, 1] - cy) / fy).max(initial=0.0))
    return fold_radius(cam.model, cam.params, reach, samples=4000) is None


def try_richer_models(m: Reconstruction, c: int, adjust: Callable[[], None], cap: float) -> LensTrial:
    """Camera `c` tried with each of CANDIDATES: `adjust()` (a bundle adjustment of the model with the
    intrinsics refined) run with the camera as it is and from the same start with each candidate; the model
    leaves with the best plausible candidate when its error is under MAX_ERROR_RATIO of the current model's,
    else as it came (the trial changes nothing then)."""
    images = np.flatnonzero(m.registered & (m.camera_of == c))
    obs = m.observations_of_images(images)
    trial = LensTrial(int(c), len(images), m.lens_trials.get(int(c), {}).get("trials", 0) + 1)
    start = _state(m)
    adjust()
    trial.errors[MODEL] = camera_error(m, obs, cap)
    best = None
    for model in CANDIDATES:
        _restore(m, start)
        cam = m.cameras[c]
        m.set_camera_model(c, model, converted_params(model, start[3][c][1], cam.width, cam.height))
        adjust()
        error = camera_error(m, obs, cap)
        trial.errors[model] = error
        better = best is None or error < best[0]
        if better and error < MAX_ERROR_RATIO * trial.errors[MODEL] and _plausible(m, c, obs):
            best = (error, model, _state(m))
    if best is None:  # as before the trial, so that a camera that keeps its model maps as without trials
        _restore(m, start)
    else:
        trial.chosen = best[1]
        _restore(m, best[2])
    m.lens_trials[int(c)] = trial.record()
    log.info("lens of %s", trial.text())
    return trial


def fits_better(fit: tuple[int, int], other: tuple[int, int]) -> bool:
    """Whether a coarse model's fit (registered images, observations within the filters' gate) beats `other`'s:
    more images, or as many with MIN_GAIN times the observations; a focal far off leaves a coarse model of few
    images (a 150 deg lens: 3 of 12 from the guess, 5 from WIDE_FOCAL)."""
    return fit[0] > other[0] or (fit[0] == other[0] and fit[1] > MIN_GAIN * other[1])


def choose_models(m: Reconstruction, adjust: Callable[[], None], cap: float) -> bool:
    """Each camera of `m` due a trial (`due_cameras`) tried with the richer models (`try_richer_models`,
    `adjust()` a BA of the model with the intrinsics refined, `cap` the filters' threshold); True when one
    switched."""
    switched = False
    for c in due_cameras(m):
        switched |= try_richer_models(m, c, adjust, cap).chosen != MODEL
    return switched


def switched_cameras(models: list[Reconstruction]) -> dict[int, tuple[str, np.ndarray, dict]]:
    """Camera id -> (model, parameters, trial record) of the cameras a trial moved off MODEL, from the first of
    `models` (the largest first) that moved each."""
    out = {}
    for m in models:
        for c, record in m.lens_trials.items():
            if record["chosen"] != MODEL and c not in out:
                out[int(c)] = (m.cameras[c].model, m.cameras[c].params.copy(), record)
    return out

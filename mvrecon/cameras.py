"""Which images share a camera, and the starting intrinsics of each camera.

COLMAP's rule is the default: images of the same size taken with the same make/model/focal length share one
camera (and so one set of intrinsics to refine), which makes bundle adjustment far better conditioned than one
camera per image. The focal prior comes from EXIF when it can (35 mm equivalent, else focal length in mm times the
sensor's pixel density) and is then *trusted* (COLMAP's has_prior_focal_length: the verifier may estimate an
essential matrix with it); otherwise it is COLMAP's guess 1.2 * max(width, height), not trusted. Known intrinsics
given by the user are trusted as they are.
"""

from dataclasses import dataclass, field
from pathlib import PurePosixPath

import numpy as np

from .config import bounded
from .database import CameraInfo
from .errors import InputError
from .geometry import camera as camera_model
from .io.images import ImageMeta

CAMERA_MODES = ("auto", "single", "per-folder", "per-image")


def report_entry(camera_id: int, model: str, width: int, height: int, params: np.ndarray) -> dict:
    """A camera as report.json lists it (COLMAP's parameter order), for either engine's model."""
    return {"camera_id": int(camera_id), "model": model, "width": int(width), "height": int(height),
            "params": [float(v) for v in params]}


@dataclass(frozen=True)
class CameraConfig:
    model: str = "SIMPLE_RADIAL"  # SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV or OPENCV_FISHEYE
    mode: str = "auto"  # auto: same size + EXIF make/model/focal share a camera; single; per-folder; per-image
    params: tuple[float, ...] = ()  # known intrinsics in the model's COLMAP order; trusted; empty = from EXIF
    # focal guess without EXIF = factor * max(width, height), as COLMAP
    default_focal_factor: float = bounded(1.2, 0.0, low_open=True)
    # the user named the model (a flag or a config file), even the default one: the mapper then keeps it
    # (sfm/lens.py); out of the hash, and recorded by the features stage only when true (`model_left_open`)
    model_given: bool = field(default=False, metadata={"hash": False})

    @property
    def model_left_open(self) -> bool:
        """Whether the mapper may choose each camera's model from the data (sfm/lens.py): the default model,
        not named by the user, without known intrinsics."""
        return self.model == CameraConfig.model and not self.model_given and not self.params

    def validate(self, origin: dict[str, str] | None = None,
                 size: tuple[int, int] | None = None) -> "CameraConfig":
        """This config, or an InputError naming where the faulty value came from: `origin` maps "mode", "model"
        and "params" to how the user gave each ("--camera-model PINHOLE", "cams.toml: camera: mode = 'x'"); a
        field left out was not written by the user, so it is named only when no given one is at fault, and then
        as the default it is ("the default camera model SIMPLE_RADIAL"), not as a flag nobody typed. Without
        `origin`, the fields that differ from the defaults are named as flags. `size` (width, height) of the
        images the params are for places the farthest corner for the fold check; without it, the corner at
        (0, 0) does (the farthest one for a centred principal point)."""
        shown = ",".join(f"{v:g}" for v in self.params) if all(
            isinstance(v, (int, float)) for v in self.params) else repr(list(self.params))
        if origin is None:
            flags = {"mode": f"--camera-mode {self.mode}", "model": f"--camera-model {self.model}",
                     "params": f"--camera-params {shown}"}
            origin = {n: flag for n, flag in flags.items() if getattr(self, n) != getattr(CameraConfig, n)}

        def unwritten(name):  # a value set in code, or the default
            default = "the default " if getattr(self, name) == getattr(CameraConfig, name) else ""
            return f"{default}camera {name} {shown if name == 'params' else getattr(self, name)}"

        def where(*names):
            return " with ".join(origin[n] for n in names if n in origin) or " with ".join(map(unwritten, names))

        if self.mode not in CAMERA_MODES:
            raise InputError(f"{where('mode')}: expected one of {', '.join(CAMERA_MODES)}")
        if self.model not in camera_model.PARAM_NAMES:
            raise InputError(f"{where('model')}: expected one of {', '.join(camera_model.MODELS)}")
        try:
            camera_model.check_model(self.model, self.params if self.params else
                                     camera_model.default_params(self.model, 1.0, 2, 2))
        except ValueError as exc:
            raise InputError(f"{where('params', 'model') if self.params else where('model')}: {exc}") from None
        focal = [v for name, v in zip(camera_model.PARAM_NAMES[self.model], self.params) if name.startswith("f")]
        if not all(np.isfinite(self.params)) or (focal and min(focal) <= 0):
            raise InputError(f"{where('params')}: expected finite numbers and a positive focal length")
        if self.params:
            _refuse_fold(self.model, self.params, size, where('params'))
        return self


GIVEN_KEY = "camera_model_given"  # in the features stage's record when the user named the default model


def recorded_model_left_open(features: dict | None) -> bool:
    """`CameraConfig.model_left_open` of the run the features stage `features` recorded (its record's
    config: the camera table, and GIVEN_KEY when the default model was named), so that `map -w` decides as
    `reconstruct` did; False without a record (a database another tool made: its cameras are its choice)."""
    camera = (features or {}).get("camera")
    if not isinstance(camera, dict):
        return False
    return (camera.get("model") == CameraConfig.model and not camera.get("params")
            and not features.get(GIVEN_KEY, False))


def _refuse_fold(model: str, params, size: tuple[int, int] | None, where: str) -> None:
    """InputError when trusted params make the lens fold over inside the image: past the radius where the
    distorted radius stops growing with the ray's angle, two rays share a pixel and the image farther out has
    no ray, so a run with them failed late with no reason given (OPENCV_FISHEYE 285,285,320,240,-2,0,0,0 folds
    78 px out)."""
    fx, fy, cx, cy, _ = camera_model.split(model, params)
    w, h = size if size is not None else (0.0, 0.0)
    corner = max(np.hypot((u - cx) / fx, (v - cy) / fy) for u in (0.0, w) for v in (0.0, h))
    fold = fold_radius(model, params, corner)
    if fold is not None:
        focal = camera_model.focal_length(model, params)
        raise InputError(f"{where}: the {model} lens model folds over {fold * focal:.0f} px from the principal "
                         f"point, inside the image (its farthest corner is {corner * focal:.0f} px out), so the "
                         "image past that radius has no ray; check the distortion coefficients")


def fold_radius(model: str, params: np.ndarray, corner: float, samples: int = 20000) -> float | None:
    """The distorted radius (normalised image units) where the model's distortion stops growing with the ray's
    angle from the axis, when that is short of `corner` (normalised too), else None. Rays are sampled by angle up
    to 90 deg, which covers every ray of a pinhole model and every one a fisheye projects, toward the axes and
    the diagonals (OPENCV's tangential terms move a point off its ray, so one direction would not do)."""
    r = np.tan(np.linspace(0.0, np.pi / 2, samples, endpoint=False))
    folds = []
    for phi in np.arange(8) * np.pi / 4:
        rd = np.linalg.norm(camera_model.distort(model, params, r[:, None] * [np.cos(phi), np.sin(phi)]), axis=1)
        drop = np.flatnonzero(np.diff(rd) <= 0)
        if drop.size and rd[drop[0]] < corner:
            folds.append(float(rd[drop[0]]))
    return min(folds, default=None)


def focal_prior(meta: ImageMeta, default_factor: float = 1.2) -> tuple[float, bool]:
    """(focal length in pixels, trusted) for an image, from its EXIF when possible."""
    long_side = max(meta.width, meta.height)
    if meta.focal_35mm:
        return meta.focal_35mm / 36.0 * long_side, True  # the 35 mm frame is 36 mm on its long side
    if meta.focal_px_from_sensor:
        return meta.focal_px_from_sensor, True
    return default_factor * long_side, False


def group_cameras(names: list[str], metas: dict[str, ImageMeta],
                  config: CameraConfig) -> list[tuple[CameraInfo, list[str]]]:
    """Cameras (camera_id unset) and the images of each, in the order of `names`."""
    config.validate(size=(metas[names[0]].width, metas[names[0]].height) if config.params and names else None)
    groups: dict[tuple, list[str]] = {}
    for name in names:
        m = metas[name]
        if config.mode == "single":
            key = ()
        elif config.mode == "per-image":
            key = (name,)
        elif config.mode == "per-folder":
            key = (str(PurePosixPath(name).parent), m.width, m.height)
        else:
            key = (m.width, m.height, m.make, m.model, m.focal_mm, m.focal_35mm)
        groups.setdefault(key, []).append(name)
    if config.params:  # known intrinsics hold for one image size: a principal point is in pixels of it
        first = metas[names[0]]
        odd = next((n for n in names if (metas[n].width, metas[n].height) != (first.width, first.height)), None)
        if odd is not None:
            raise InputError(f"{odd}: is {metas[odd].width}x{metas[odd].height} but {names[0]} is "
                             f"{first.width}x{first.height}, and --camera-params holds the intrinsics of one "
                             "image size; give images of one size, or leave --camera-params out")
    out = []
    for members in groups.values():
        sizes = {(metas[n].width, metas[n].height) for n in members}
        if len(sizes) > 1:
            shown = ", ".join(f"{w}x{h}" for w, h in sorted(sizes))
            raise InputError(f"{members[0]}: --camera-mode {config.mode} needs images of one size, "
                             f"found {shown}")
        first = metas[members[0]]
        if config.params:
            params, trusted = camera_model.check_model(config.model, config.params), True
        else:
            focal, trusted = focal_prior(first, config.default_focal_factor)
            params = camera_model.default_params(config.model, focal, first.width, first.height)
        out.append((CameraInfo(model=config.model, width=first.width, height=first.height, params=params,
                               prior_trusted=trusted), members))
    return out


def parse_camera_params(text: str | None) -> tuple[float, ...]:
    """'f,cx,cy,k' (commas or spaces) -> floats; an unparsable list is an InputError naming the value."""
    if not text:
        return ()
    try:
        return tuple(float(v) for v in text.replace(",", " ").split())
    except ValueError:
        raise InputError(f"--camera-params {text!r}: expected numbers separated by commas") from None

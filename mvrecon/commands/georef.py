"""Georeference a finished model with ground control: markers seen in its images, or known camera positions.

Reads RUN/sparse/0 (or --model) and a control file: OpenDroneMap's gcp_list.txt (control points with their
pixels in the images, io/gcp.py), each point triangulated from its registered views with the model's cameras;
or a CSV of camera positions in the --pose-priors format (docs/georef.md: `name,lat,lon,alt` or `name,x,y,z` in a
named frame, optional sigmas). Fits the similarity taking the model onto them (robust: a control point far off
its sigmas is left out and named), writes the model in place in east/north/up metres about the control points'
median (or earth-centred with --frame ecef), and reports each control point's residual (and a marker's
reprojection error), also in RUN/georef.json.

Example:
  mvrecon georef out/ --gcp gcp_list.txt
"""

import argparse
import logging
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.colmap_model import load_reconstruction
from ..io.files import write_json
from ..io.gcp import is_gcp_list, read_gcp_list
from ..io.gps import enu_to_ecef, from_ecef, from_enu
from ..io.pose_priors import read_priors_csv
from ..sfm.config import FRAMES
from ..sfm.georef import CenterPriors, align_centres, triangulate_observed
from ..workspace import Workspace

ORDER = 33
ON_INTERRUPT = "the model is rewritten only at the end; rerun the same command"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", help="output folder of `mvrecon reconstruct` (holds sparse/0)")
    parser.add_argument("--gcp", required=True, metavar="CSV",
                        help="control points seen in the images (OpenDroneMap's gcp_list.txt: a frame line, then "
                             "geo_x geo_y geo_z im_x im_y image_name [gcp_name]), or known camera positions "
                             "(CSV: name,lat,lon,alt or name,x,y,z, optional sigma columns)")
    parser.add_argument("--model", default=None, help="model folder (default: RUN/sparse/0, the largest)")
    parser.add_argument("--frame", choices=FRAMES, default="enu",
                        help="write the model in metres east, north, up of the origin (enu, default) or "
                             "earth-centred (ecef)")


def _control_cameras(path: str, rec) -> tuple[list[str], np.ndarray, CenterPriors, dict]:
    """Control cameras: (their names, their centres in the model, their known positions, no extra record)."""
    centres = {im.name: np.asarray(im.projection_center()) for im in rec.images.values() if im.has_pose}
    gcp = read_priors_csv(path, sorted({im.name for im in rec.images.values()}))
    unregistered = sorted(set(gcp) - set(centres))
    if unregistered:
        raise InputError(f"{path}: names {len(unregistered)} image(s) the model has not registered: "
                         + ", ".join(unregistered[:10]))
    names = sorted(gcp)
    priors = CenterPriors.of({k: gcp[n] for k, n in enumerate(names)})
    used = [names[int(i)] for i in priors.image_ids]
    return used, np.array([centres[n] for n in used]), priors, {"kind": "cameras"}


def _control_points(path: str, rec) -> tuple[list[str], np.ndarray, CenterPriors, dict]:
    """Control points seen in the images: (their names, their positions triangulated in the model, their known
    positions, their views and reprojection errors for the record)."""
    points = read_gcp_list(path, sorted(im.name for im in rec.images.values()))
    images = {im.name: im for im in rec.images.values() if im.has_pose}
    few = [n for n, p in points.items() if sum(i in images for i in p.observations) < 2]
    if few:
        raise InputError(f"{path}: control point(s) seen in fewer than 2 registered images of the model, so not "
                         "placed in it: " + ", ".join(few[:10]))
    views = []
    for p in points.values():
        obs = []
        for name, uv in p.observations.items():
            if name in images:
                pose, cam = images[name].cam_from_world(), rec.cameras[images[name].camera_id]
                obs.append((np.asarray(pose.rotation.matrix()), np.asarray(pose.translation), cam.model.name,
                            np.asarray(cam.params, float), uv))
        views.append(obs)
    X, errors = triangulate_observed(views)
    names = list(points)
    behind = [n for n, x in zip(names, X) if not np.isfinite(x).all()]
    if behind:
        raise InputError(f"{path}: control point(s) whose rays in the model do not meet in front of the cameras "
                         "(pixels in the wrong images?): " + ", ".join(behind[:10]))
    priors = CenterPriors.of({k: points[n].prior for k, n in enumerate(names)})
    used = [names[int(i)] for i in priors.image_ids]
    record = {"kind": "points",
              "views": {n: len(views[names.index(n)]) for n in used},
              "reprojection_px": {n: round(float(np.sqrt(np.mean(errors[names.index(n)] ** 2))), 3) for n in used}}
    return used, X[priors.image_ids], priors, record


def run(args: argparse.Namespace) -> int:
    import pycolmap  # noqa: PLC0415 - the model's transform and writer, for this command only

    run_dir = Path(args.run)
    model_dir = Path(args.model) if args.model else run_dir / "sparse" / "0"
    if not model_dir.is_dir():
        raise InputError(f"{model_dir}: no model here (the output folder of `mvrecon reconstruct`, or --model)")
    with Workspace(run_dir).lock():
        rec = load_reconstruction(model_dir)
        control = _control_points if is_gcp_list(args.gcp) else _control_cameras
        used, located, priors, extra = control(args.gcp, rec)
        fit = align_centres(located, priors.positions, priors.sigmas)
        if fit is None:
            raise InputError(f"{args.gcp}: needs 3 or more control points (or registered cameras) spread in two "
                             "directions (not along one line) to fix a model's position, orientation and scale")
        T, inliers = fit
        frame = args.frame if priors.origin is not None else "local"
        rec.transform(pycolmap.Sim3d(T.scale, pycolmap.Rotation3d(T.R), T.t))
        if frame == "ecef":
            R, t = enu_to_ecef(priors.origin)
            rec.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(R), t))
        residuals = {n: d for n, d in zip(used, T.apply(located) - priors.positions)}
        rec.write(str(model_dir))
        record = {"frame": frame, "origin": None if priors.origin is None else priors.origin.tolist(),
                  "gcp": {"file": str(Path(args.gcp).resolve()), **extra, "scale": T.scale,
                          "rms_m": float(np.sqrt(np.mean([np.sum(d**2) for d, ok in zip(residuals.values(), inliers)
                                                          if ok]))),
                          "residuals_m": {n: [round(float(v), 4) for v in d] for n, d in residuals.items()},
                          "outliers": [n for n, ok in zip(used, inliers) if not ok]}}
        if priors.origin is not None:
            centres = {im.name: np.asarray(im.projection_center()) for im in rec.images.values() if im.has_pose}
            if frame == "ecef":
                centres = {n: from_ecef(c[None])[0] for n, c in centres.items()}
            else:
                centres = dict(zip(centres, from_enu(np.array(list(centres.values())), priors.origin)))
            record["cameras"] = {n: [float(a), float(b), round(float(c), 4)]
                                 for n, (a, b, c) in sorted(centres.items())}
        write_json(run_dir / "georef.json", record, indent=1)
    log = logging.getLogger("mvrecon")
    log.info("%s: georeferenced on %d of %d control %s (scale %.6g), RMS %.3f m, frame %s", model_dir,
             int(inliers.sum()), len(inliers), extra["kind"], T.scale, record["gcp"]["rms_m"], frame)
    for n, d in residuals.items():
        seen = (f", {extra['views'][n]} views, reprojection {extra['reprojection_px'][n]:.2f} px"
                if extra["kind"] == "points" else "")
        log.info("  %s: residual east %.3f north %.3f up %.3f m%s%s", n, *d, seen,
                 "" if n not in record["gcp"]["outliers"] else " (left out)")
    return 0

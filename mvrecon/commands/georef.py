"""Georeference a finished model with ground control: known positions of some of its cameras.

Reads RUN/sparse/0 (or --model) and a CSV of camera positions in the --pose-priors format (docs/georef.md:
`name,lat,lon,alt` or `name,x,y,z` in a named frame, optional sigmas), fits the similarity taking the cameras
onto them (robust: a control point far off its sigmas is left out and named), writes the model in place in
east/north/up metres about the control points' median (or earth-centred with --frame ecef), and reports each
control point's residual, also in RUN/georef.json.

Example:
  mvrecon georef out/ --gcp control.csv
"""

import argparse
import logging
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.colmap_model import load_reconstruction
from ..io.files import write_json
from ..io.gps import enu_to_ecef, from_enu
from ..io.pose_priors import read_priors_csv
from ..sfm.config import FRAMES
from ..sfm.georef import CenterPriors, align_centres
from ..workspace import Workspace

ORDER = 33
ON_INTERRUPT = "the model is rewritten only at the end; rerun the same command"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", help="output folder of `mvrecon reconstruct` (holds sparse/0)")
    parser.add_argument("--gcp", required=True, metavar="CSV",
                        help="known camera positions: name,lat,lon,alt or name,x,y,z (+ '# frame: enu LAT LON "
                             "ALT', 'ecef' or 'local'), optional sigma or sigma_h,sigma_v columns")
    parser.add_argument("--model", default=None, help="model folder (default: RUN/sparse/0, the largest)")
    parser.add_argument("--frame", choices=FRAMES, default="enu",
                        help="write the model in metres east, north, up of the origin (enu, default) or "
                             "earth-centred (ecef)")


def run(args: argparse.Namespace) -> int:
    import pycolmap  # noqa: PLC0415 - the model's transform and writer, for this command only

    run_dir = Path(args.run)
    model_dir = Path(args.model) if args.model else run_dir / "sparse" / "0"
    if not model_dir.is_dir():
        raise InputError(f"{model_dir}: no model here (the output folder of `mvrecon reconstruct`, or --model)")
    with Workspace(run_dir).lock():
        rec = load_reconstruction(model_dir)
        centres = {im.name: np.asarray(im.projection_center()) for im in rec.images.values() if im.has_pose}
        gcp = read_priors_csv(args.gcp, sorted({im.name for im in rec.images.values()}))
        unregistered = sorted(set(gcp) - set(centres))
        if unregistered:
            raise InputError(f"{args.gcp}: names {len(unregistered)} image(s) the model has not registered: "
                             + ", ".join(unregistered[:10]))
        by_id = {k: gcp[n] for k, n in enumerate(sorted(gcp))}
        names = sorted(gcp)
        priors = CenterPriors.of(by_id)
        used = [names[int(i)] for i in priors.image_ids]
        fit = align_centres(np.array([centres[n] for n in used]), priors.positions, priors.sigmas)
        if fit is None:
            raise InputError(f"{args.gcp}: needs 3 or more registered cameras spread in two directions (not along "
                             "one line) to fix a model's position, orientation and scale")
        T, inliers = fit
        frame = args.frame if priors.origin is not None else "local"
        rec.transform(pycolmap.Sim3d(T.scale, pycolmap.Rotation3d(T.R), T.t))
        if frame == "ecef":
            R, t = enu_to_ecef(priors.origin)
            rec.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(R), t))
        residuals = {n: T.apply(centres[n][None])[0] - p for n, p in zip(used, priors.positions)}
        rec.write(str(model_dir))
        record = {"frame": frame, "origin": None if priors.origin is None else priors.origin.tolist(),
                  "gcp": {"file": str(Path(args.gcp).resolve()), "scale": T.scale,
                          "rms_m": float(np.sqrt(np.mean([np.sum(d**2) for d, ok in zip(residuals.values(), inliers)
                                                          if ok]))),
                          "residuals_m": {n: [round(float(v), 4) for v in d] for n, d in residuals.items()},
                          "outliers": [n for n, ok in zip(used, inliers) if not ok]}}
        if priors.origin is not None:
            lla = from_enu(T.apply(np.array([centres[n] for n in sorted(centres)])), priors.origin)
            record["cameras"] = {n: [float(a), float(b), round(float(c), 4)]
                                 for n, (a, b, c) in zip(sorted(centres), lla)}
        write_json(run_dir / "georef.json", record, indent=1)
    log = logging.getLogger("mvrecon")
    log.info("%s: georeferenced on %d of %d control cameras (scale %.6g), RMS %.3f m, frame %s", model_dir,
             int(inliers.sum()), len(inliers), T.scale, record["gcp"]["rms_m"], frame)
    for n, d in residuals.items():
        log.info("  %s: residual east %.3f north %.3f up %.3f m%s", n, *d,
                 "" if n not in record["gcp"]["outliers"] else " (left out)")
    return 0

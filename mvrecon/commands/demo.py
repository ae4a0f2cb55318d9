"""Demo: render a small ground-truth scene, reconstruct it end to end, and print the accuracy.

Renders the catalog scene `object_orbit_small` (10 views, 640x480, known cameras) into OUT/scene, runs
`reconstruct` on its images into OUT/run, and compares the result with the scene's ground truth: registered
images, points, reprojection error, relative-pose AUC@1/5 deg, median rotation and camera-centre errors after a
Sim3 alignment. The figures are also written to OUT/accuracy.json. Everything is cached: a second run reuses the
scene and the finished reconstruction (--overwrite reconstructs again, e.g. with another --seed). --scene takes
the catalog's perspective scenes (kinds perspective and colmap_synthetic in `mvrecon scene list`); stereo pairs
and SEM tilt series have their own commands, `mvrecon stereo` and `mvrecon sem`.

Example:
  mvrecon demo -o out/demo
  mvrecon demo -o out/demo_wide --scene wide_orbit_small
  mvrecon demo -o out/demo_fisheye --scene fisheye_orbit_small --camera-model OPENCV_FISHEYE
"""

import argparse
import logging
import math
from pathlib import Path

from ..cameras import CameraConfig
from ..errors import InputError
from ..eval.compare import jsonable
from ..eval.ground_truth import load_ground_truth
from ..eval.metrics import accuracy_summary
from ..eval.models import load_reconstruction, model_stats, poses, sparse_models
from ..geometry.camera import MODELS
from ..io.files import write_json
from ..pipeline import FrontendConfig, ReconstructConfig, reconstruct
from ..scenes import make_scene
from ..scenes.catalog import load_entry
from ..sfm.config import MapperConfig
from ._options import non_negative_int
from .reconstruct import no_model

ORDER = 1
HOLDS_OUTPUT = True  # its -o folder is held against a second run (`io.files.hold_folder`)
ON_INTERRUPT = "features, matches and the mapping snapshot are kept; rerun the same command to continue"

SCENE = "object_orbit_small"


KINDS = ("perspective", "colmap_synthetic")  # scene kinds `reconstruct` is for (multi-view, perspective cameras)
OTHER_COMMANDS = {"stereo": "mvrecon stereo", "sem_tilt": "mvrecon sem"}  # the command for each other kind


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-o", "--output", default="out/demo", help="output folder (default: out/demo)")
    parser.add_argument("--scene", default=SCENE,
                        help=f"catalog scene to use, a perspective one (`mvrecon scene list`; default: {SCENE})")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="mapper seed (default 0)")
    parser.add_argument("--camera-model", choices=MODELS, default=None,
                        help=f"camera model to reconstruct with (default: {CameraConfig.model}, which the "
                             "mapper may turn into OPENCV or OPENCV_FISHEYE from the data; e.g. OPENCV for "
                             "wide_orbit_small, OPENCV_FISHEYE for fisheye_orbit_small)")
    parser.add_argument("--overwrite", action="store_true",
                        help="reconstruct OUT/run again from the start, e.g. with another --seed (the scene is "
                             "kept: it is the same for the same --scene)")


def check_scene_kind(name: str) -> None:
    """Refuse, before rendering, a scene demo cannot reconstruct: a stereo pair or an SEM tilt series ran to the
    end with 0 images registered (stereo) or failed after the whole reconstruction (SEM: no gt/sparse)."""
    kind = load_entry(name)[0].get("kind", "perspective")
    if kind not in KINDS:
        other = OTHER_COMMANDS.get(kind)
        instead = f"; for this one use `{other}` on the images of `mvrecon scene make {name} -o DIR`" if other else ""
        raise InputError(f"--scene {name}: a {kind} scene; demo reconstructs perspective scenes (kind "
                         f"{' or '.join(KINDS)} in `mvrecon scene list`){instead}")


def scene_model_hint(name: str, scene: Path | str, model: str) -> str | None:
    """The line naming the scene's own camera model when the demo reconstructs with another one (without it
    fisheye_orbit_small ran SIMPLE_RADIAL, AUC@1 0.50 against 0.91, with no word); None when they agree."""
    truth = sorted({cam.model.name for cam in load_reconstruction(Path(scene) / "gt" / "sparse").cameras.values()})
    if len(truth) != 1 or truth[0] == model:
        return None
    return (f"scene {name} is rendered with {truth[0]} cameras and this demo reconstructs with {model}; "
            f"--camera-model {truth[0]} fits the scene")


def run(args: argparse.Namespace) -> int:
    check_scene_kind(args.scene)
    log = logging.getLogger("mvrecon")
    out = Path(args.output)
    log.info("rendering scene %s into %s ...", args.scene, out / "scene")
    scene = make_scene(args.scene, out / "scene")
    # a model left open that the mapper may choose needs no hint: it logs its choice (sfm/lens.py)
    chooses = not args.camera_model and MapperConfig.choose_camera_model
    hint = None if chooses else scene_model_hint(args.scene, scene, args.camera_model or CameraConfig.model)
    if hint:
        log.info("%s", hint)
    run_dir = out / "run"
    camera = CameraConfig(model=args.camera_model, model_given=True) if args.camera_model else CameraConfig()
    config = ReconstructConfig(frontend=FrontendConfig(camera=camera), mapper=MapperConfig(seed=args.seed))
    report = reconstruct(config, scene / "images", run_dir, resume=True, overwrite=args.overwrite)
    models = sparse_models(run_dir / "sparse")
    gt = load_ground_truth(scene / "gt" / "sparse")
    summary = accuracy_summary([poses(m) for m in models], gt)
    stats = model_stats(models[0]) if models else {"registered": 0, "points": 0,
                                                   "mean_reprojection_error_px": None}
    keys = ("registered", "points", "mean_reprojection_error_px")
    result = {"scene": args.scene, "images": len(gt), **{k: stats[k] for k in keys},
              "models": len(models), "wall_s": report["total"]["wall_s"], **summary}
    # strict JSON (no NaN, which JSON has not): a figure there is none of is null
    write_json(out / "accuracy.json", jsonable(result), indent=1, allow_nan=False)
    if not models:  # the scene's images gave no model: say why (reconstruct's line), no figures to show
        return no_model(run_dir, report["images"])
    reprojection = stats["mean_reprojection_error_px"]
    lines = [
        f"mvrecon demo: scene {args.scene} ({len(gt)} images, ground truth in {scene / 'gt' / 'sparse'})",
        f"  registered images      {summary['registered']} / {len(gt)} in {len(models)} model(s)",
        f"  points                 {stats['points']}",
        "  reprojection error     "
        + (f"{reprojection:.3f} px (mean)" if reprojection is not None and math.isfinite(reprojection) else "-"),
        f"  relative pose AUC@1    {summary['auc@1']:.3f}",
        f"  relative pose AUC@5    {summary['auc@5']:.3f}",
    ]
    if "median_rotation_error_deg" in summary:
        lines += [f"  median rotation error  {summary['median_rotation_error_deg']:.4f} deg",
                  f"  median centre error    {summary['median_center_error']:.5f} "
                  f"({summary['median_center_error_pct']:.3f}% of the scene)"]
    lines += [f"  wall time              {report['total']['wall_s']:.1f} s (features, matching, mapping)",
              f"  outputs                {run_dir}/sparse/0, {run_dir}/points.ply, {run_dir}/report.json"]
    print("\n".join(lines))
    return 0

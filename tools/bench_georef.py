"""Georeferencing accuracy against a rendered scene's truth, and the bound GPS noise sets on it.

The bound: a model of perfect shape (the true camera centres) fitted by a similarity to fixes of the given noise
(true centres plus Gaussian noise of sigma east, north, up), repeated over many draws: the RMS distance of the
fitted centres from the truth is what any mapper can reach from such fixes alone. A run (`--run WORKSPACE`,
report.json with a `georef` entry) is scored by its cameras' distance from the truth, its scale error, its shape
after a similarity to the truth, and AUC@5 of its poses; with `--control`, the cameras as `mvrecon georef --gcp`
aligned them to ground control (georef.json).

  python tools/bench_georef.py SCENE --sigma 2.5 2.5 5 [--trials 2000] [--run WS] [--fixes PRIORS.csv]
  python tools/bench_georef.py SCENE --run WS --control
  python tools/bench_georef.py SCENE --drift WS [WS ...]

SCENE holds gt/sparse and, for the bound and the score, gt/gps.json (`mvrecon scene make`). --fixes: the priors
the run was given, to report the similarity of the true centres onto exactly those fixes (this draw's bound).
--drift: a loop's drift (street_long, whose last frame is back at its first): each run's model aligned to the
truth on its first 10 frames, the distance of its last frame from the truth, in metres and in % of the path, and
the largest distance of any frame (where the loop is farthest from its start).
"""

import argparse
import json
from pathlib import Path

import numpy as np

from mvrecon.eval.ground_truth import load_ground_truth
from mvrecon.eval.metrics import accuracy_summary
from mvrecon.eval.models import poses, sparse_models
from mvrecon.geometry.sim3 import umeyama
from mvrecon.io.colmap_model import load_reconstruction
from mvrecon.io.gps import to_enu
from mvrecon.io.pose_priors import read_priors_csv


def rms(d: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(d**2, axis=1))))


def bound(true: np.ndarray, sigma: np.ndarray, trials: int, seed: int) -> dict:
    """Percentiles of the RMS error (total, horizontal, vertical) and of |scale - 1| of a similarity taking the
    true centres onto noisy fixes."""
    rng = np.random.default_rng(seed)
    out = {"rms": [], "h": [], "v": [], "scale": []}
    for _ in range(trials):
        T = umeyama(true, true + rng.normal(0.0, 1.0, true.shape) * sigma)
        d = T.apply(true) - true
        out["rms"].append(rms(d))
        out["h"].append(rms(d[:, :2]))
        out["v"].append(float(np.sqrt(np.mean(d[:, 2] ** 2))))
        out["scale"].append(abs(T.scale - 1.0))
    return {k: {"median": round(float(np.median(v)), 4), "p90": round(float(np.percentile(v, 90)), 4)}
            for k, v in out.items()}


def score(run: Path, scene: Path, gps: dict, control: bool = False) -> dict:
    """A run's cameras against the truth: as mapped with its priors (report.json), or as `mvrecon georef --gcp`
    aligned them to ground control (georef.json) when `control`."""
    report = json.loads((run / "report.json").read_text())
    if control:
        geo = json.loads((run / "georef.json").read_text())["cameras"]
        cams = {n: dict(zip(("lat", "lon", "alt"), v)) for n, v in geo.items()}
    else:
        cams = report["georef"]["images"]
    names = sorted(n for n in cams if "lat" in cams[n])
    est = to_enu(np.array([[cams[n]["lat"], cams[n]["lon"], cams[n]["alt"]] for n in names]),
                 np.array(gps["origin"]))
    true = np.array([gps["images"][n]["true_enu"] for n in names])
    d = est - true
    shape = umeyama(est, true)
    gt = load_ground_truth(scene / "gt" / "sparse")
    acc = accuracy_summary([poses(r) for r in sparse_models(run / "sparse")], gt)
    return {"registered": len(names), "auc@5": round(float(acc["auc@5"]), 4), "rms_m": round(rms(d), 4),
            "rms_h_m": round(rms(d[:, :2]), 4),
            "rms_v_m": round(float(np.sqrt(np.mean(d[:, 2] ** 2))), 4),
            "mean_offset_m": [round(float(v), 4) for v in d.mean(axis=0)],
            "scale_error_pct": round(100.0 * (1.0 / shape.scale - 1.0), 4),
            "shape_rms_m": round(rms(shape.apply(est) - true), 4),
            "flagged": [f for m in report.get("georef", {}).get("models", []) for f in m.get("flagged", [])]}


def loop_drift(run: Path, scene: Path, first: int = 10) -> dict:
    """The drift at the loop's end of a run's largest model (see the module docstring)."""
    gt = load_reconstruction(scene / "gt" / "sparse")
    truth = {im.name: np.asarray(im.projection_center()) for im in gt.images.values()}
    rec = sparse_models(run / "sparse")[0]
    est = {im.name: np.asarray(im.projection_center()) for im in rec.images.values() if im.has_pose}
    names = sorted(est)
    e, t = np.array([est[n] for n in names]), np.array([truth[n] for n in names])
    path = float(np.sum(np.linalg.norm(np.diff(np.array([truth[n] for n in sorted(truth)]), axis=0), axis=1)))
    err = np.linalg.norm(umeyama(e[:first], t[:first]).apply(e) - t, axis=1)
    end = float(err[-1])
    acc = accuracy_summary([poses(r) for r in sparse_models(run / "sparse")],
                           load_ground_truth(scene / "gt" / "sparse"))
    return {"run": str(run), "registered": len(names), "last": names[-1], "path_m": round(path, 2),
            "loop_drift_m": round(end, 4), "loop_drift_pct": round(100.0 * end / path, 4),
            "max_drift_m": round(float(err.max()), 4), "max_drift_at": names[int(np.argmax(err))],
            "shape_rms_m": round(rms(umeyama(e, t).apply(e) - t), 4), "auc@5": round(float(acc["auc@5"]), 4)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path)
    ap.add_argument("--sigma", type=float, nargs=3, default=[2.5, 2.5, 5.0], metavar=("E", "N", "U"))
    ap.add_argument("--trials", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--run", type=Path, default=None, help="a workspace to score")
    ap.add_argument("--control", action="store_true",
                    help="score the run's cameras as `mvrecon georef --gcp` aligned them (RUN/georef.json)")
    ap.add_argument("--fixes", type=Path, default=None, help="the pose-prior CSV the run was given")
    ap.add_argument("--drift", type=Path, nargs="+", default=None, metavar="WS", help="runs to measure loop drift")
    args = ap.parse_args()
    if args.drift:
        for run in args.drift:
            print(json.dumps(loop_drift(run, args.scene)))
        return
    gps = json.loads((args.scene / "gt" / "gps.json").read_text())
    names = sorted(gps["images"])
    true = np.array([gps["images"][n]["true_enu"] for n in names])
    result = {"cameras": len(names), "sigma": args.sigma,
              "bound": bound(true, np.array(args.sigma), args.trials, args.seed)}
    if args.fixes is not None:
        priors = read_priors_csv(args.fixes, names)
        fixes = to_enu(np.array([priors[n].position for n in names]), np.array(gps["origin"]))
        d = umeyama(true, fixes).apply(true) - true
        result["this_draw"] = {"rms_m": round(rms(d), 4), "fixes_rms_m": round(rms(fixes - true), 4)}
    if args.run is not None:
        result["run"] = score(args.run, args.scene, gps, args.control)
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()

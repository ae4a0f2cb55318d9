"""How well a database's verified matches agree with ground-truth poses (not a test).

    .venv/bin/python tools/keypoint_accuracy.py GT DATABASE [DATABASE ...]

GT: a COLMAP model (a catalog scene's DIR/gt/sparse: poses and the true lens), a Middlebury `*_par.txt`, Strecha
`gt_dense_cameras/` or IMC `calibration/` (poses and K of undistorted images). DATABASE: ours
(`mvrecon features` + `match`) or COLMAP's, so both front ends are measured on the same images.

For every verified inlier match it takes the distance of the two keypoints to the true epipolar lines (the mean
of both, in pixels, through the true lens), and prints per database: inliers, the median distance, the share
above 1 px, the constant offset (px) that a keypoint convention error would add to every keypoint (fitted by
least squares on the matches within 1.5 px), and the median and share above 1 px per keypoint scale (sigma in
pixels). The distance along the epipolar line is not seen, so a wrong match along it counts as good. A
source whose K has its own pixel convention or principal point error shows it as the same offset for every
database (templeRing about (+2.5, -1.1) px, Strecha herzjesu about (+0.4, +0.4)): compare engines, and read
the absolute offset only on a catalog scene.
"""

import argparse
import sqlite3
from pathlib import Path

import numpy as np

from mvrecon import database as dbmod
from mvrecon.eval.ground_truth import load_ground_truth

SCALES = ((0, 1.2), (1.2, 2), (2, 3), (3, 5), (5, 10), (10, np.inf))


def _undistorter(gt_path: Path, gt):
    """name -> (pixels -> undistorted pixels of K, K): through the COLMAP model's lens, else K as given (COLMAP
    pixels less 0.5: those sources put the top-left pixel's centre at 0)."""
    if gt.kind == "colmap":
        import pycolmap

        model = pycolmap.Reconstruction(str(gt_path))  # kept alive: its cameras are views into it
        cams = {im.name: im.camera_id for im in model.images.values()}

        def undistort(name, xy):
            cam = model.cameras[cams[name]]
            K = np.asarray(cam.calibration_matrix())
            return np.asarray(cam.cam_from_img(xy)) @ K[:2, :2].T + K[:2, 2], K
        return undistort
    return lambda name, xy: (xy - 0.5, gt.intrinsics[name])


def _skew(t):
    return np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])


def _scale(kp: np.ndarray) -> np.ndarray:
    """Keypoint sigma in pixels: ours store it (x, y, scale, angle), COLMAP an affine shape (x, y, a11..a22)."""
    if kp.shape[1] >= 6:
        return np.sqrt(np.abs(kp[:, 2] * kp[:, 5] - kp[:, 3] * kp[:, 4]))
    return kp[:, 2]


def match_errors(gt_path: Path, database: Path):
    """(distance to the true epipolar lines, signed distance, its gradient w.r.t. a common keypoint offset,
    keypoint scale) over all verified inlier matches of pairs whose images both have ground truth."""
    gt = load_ground_truth(gt_path)
    undistort = _undistorter(gt_path, gt)
    db = sqlite3.connect(database)
    images = dbmod.read_images(db)
    keypoints = {i: dbmod.read_keypoints(db, i) for i in images}
    out = []
    for pair, data in db.execute("SELECT pair_id, data FROM two_view_geometries WHERE rows > 0"):
        i, j = dbmod.pair_images(pair)
        a, b = Path(images[i].name).name, Path(images[j].name).name
        if a not in gt or b not in gt:
            continue
        m = np.frombuffer(data, np.uint32).reshape(-1, 2).astype(np.int64)
        k1, k2 = keypoints[i][m[:, 0]], keypoints[j][m[:, 1]]
        (p1, K1), (p2, K2) = undistort(a, k1[:, :2]), undistort(b, k2[:, :2])
        (R1, t1), (R2, t2) = gt[a], gt[b]
        R = R2 @ R1.T
        F = np.linalg.inv(K2).T @ _skew(t2 - R @ t1) @ R @ np.linalg.inv(K1)
        x1, x2 = np.c_[p1, np.ones(len(p1))], np.c_[p2, np.ones(len(p2))]
        l2, l1 = x1 @ F.T, x2 @ F
        s = 0.5 * (1 / np.hypot(l2[:, 0], l2[:, 1]) + 1 / np.hypot(l1[:, 0], l1[:, 1]))
        signed = np.sum(x2 * l2, axis=1) * s
        out.append((np.abs(signed), signed, (l1[:, :2] + l2[:, :2]) * s[:, None],
                    np.maximum(_scale(k1), _scale(k2))))
    if not out:
        return None
    return [np.concatenate(parts) for parts in zip(*out)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("gt", type=Path)
    parser.add_argument("databases", type=Path, nargs="+")
    args = parser.parse_args()
    for database in args.databases:
        found = match_errors(args.gt, database)
        if found is None:
            print(f"{database}: no verified pair of two images with ground truth")
            continue
        err, signed, grad, scale = found
        near = err < 1.5
        offset = np.linalg.lstsq(grad[near], -signed[near], rcond=None)[0]
        print(f"{database}: {len(err)} inliers, median {np.median(err):.3f} px, {np.mean(err > 1):.1%} above 1 px, "
              f"constant offset ({offset[0]:+.3f}, {offset[1]:+.3f}) px")
        for low, high in SCALES:
            sel = (scale >= low) & (scale < high)
            if sel.any():
                print(f"  scale {low:>4}-{high:<4}: {sel.sum():7d} inliers, median {np.median(err[sel]):.3f} px, "
                      f"{np.mean(err[sel] > 1):.1%} above 1 px")


if __name__ == "__main__":
    main()

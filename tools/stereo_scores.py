"""Print the stereo score table: the paper's method (gee), OpenCV SGBM and `best` on scikit-image's Motorcycle,
Middlebury 2003 Cones (all and non-occluded pixels) and, with --scene, the catalog's rendered stereo_pair_small;
plus our eight-point F against OpenCV's on each pair. Run by hand:

    .venv/bin/python tools/stereo_scores.py [--scene]

bad-t counts holes as bad (the dense figure); bad-2-sparse is over predicted pixels only. Times are wall seconds
of the disparity step alone, with the ratio to OpenCV SGBM measured in the same run (pycolmap has no two-view
disparity to compare with: its PatchMatch stereo needs CUDA).
"""

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"


def pairs(with_scene: bool):
    import skimage.data

    from mvrecon.io.images import read_image
    from mvrecon.stereo.pipeline import load_ground_truth, load_mask

    left, right, gt = skimage.data.stereo_motorcycle()
    yield "Motorcycle (skimage, 741x500)", left, right, gt, None, 64
    cones = DATA / "stereo_middlebury2003_cones_gray"
    if cones.is_dir():
        yield ("Cones 2003 (450x375 grey)", read_image(cones / "left.png"), read_image(cones / "right.png"),
               load_ground_truth(cones / "disp_left.tif"), load_mask(cones / "occlusion.png"), 64)
    else:
        print(f"Cones not found at {cones}: skipped", file=sys.stderr)
    if with_scene:
        from mvrecon.scenes.catalog import make_scene
        from mvrecon.stereo.calib import read_calib

        folder = make_scene("stereo_pair_small", Path(tempfile.mkdtemp()) / "stereo_pair_small")
        yield ("catalog stereo_pair_small (640x480)", read_image(folder / "images" / "im0.png"),
               read_image(folder / "images" / "im1.png"), load_ground_truth(folder / "disp0GT.pfm"),
               load_mask(folder / "mask0nocc.png"), read_calib(folder / "calib.txt").ndisp)


def main() -> int:
    import cv2

    from mvrecon.geometry.fundamental import ransac_fundamental, sampson_distance
    from mvrecon.stereo.best import BestConfig, best_disparity
    from mvrecon.stereo.evaluate import evaluate, format_table
    from mvrecon.stereo.gee import GEEConfig, gee_disparity
    from mvrecon.stereo.pipeline import sift_matches
    from mvrecon.stereo.sgbm import SGBMConfig, sgbm_disparity

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", action="store_true", help="also render and score the catalog stereo scene")
    args = parser.parse_args()
    for title, left, right, gt, mask, ndisp in pairs(args.scene):
        x1, x2 = sift_matches(left, right)
        F, inl = ransac_fundamental(x1, x2)
        F_cv, m_cv = cv2.findFundamentalMat(x1, x2, cv2.FM_RANSAC, 1.0, 0.999)
        m_cv = m_cv.ravel() > 0
        print(f"\n## {title}: search range 0..{ndisp}\n")
        ours = np.median(sampson_distance(F, x1[inl], x2[inl]))
        cv_on_ours = np.median(sampson_distance(F_cv, x1[inl], x2[inl]))
        ours_on_cv = np.median(sampson_distance(F, x1[m_cv], x2[m_cv]))
        print(f"F: {len(x1)} matches; ours {inl.sum()} inliers, median Sampson {ours:.3f} px; OpenCV {m_cv.sum()} "
              f"inliers; OpenCV's F on our inliers {cv_on_ours:.3f} px; "
              f"our F on OpenCV's inliers {ours_on_cv:.3f} px\n")
        methods = {
            "gee (paper, alpha 3)": lambda: gee_disparity(left, right, GEEConfig(num_disparities=ndisp)).disparity,
            "gee (no removal)": lambda: gee_disparity(left, right, GEEConfig(num_disparities=ndisp,
                                                                               alpha=np.inf)).disparity,
            "sgbm (tuned)": lambda: sgbm_disparity(left, right, SGBMConfig(num_disparities=ndisp)),
            "sgbm (tuned, 0..80)": lambda: sgbm_disparity(left, right, SGBMConfig(num_disparities=80)),
            "best": lambda: best_disparity(left, right, BestConfig(num_disparities=ndisp)),
        }
        rows, times = {}, {}
        for name, fn in methods.items():
            t0 = time.perf_counter()
            d = fn()
            times[name] = time.perf_counter() - t0
            rows[name] = evaluate(d, gt, mask)
        print(format_table(rows))
        ref = times["sgbm (tuned)"]
        print("\ndisparity time (s): " + ", ".join(f"{n} {t:.2f} ({t / ref:.0f}x sgbm)" for n, t in times.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())

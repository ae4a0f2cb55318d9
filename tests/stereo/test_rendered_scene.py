"""The catalog's rendered stereo scene (Middlebury layout: im0/im1, calib.txt, disp0GT.pfm, mask0nocc.png):
`best` disparity and depth against its ground truth (the full CLI run is tested on Middlebury in test_two_view.py)."""

import numpy as np
import pytest


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from mvrecon.scenes import catalog

    return catalog.make_scene("stereo_pair_small", tmp_path_factory.mktemp("stereo_pair_small"))


def test_best_on_rendered_stereo_pair(scene):
    from mvrecon.io.images import read_image
    from mvrecon.stereo.best import BestConfig, best_disparity
    from mvrecon.stereo.calib import read_calib
    from mvrecon.stereo.depth import disparity_to_depth
    from mvrecon.stereo.evaluate import evaluate
    from mvrecon.stereo.pipeline import load_ground_truth, load_mask

    calib = read_calib(scene / "calib.txt")
    left, right = read_image(scene / "images" / "im0.png"), read_image(scene / "images" / "im1.png")
    gt, nonocc = load_ground_truth(scene / "disp0GT.pfm"), load_mask(scene / "mask0nocc.png")
    disparity = best_disparity(left, right, BestConfig(num_disparities=calib.ndisp))
    m = evaluate(disparity, gt, nonocc)
    assert m["nonocc"]["bad-2"] < 2.0  # measured 0.20
    assert m["all"]["bad-2"] < 5.0  # measured 0.47
    assert m["nonocc"]["avgerr"] < 0.5
    # the left-edge band where the search range reaches outside the right image: filled from its right, not left at
    # disparity 0 (before: 320 pixels at 0, band bad-2 8.4 %; measured now 0 and 0.0 %)
    band, gt_band = disparity[:, :calib.ndisp], gt[:, :calib.ndisp]
    known = np.isfinite(gt_band)
    assert band.min() >= 1.0 and np.mean(np.abs(band[known] - gt_band[known]) > 2) < 0.02
    depth = disparity_to_depth(disparity, calib.focal, calib.baseline, calib.doffs)
    gt_depth = 1000 * np.load(scene / "gt" / "depth" / "im0.npy")  # metres; calib.txt's baseline is in mm
    ok = nonocc & np.isfinite(depth) & np.isfinite(gt_depth)
    rel = np.abs(depth[ok] - gt_depth[ok]) / gt_depth[ok]
    assert np.median(rel) < 0.01

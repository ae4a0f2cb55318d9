"""The shared accuracy metrics: AUC as COLMAP's benchmark defines it, relative-pose and aligned absolute errors."""

import numpy as np
import pycolmap
import pytest

from mvrecon.eval import metrics, models
from mvrecon.geometry.rotation import angle_axis_to_rotmat


@pytest.fixture(scope="module")
def gt():
    opts = pycolmap.SyntheticDatasetOptions(num_rigs=1, num_frames_per_rig=8, num_points3D=50)
    return models.poses(pycolmap.synthesize_dataset(opts))


def similar_copy(poses, scale=2.0, rvec=(0.2, 0.5, -0.3), shift=(1, 2, 3)):
    R, t = angle_axis_to_rotmat(rvec), np.asarray(shift, float)
    out = {}
    for name, (Ri, ti) in poses.items():
        C = scale * R @ metrics.camera_center(Ri, ti) + t
        R2 = Ri @ R.T
        out[name] = (R2, -R2 @ C)
    return out


def test_auc_values_by_hand():
    auc = metrics.pose_auc([0, 0.5, 1, 20])
    assert auc[0.5] == pytest.approx(0.25)
    assert auc[1.0] == pytest.approx(0.4375)
    assert auc[10.0] == pytest.approx(0.725)
    assert metrics.pose_auc([180, 180])[10.0] == 0.0


def test_relative_pose_errors_by_hand():
    """Two cameras looking along z, 1 unit apart along x. An estimate that puts the second 1 unit along y instead
    has the relative pose's direction 90 deg off; one that turns the second by 2 deg about z in place is 2 deg
    off; a pair split across models fails."""
    turn = angle_axis_to_rotmat([0, 0, np.radians(2.0)])
    a, b = (np.eye(3), np.zeros(3)), (np.eye(3), -np.array([1.0, 0, 0]))
    gt = {"a": a, "b": b}
    moved = (np.eye(3), -np.array([0, 1.0, 0]))
    turned = (turn, turn @ b[1])
    assert metrics.relative_pose_errors([{"a": a, "b": moved}], gt) == pytest.approx([90.0])
    m = metrics.relative_pose_error_matrix([a, turned], [a, b])
    assert m[0, 1] == pytest.approx(2.0) and m[1, 0] == pytest.approx(2.0)
    assert (np.diag(m) == metrics.FAILED_DEG).all()  # an image with itself has no direction
    assert metrics.relative_pose_errors([{"a": a}, {"b": b}], gt) == pytest.approx([metrics.FAILED_DEG])


def test_a_model_against_itself_scores_exactly_one(gt):
    """Equal poses give errors of 0, not the 1e-6 deg an arccos of a cosine rounded below 1 gives: a model scored
    against itself (the study's clean model) has AUC 1.0 to the last digit."""
    errors = metrics.relative_pose_errors([gt], gt)
    assert np.abs(errors).max() < 1e-9
    assert metrics.accuracy_summary([gt], gt)["auc@1"] == 1.0


def test_similar_model_scores_perfectly(gt):
    s = metrics.accuracy_summary([similar_copy(gt)], gt)
    assert s["auc@0.5"] > 0.999 and s["registered"] == len(gt) and s["components"] == 1
    assert s["max_rotation_error_deg"] < 1e-6 and s["median_center_error_pct"] < 1e-6


def test_missing_and_split_images_count_as_failed_pairs(gt):
    names = sorted(gt)
    est = similar_copy(gt)
    first = {n: est[n] for n in names[:5]}
    second = {n: est[n] for n in names[5:7]}  # names[7] unregistered
    errors = metrics.relative_pose_errors([first, second], gt)
    n = len(names)
    assert len(errors) == n * (n - 1) // 2
    good_pairs = 5 * 4 // 2 + 1  # pairs inside the first model, and the one pair inside the second
    assert np.sum(errors < 1e-3) == good_pairs
    assert np.sum(errors == metrics.FAILED_DEG) == len(errors) - good_pairs


def test_alignment_reports_the_perturbed_image(gt):
    est = similar_copy(gt)
    name = sorted(gt)[3]
    R, t = est[name]
    R2 = angle_axis_to_rotmat([0, 0, np.radians(2.0)]) @ R
    est[name] = (R2, -R2 @ metrics.camera_center(R, t))  # same centre, turned by 2 degrees
    al = metrics.align_and_compare(est, gt)
    assert al.rotation_errors_deg[name] == pytest.approx(2.0, abs=1e-6)
    others = [v for k, v in al.rotation_errors_deg.items() if k != name]
    assert max(others) < 1e-6


@pytest.mark.parametrize("turn_deg, misplaced", [(4.0, False), (6.0, True), (90.0, True)])
def test_an_image_at_a_wrong_pose_is_counted_as_misplaced(gt, turn_deg, misplaced):
    """One image turned about its centre by more than 5 deg is misplaced, by less it is not; the others never are,
    whatever the model's frame."""
    est = similar_copy(gt)
    name = sorted(gt)[2]
    R, t = est[name]
    R2 = angle_axis_to_rotmat([np.radians(turn_deg), 0, 0]) @ R
    est[name] = (R2, -R2 @ metrics.camera_center(R, t))
    assert metrics.misplaced_images(est, gt) == ([name] if misplaced else [])
    assert metrics.accuracy_summary([est], gt)["misplaced"] == int(misplaced)


def test_a_model_mostly_at_wrong_poses_is_misplaced_throughout(gt):
    """Where every image is turned at random, no right majority remains: every image counts as misplaced."""
    rng = np.random.default_rng(0)
    est = {n: (angle_axis_to_rotmat(rng.normal(size=3)) @ R, t) for n, (R, t) in gt.items()}
    assert metrics.misplaced_images(est, gt) == sorted(gt)


def test_an_image_at_a_wrong_place_is_counted_as_misplaced(gt):
    """A camera at a right rotation but thrown far off (a wrong position from translation averaging) is
    misplaced too: its directions to the other cameras are wrong."""
    est = similar_copy(gt, scale=1.0, rvec=(0, 0, 0), shift=(0, 0, 0))
    name = sorted(gt)[4]
    R, t = est[name]
    centres = np.array([metrics.camera_center(*p) for p in gt.values()])
    far = metrics.camera_center(R, t) + 10 * np.ptp(centres, axis=0).max() * np.array([1.0, 0.0, 0.0])
    est[name] = (R, -R @ far)
    assert metrics.misplaced_images(est, gt) == [name]

"""Dense scoring: the truth of a rendered scene lies on its meshes, ETH3D-style scores of known clouds, the frame
alignment, and depth-map scores of COLMAP .bin maps."""

import math
import shutil

import numpy as np
import pycolmap
import pytest

from mvrecon.errors import InputError
from mvrecon.eval import dense
from mvrecon.eval.dense import DenseTruth, frame_alignment, score_cloud
from mvrecon.eval.models import load_reconstruction, poses
from mvrecon.geometry.rotation import rotation_error_deg
from mvrecon.geometry.sim3 import Sim3
from mvrecon.interrupts import import_open3d
from mvrecon.io.colmap_array import write_colmap_array
from mvrecon.io.ply import write_ply
from mvrecon.scenes.build import build_mesh
from mvrecon.scenes.catalog import load_entry


@pytest.fixture(scope="module")
def truth(object_orbit_small):
    return dense.scene_truth(object_orbit_small)


def plane_truth(spacing: float = 0.003, size: float = 1.0) -> DenseTruth:
    """Samples of the plane z = 0 on a square grid, every one seen by two views, extent 1."""
    g = np.arange(0.0, size, spacing)
    x, y = np.meshgrid(g, g)
    points = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1)
    return DenseTruth(points=points, views=np.full(len(points), 2), extent=1.0, spacing=spacing)


def test_truth_samples_lie_on_the_scene_meshes_and_most_are_seen_twice(truth):
    entry, _, path = load_entry("object_orbit_small")
    mesh = build_mesh(entry, path.parent)
    o3d = import_open3d()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                        o3d.core.Tensor(mesh.triangles.astype(np.uint32)))
    distance = scene.compute_distance(o3d.core.Tensor(truth.points.astype(np.float32))).numpy()
    assert np.quantile(distance, 0.999) < 0.05 * truth.spacing  # back-projected exactly (float32 depth)
    assert truth.spacing == pytest.approx(0.001 * truth.extent)
    assert 8.0 < truth.extent < 12.0  # the 8 m floor's diagonal, as far as the views see it
    seen = truth.views
    assert seen.min() >= 1 and seen.max() <= 10
    assert 0.85 < np.mean(seen >= 2) < 1.0  # a few faces (the floor's far edges) only one view sees
    # the samples are about a spacing apart: one per grid cell
    gaps = dense.cKDTree(truth.points).query(truth.points[::50], k=2)[0][:, 1]
    assert 0.2 * truth.spacing < np.median(gaps) < 1.5 * truth.spacing


def test_the_truth_itself_scores_one_and_nothing_scores_zero(truth):
    score = score_cloud(truth.points, truth)
    assert all(v == 1.0 for v in (*score.accuracy.values(), *score.completeness.values(), *score.fscore.values()))
    assert score.truth_points == int(np.sum(truth.views >= 2))
    empty = score_cloud(np.zeros((0, 3)), truth)
    assert set(empty.fscore.values()) == {0.0}


def test_noise_along_the_normal_gives_the_expected_accuracy():
    truth = plane_truth()
    rng = np.random.default_rng(3)
    sigma = 0.004
    cloud = truth.points.copy()
    cloud[:, 2] = rng.normal(0.0, sigma, len(cloud))  # the nearest sample stays the point's own
    score = score_cloud(cloud, truth)
    for tau in dense.TOLERANCES:
        assert score.accuracy[tau] == pytest.approx(math.erf(tau / (sigma * math.sqrt(2))), abs=0.01)
    # every sample keeps its noisy point within 1% (2.5 sigma) or has a neighbour that is
    assert score.completeness[0.01] > 0.99


def test_a_missing_half_gives_the_expected_completeness_and_full_accuracy():
    truth = plane_truth()
    cloud = truth.points[truth.points[:, 0] < 0.5]
    score = score_cloud(cloud, truth)
    last = cloud[:, 0].max()
    for tau in dense.TOLERANCES:
        expected = np.mean(truth.points[:, 0] <= last + tau)  # the cut's band within tau is still recalled
        assert score.completeness[tau] == pytest.approx(expected, abs=1e-9)
        assert 0.5 <= expected < 0.52 and (expected > 0.5) == (tau > truth.spacing)
        assert score.accuracy[tau] == 1.0
        assert score.fscore[tau] == pytest.approx(2 * expected / (1 + expected))


def test_points_seen_by_one_view_count_for_accuracy_but_not_completeness():
    truth = plane_truth()
    one_view = truth.points[:, 0] > 0.9
    truth = DenseTruth(points=truth.points, views=np.where(one_view, 1, 2), extent=1.0, spacing=truth.spacing)
    score = score_cloud(truth.points[~one_view], truth)
    assert score.completeness[0.002] == 1.0  # nothing one view sees is asked for
    assert score.accuracy[0.002] == 1.0
    score = score_cloud(truth.points, truth)
    assert score.accuracy[0.002] == 1.0  # ... and a point there is right


def random_poses(count: int, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    out = {}
    for k in range(count):
        q = rng.normal(size=4)
        out[f"{k:03d}.png"] = (pycolmap.Rotation3d(q / np.linalg.norm(q)).matrix(), rng.normal(0, 3, 3))
    return out


def transformed(poses_by_name: dict, sim: Sim3) -> dict:
    """The same cameras in the frame X' = s R X + t: cam_from_world' = (R_c R^T, s t_c - R_c R^T t)."""
    return {n: (Rc @ sim.R.T, sim.scale * tc - Rc @ sim.R.T @ sim.t) for n, (Rc, tc) in poses_by_name.items()}


def test_frame_alignment_recovers_a_known_similarity():
    truth = random_poses(8)
    q = pycolmap.Rotation3d(np.array([0.2, -0.4, 0.1, 0.9]) / np.linalg.norm([0.2, -0.4, 0.1, 0.9])).matrix()
    est_from_truth = Sim3(0.37, q, np.array([1.5, -2.0, 0.7]))
    est = transformed(truth, est_from_truth)
    est["000.png"] = (est["000.png"][0], est["000.png"][1] + 40.0)  # one camera far off: an outlier
    found = frame_alignment(est, truth)
    expected = est_from_truth.inverse()
    assert found.scale == pytest.approx(expected.scale, rel=1e-9)
    assert rotation_error_deg(found.R, expected.R) < 1e-6
    np.testing.assert_allclose(found.t, expected.t, atol=1e-8)
    with pytest.raises(InputError, match="3 are needed"):
        frame_alignment(dict(list(est.items())[:2]), truth)


@pytest.fixture(scope="module")
def exact_workspace(object_orbit_small, tmp_path_factory):
    """A dense workspace holding the truth itself in another frame: the scene's cameras moved by a similarity
    (scale 2.5) and each view's true depth, scaled alike, as its geometric .bin depth map."""
    folder = tmp_path_factory.mktemp("dense")
    rec = load_reconstruction(object_orbit_small / "gt" / "sparse")
    sim = pycolmap.Sim3d(2.5, pycolmap.Rotation3d(np.array([0.1, 0.2, -0.3, 0.93]) / np.linalg.norm(
        [0.1, 0.2, -0.3, 0.93])), np.array([0.4, -1.0, 2.0]))
    rec.transform(sim)
    (folder / "sparse").mkdir()
    rec.write_binary(str(folder / "sparse"))
    maps = folder / "stereo" / "depth_maps"
    maps.mkdir(parents=True)
    for image in rec.images.values():
        depth = np.load(object_orbit_small / "gt" / "depth" / image.name.replace(".png", ".npy"))
        write_colmap_array(maps / f"{image.name}.geometric.bin", np.where(np.isfinite(depth), 2.5 * depth, 0))
    return folder


def test_depth_scores_of_the_true_depth_are_one_and_of_a_wrong_half_a_half(exact_workspace, object_orbit_small,
                                                                            tmp_path):
    gt = poses(load_reconstruction(object_orbit_small / "gt" / "sparse"))
    to_truth = frame_alignment(poses(dense.dense_model(exact_workspace)), gt)
    assert to_truth.scale == pytest.approx(1 / 2.5, rel=1e-6)
    scores = dense.depth_scores(exact_workspace, object_orbit_small, to_truth)
    assert len(scores) == 10 and min(scores.values()) > 0.999

    broken = tmp_path / "broken"
    shutil.copytree(exact_workspace, broken)
    path = broken / "stereo" / "depth_maps" / "0003.png.geometric.bin"
    depth = dense.read_colmap_array(path)
    depth[:, : depth.shape[1] // 2] *= 1.02  # 2% too far on the left half
    write_colmap_array(path, depth)
    (broken / "stereo" / "depth_maps" / "0005.png.geometric.bin").unlink()
    scores = dense.depth_scores(broken, object_orbit_small, to_truth)
    valid = np.isfinite(np.load(object_orbit_small / "gt" / "depth" / "0003.npy"))
    right_half = valid[:, valid.shape[1] // 2:].sum() / valid.sum()
    assert scores["0003.png"] == pytest.approx(right_half, abs=0.005)
    assert scores["0005.png"] == 0.0  # no depth map: nothing right

    agreement = dense.depth_agreement(broken, stride=4)
    assert "0005.png" not in agreement
    assert agreement["0004.png"]["confirmed"] > 0.9
    assert agreement["0003.png"]["confirmed"] < agreement["0004.png"]["confirmed"] - 0.3
    assert agreement["0004.png"]["valid"] == pytest.approx(np.isfinite(np.load(
        object_orbit_small / "gt" / "depth" / "0004.npy")).mean())


def test_a_workspace_of_the_truth_scores_one_in_its_own_frame(exact_workspace, object_orbit_small, truth,
                                                             tmp_path):
    workspace = tmp_path / "dense"
    shutil.copytree(exact_workspace, workspace)
    gt = poses(load_reconstruction(object_orbit_small / "gt" / "sparse"))
    to_dense = frame_alignment(gt, poses(dense.dense_model(workspace)))
    write_ply(workspace / "fused.ply", to_dense.apply(truth.points))
    result = dense.score_workspace(workspace, object_orbit_small, truth)
    assert result["alignment_scale"] == pytest.approx(1 / 2.5, rel=1e-6)
    assert result["views"] == 10 and result["depth_within_1pct"] > 0.999
    fused = result["fused"]
    assert fused["points"] == len(truth.points)
    assert min(fused[f"fscore@{p}%"] for p in ("0.2", "0.5", "1")) > 0.999
    (workspace / "fused.ply").unlink()
    with pytest.raises(InputError, match="no fused.ply"):
        dense.score_workspace(workspace, object_orbit_small, truth)


@pytest.mark.slow
def test_the_fused_cloud_of_a_small_catalog_scene_scores_f_at_one_percent_of_0_85(object_orbit_small, truth,
                                                                                   tmp_path):
    """`mvrecon dense` on the scene's exact sparse model: its fused cloud, scored against the rendered truth."""
    from mvrecon.dense import run_dense

    summary = run_dense(object_orbit_small / "gt" / "sparse", object_orbit_small / "images", tmp_path / "dense",
                        mesh=False)
    assert not summary.skipped
    result = dense.score_workspace(tmp_path / "dense", object_orbit_small, truth)
    assert result["fused"]["fscore@1%"] >= 0.85
    assert result["depth_within_1pct"] > 0.4

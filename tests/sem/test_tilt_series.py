"""SEM tilt-series photogrammetry: geometry on exact correspondences, the rendered sem_tilt_small scene end to end,
ICP agreement of KD-tree and brute force, and one-line CLI errors on bad input."""

import json

import numpy as np
import pytest

from mvrecon.cli import main
from mvrecon.geometry.rotation import angle_axis_to_rotmat
from mvrecon.sem.affine import ransac_affine_fundamental, tilt_axis_from_affine_fundamental
from mvrecon.sem.factorization import Observations, solve_tilt_series
from mvrecon.sem.icp import icp, nearest_brute_force
from mvrecon.sem.parallax import heights_from_parallax, project_tilted


def _surface(n=1500, seed=0):
    """World points (reference pixels, centred) on a smooth height field with a bump and a ridge, heights ~0..40."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-200, 200, size=(n, 2))
    z = 30 * np.exp(-((xy[:, 0] - 40) ** 2 + (xy[:, 1] + 30) ** 2) / 80 ** 2) + 10 * np.sin(xy[:, 0] / 60) + 10
    return np.column_stack([xy, z])


def _observe(X, tilts, axis, noise_px, seed=1, drifts=None):
    rng = np.random.default_rng(seed)
    image, point, uv = [], [], []
    for i, t in enumerate(tilts):
        shift = (0.0, 0.0) if drifts is None else drifts[i]
        p = project_tilted(X, axis, t, (0.0, 0.0), shift) + rng.normal(0, noise_px, size=(len(X), 2))
        image.append(np.full(len(X), i))
        point.append(np.arange(len(X)))
        uv.append(p)
    return Observations(np.concatenate(image), np.concatenate(point), np.vstack(uv))


def _height_rms_percent(estimated, truth):
    r = estimated - truth
    r = r - np.median(r)
    return 100 * np.sqrt(np.mean(r ** 2)) / np.ptp(truth)


def test_known_tilts_height_rms_under_one_percent():
    X = _surface()
    tilts = (-10.0, 0.0, 10.0)
    obs = _observe(X, tilts, 90.0, 0.1, drifts=[(1.5, -2.0), (0, 0), (-3.0, 0.7)])
    sol = solve_tilt_series(obs, 3, reference=1, tilts_deg=tilts, axis_deg=90.0)
    assert _height_rms_percent(sol.points[:, 2], X[:, 2]) < 1.0
    # the paper's two-view step on the widest pair (drift across the axis only offsets the heights)
    pair = heights_from_parallax(obs.uv[obs.image == 0], obs.uv[obs.image == 2], -10.0, 10.0, 90.0, (0.0, 0.0))
    assert _height_rms_percent(pair[:, 2], X[:, 2]) < 1.0


def test_estimated_tilts_and_axis_from_three_views():
    X = _surface(seed=3)
    tilts = np.array([-8.0, 0.0, 7.0])
    axis = 75.0
    obs = _observe(X, tilts, axis, 0.1, seed=4, drifts=[(0.8, 1.1), (0, 0), (-1.2, 0.4)])
    sol = solve_tilt_series(obs, 3, reference=1)
    assert np.max(np.abs(sol.tilts_deg - tilts)) < 0.2, sol.tilts_deg
    assert abs(sol.axis_deg - axis) < 0.5
    # the height scale inherits the relative tilt error (bas-relief): 0.1 deg of 8 deg is already 1.25%
    assert _height_rms_percent(sol.points[:, 2], X[:, 2]) < 3.0


def test_affine_fundamental_rejects_mismatches_and_gives_the_axis():
    X = _surface(seed=5)
    rng = np.random.default_rng(6)
    x1 = project_tilted(X, 60.0, 0.0, (240.0, 240.0))
    x2 = project_tilted(X, 60.0, 8.0, (240.0, 240.0), (2.0, -1.0)) + rng.normal(0, 0.2, size=x1.shape)
    bad = rng.choice(len(X), 200, replace=False)
    # mismatches displaced along the tilt axis break the constraint (ones across it are invisible to it)
    a = np.array([np.cos(np.radians(60.0)), np.sin(np.radians(60.0))])
    x2[bad] += (rng.uniform(5, 60, 200) * rng.choice([-1, 1], 200))[:, None] * a
    F, inliers = ransac_affine_fundamental(x1, x2)
    assert not inliers[bad].any()
    assert np.delete(inliers, bad).mean() > 0.98
    assert abs(tilt_axis_from_affine_fundamental(F) - 60.0) < 0.5


def _moved_surface(n=3000, seed=7):
    """(source, target, R, t): target = R source + t, a 2 degree turn and a few pixels of shift."""
    X = _surface(n=n, seed=seed)
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    R = angle_axis_to_rotmat(np.radians(2.0) * axis)
    t = np.array([3.0, -2.0, 1.5])
    return (X - t) @ R, X, R, t


def test_icp_kdtree_and_brute_force_reach_the_same_transform():
    source, target, R, t = _moved_surface()
    kd = icp(source, target, "kdtree")
    bf = icp(source, target, "brute")
    assert kd.iterations == bf.iterations
    assert np.max(np.abs(kd.matrix - bf.matrix)) <= 1e-6 * np.max(np.abs(kd.matrix))
    assert np.allclose(kd.matrix[:3, :3], R, atol=1e-6) and np.allclose(kd.matrix[:3, 3], t, atol=1e-4)
    assert kd.rms < 1e-6


def test_brute_force_nearest_neighbours_match_a_kdtree():
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(3)
    targets = rng.uniform(-300, 300, size=(5000, 3))
    queries = rng.uniform(-300, 300, size=(777, 3))
    index, dist = nearest_brute_force(queries, targets, chunk_elements=50_000)  # many blocks
    ref_dist, ref_index = cKDTree(targets).query(queries)
    assert np.array_equal(index, ref_index)
    assert np.allclose(dist, ref_dist, rtol=1e-12, atol=1e-9)


def test_open3d_point_to_point_converges_and_agrees_with_brute_force():
    source, target, R, t = _moved_surface()
    o3 = icp(source, target, "open3d-point")
    bf = icp(source, target, "brute")
    assert np.allclose(o3.matrix[:3, :3], R, atol=1e-6) and np.allclose(o3.matrix[:3, 3], t, atol=1e-4)
    assert o3.pairs == len(source) and o3.rms < 1e-6
    assert np.max(np.abs(o3.matrix - bf.matrix)) <= 1e-6 * np.max(np.abs(bf.matrix))


def test_open3d_point_to_plane_converges_on_a_noisy_copy():
    source, target, R, t = _moved_surface(seed=8)
    source = source + np.random.default_rng(9).normal(0, 0.05, size=source.shape)
    result = icp(source, target, "open3d-plane")
    angle = np.degrees(np.arccos(np.clip((np.trace(result.matrix[:3, :3] @ R.T) - 1) / 2, -1, 1)))
    assert angle < 0.02, angle  # started 2 degrees off
    assert np.linalg.norm(result.matrix[:3, 3] - t) < 0.05
    assert result.rms < 0.2 and result.pairs > 0.95 * len(source)


def _tilted_views(heights, tilts, axis, seed=0):
    """Grey views of a random texture painted on the height field `heights` (pixels, on the 0-degree grid), seen
    at each tilt about the in-plane axis by parallel projection: each view pixel finds the surface point it sees
    by fixed-point iteration of x = R2^-1 (u - R[:2, 2] h(x)) (converges while sin(tilt) * slope < 1)."""
    import cv2

    from mvrecon.sem.parallax import tilt_rotation

    h, w = heights.shape
    rng = np.random.default_rng(seed)
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (h, w)).astype(np.float32), (0, 0), 1.2)
    texture = cv2.normalize(texture, None, 20, 235, cv2.NORM_MINMAX)
    centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    offsets = np.stack([xs - centre[0], ys - centre[1]], axis=-1)
    views = []
    for t in tilts:
        R = tilt_rotation(axis, t)
        inverse = np.linalg.inv(R[:2, :2])
        world = offsets @ inverse.T
        for _ in range(30):
            z = cv2.remap(heights.astype(np.float32), *(world + centre).astype(np.float32).transpose(2, 0, 1),
                          cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            world = (offsets - z[..., None] * R[:2, 2]) @ inverse.T
        u, v = (world + centre).astype(np.float32).transpose(2, 0, 1)
        views.append(np.clip(cv2.remap(texture, u, v, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT), 0, 255)
                     .astype(np.uint8))
    return views


def test_rectified_pairs_and_refinement_recover_heights_about_an_oblique_axis():
    """Three views of a bump on a slope, tilted -8, 0, 8 deg about an axis at 60 deg: the pairs' semi-global
    matches agree with the truth to a fraction of the whole-disparity step (7.1 px of height here), and the
    least-squares refinement from them to a fraction of a pixel. Measured: 0.84 px RMS (2.3 px with the axis
    taken 30 deg off), 0.13 px refined."""
    from mvrecon.sem.dense import fill_nearest, refine_heights
    from mvrecon.sem.rectified import StereoConfig, disparity_per_height, stereo_heights

    h = w = 128
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    truth = 25 * np.exp(-((xs - 70) ** 2 + (ys - 55) ** 2) / (2 * 22.0 ** 2)) + 0.1 * (xs - 64)  # 0..~30 px
    tilts, axis = [-8.0, 0.0, 8.0], 60.0
    images = _tilted_views(truth, tilts, axis)
    shifts = np.zeros((3, 2))
    matched, report = stereo_heights(images, tilts, axis, shifts, 1, (truth.min(), truth.max()), StereoConfig())
    assert [p["pair"] for p in report["pairs"]] == [[1, 0], [1, 2]]
    inner = np.zeros((h, w), bool)
    inner[16:-16, 16:-16] = True
    ok = inner & np.isfinite(matched)
    assert ok.sum() > 0.8 * inner.sum()
    assert 7.0 < 1 / abs(disparity_per_height(0.0, 8.0)) < 7.2  # px of height per px of disparity
    error = matched[ok] - truth[ok]
    assert abs(np.median(error)) < 0.3 and np.sqrt(np.mean(error ** 2)) < 1.5
    refined = refine_heights(images, tilts, axis, shifts, 1, fill_nearest(matched))
    error = (refined - truth)[inner]
    assert abs(np.median(error)) < 0.1 and np.sqrt(np.mean(error ** 2)) < 0.25


def test_combine_pairs_keeps_what_two_pairs_agree_on():
    from mvrecon.sem.rectified import combine_pairs

    nan = np.nan
    # per pixel: three pairs agree / one is wrong / only one matched / two disagree / two agree, one hole
    maps = np.array([[[10.0, 10.0, 10.0, 10.0, 10.0]],
                     [[10.5, 10.2, nan, 30.0, 10.4]],
                     [[9.5, 40.0, nan, nan, nan]]])
    scales = [1.0, 1.0, 0.5]  # the third pair has half the disparity per height: a quarter of the weight
    out = combine_pairs(maps, scales, tolerance_px=1.0)[0]
    assert out[0] == pytest.approx((10 + 10.5 + 0.25 * 9.5) / 2.25)
    assert out[1] == pytest.approx(10.1) and np.isnan(out[2]) and np.isnan(out[3])
    assert out[4] == pytest.approx(10.2)
    # a single pair (a two-image series) stands alone
    assert combine_pairs(maps[:1, :, 2:3], [1.0])[0, 0] == 10.0


@pytest.fixture(scope="module")
def sem_scene(tmp_path_factory):
    from mvrecon.scenes import make_scene

    root = tmp_path_factory.mktemp("sem_tilt_small")
    make_scene("sem_tilt_small", root)
    meta = json.loads((root / "gt" / "height.json").read_text())
    order = np.argsort(meta["tilt_angles_deg"])
    names = sorted((root / "images").iterdir(), key=lambda p: float(p.stem.split("_")[1]))
    return root, [str(p) for p in names], [meta["tilt_angles_deg"][i] for i in order], meta


def _scene_height_rms_percent(root, out):
    import tifffile

    gt = np.load(root / "gt" / "height.npy")
    est = tifffile.imread(out / "height.tif").astype(float)
    ok = np.isfinite(gt) & np.isfinite(est)
    assert ok.mean() > 0.9
    r = est[ok] - gt[ok]
    r -= np.median(r)  # heights are known up to an offset (no absolute reference on the specimen)
    return 100 * np.sqrt(np.mean(r ** 2)) / (np.nanmax(gt) - np.nanmin(gt))


def test_scene_known_tilts_end_to_end(sem_scene, tmp_path):
    root, images, tilts, meta = sem_scene
    out = tmp_path / "known"
    code = main(["-q", "sem", *images, "-o", str(out), "--tilts=" + ",".join(map(str, tilts)), "--axis", "y",
                 "--pixel-size", f"{meta['pixel_size_um']}um", "--gt", str(root / "gt" / "height.npy")])
    assert code == 0
    for name in ("height.tif", "height.png", "profile.png", "points.ply", "surface.ply", "report.json"):
        assert (out / name).is_file(), name
    # the default height map (sparse points refined by least-squares matching of all views, the neighbours'
    # plane as prior): measured 0.61% (0.81% with their mean as prior)
    rms = _scene_height_rms_percent(root, out)
    assert rms < 0.8
    # --gt scores the same way, over the same pixels; and every map made on the way (joint, merged points)
    report = json.loads((out / "report.json").read_text())
    accuracy = report["accuracy"]
    assert accuracy["height_source"] == "dense" and accuracy["units"] == "um"
    assert abs(accuracy["rms_percent_of_range"] - rms) < 1e-3 and accuracy["coverage"] > 0.99, accuracy
    assert sorted(accuracy["maps"]) == ["dense", "joint", "merged"]
    assert accuracy["maps"]["joint"]["rms_percent_of_range"] > 2 * rms  # measured 2.45%
    # the right axis agrees with the matches' own estimate (measured 89.89 deg, median of the 10 pairs)
    assert report["warnings"] == [] and report["axis_check"]["difference_deg"] < 0.5, report["axis_check"]


def test_scene_given_axis_contradicting_the_matches_is_warned(sem_scene, tmp_path, caplog):
    """--axis x on a series tilted about y: the heights come out 26 % of the range off (0.61 % with y), exit 0.
    The log and report.json say so, with the matches' axis and both adjustment RMS figures."""
    root, images, tilts, meta = sem_scene
    out = tmp_path / "axis_x"
    code = main(["-q", "sem", *images, "-o", str(out), "--tilts=" + ",".join(map(str, tilts)), "--axis", "x",
                 "--height-source", "joint"])
    assert code == 0
    report = json.loads((out / "report.json").read_text())
    check = report["axis_check"]
    assert check["given_deg"] == 0.0 and abs(check["from_pairs_deg"] - 90.0) < 1.0, check
    assert check["difference_deg"] > 85.0 and abs(check["axis_estimated_deg"] - 90.0) < 0.5, check
    # measured 1.124 px with the given axis, 0.135 px with the axis estimated
    assert check["rms_given_px"] > 5 * check["rms_axis_estimated_px"], check
    assert len(report["warnings"]) == 1
    warning = report["warnings"][0]
    assert warning.startswith("--axis 0 deg contradicts the matches, which put the tilt axis at 89.9 deg")
    assert f"{check['rms_given_px']:.3f} px with the given axis" in warning and "likely wrong" in warning
    assert [r.getMessage() for r in caplog.records if r.levelname == "WARNING"] == [f"warning: {warning}"]


def test_scene_estimated_tilts_end_to_end(sem_scene, tmp_path):
    root, images, tilts, meta = sem_scene
    out = tmp_path / "estimated"
    # the folder itself: its images come in signed-number order (tilt_-10.0 ... tilt_+10.0)
    assert main(["-q", "sem", str(root / "images"), "-o", str(out), "--estimate-tilts",
                 "--pixel-size", f"{meta['pixel_size_um']}um"]) == 0
    report = json.loads((out / "report.json").read_text())
    truth = np.array(tilts) - tilts[report["reference"]]
    assert np.max(np.abs(np.array(report["tilts_deg"]) - truth)) < 0.2, report["tilts_deg"]
    assert abs(report["axis_deg"] - 90.0) < 0.5
    # the height scale inherits the tilt error (bas-relief): measured 0.82% here (tilts off by up to 0.09 deg)
    assert _scene_height_rms_percent(root, out) < 1.0


def test_scene_stereo_height_source(sem_scene, tmp_path):
    """--height-source stereo: semi-global matching of the pairs (reference, other view), refined like dense."""
    root, images, tilts, meta = sem_scene
    out = tmp_path / "stereo"
    assert main(["-q", "sem", *images, "-o", str(out), "--tilts=" + ",".join(map(str, tilts)), "--axis", "y",
                 "--pixel-size", f"{meta['pixel_size_um']}um", "--height-source", "stereo",
                 "--gt", str(root / "gt" / "height.npy")]) == 0
    report = json.loads((out / "report.json").read_text())
    assert [p["pair"] for p in report["stereo"]["pairs"]] == [[2, 0], [2, 1], [2, 3], [2, 4]]
    maps = report["accuracy"]["maps"]
    # matched where two pairs agree (measured 98.8%), but locked to whole disparities (4.1%): the least-squares
    # refinement brings it to 0.61%
    matching, final = maps["stereo_matching"], maps["stereo"]
    assert matching["coverage"] > 0.9 and 2.0 < matching["rms_percent_of_range"] < 8.0, matching
    assert final["coverage"] > 0.99 and final["rms_percent_of_range"] < 0.8, final
    assert abs(_scene_height_rms_percent(root, out) - final["rms_percent_of_range"]) < 1e-3


def test_scene_height_source_option(sem_scene, tmp_path, capsys):
    root, images, tilts, meta = sem_scene
    out = tmp_path / "joint"
    assert main(["-q", "sem", *images, "-o", str(out), "--tilts=" + ",".join(map(str, tilts)), "--axis", "y",
                 "--pixel-size", f"{meta['pixel_size_um']}um", "--height-source", "joint"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["config"]["height_source"] == "joint"
    # interpolated sparse points (measured 2.46%) are what the default dense refinement improves on
    assert 1.5 < _scene_height_rms_percent(root, out) < 4.0
    with pytest.raises(SystemExit) as exc:
        main(["sem", *images, "-o", str(out), "--tilts=0,1,2,3,4", "--height-source", "bogus"])
    assert exc.value.code == 2 and "invalid choice: 'bogus'" in capsys.readouterr().err


def _noise_images(folder, count, seed=0):
    import cv2

    folder.mkdir()
    rng = np.random.default_rng(seed)
    paths = []
    for i in range(count):
        p = folder / f"img_{i}.png"
        cv2.imwrite(str(p), cv2.GaussianBlur(rng.integers(0, 255, (120, 120), dtype=np.uint8), (3, 3), 0))
        paths.append(str(p))
    return paths


def _error_lines(capsys, argv) -> tuple[int, list[str]]:
    """Exit code and stderr lines of one command."""
    code = main(argv)
    return code, capsys.readouterr().err.strip().splitlines()


def test_cli_help_documents_height_source(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["sem", "--help"])
    assert exc.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "--height-source {dense,stereo,joint,merged}" in text and "least-squares matching" in text
    assert "--gt GT" in text and "semi-global matching" in text


def test_cli_bad_input(tmp_path, capsys):
    import cv2

    images = _noise_images(tmp_path / "noise", 3)
    cases = [
        (["-q", "sem", *images, str(tmp_path / "missing.png"), "-o", str(tmp_path / "o0"), "--estimate-tilts"],
         "missing.png: no such file or folder"),
        (["-q", "sem", *images, "-o", str(tmp_path / "o1"), "--tilts", "0,5"], "2 angles given for 3 images"),
        (["-q", "sem", images[0], "-o", str(tmp_path / "o2"), "--tilts", "0"], "at least 2 images"),
        # independent noise images: nothing survives matching + affine verification
        (["-q", "sem", images[0], images[1], "-o", str(tmp_path / "o3"), "--tilts", "0,5"],
         "no image pair has verified matches"),
    ]
    wide = str(tmp_path / "noise" / "wide.png")
    cv2.imwrite(wide, np.zeros((120, 160), np.uint8))
    # the odd image and both sizes are named (this named the first image's folder and (h, w) tuples)
    cases.append((["-q", "sem", images[0], images[1], wide, "-o", str(tmp_path / "o5"), "--tilts", "0,5,10"],
                  f"{wide}: is 160x120 but {images[0]} is 120x120; the images of a tilt series must share one size"))
    for argv, expected in cases:
        code, lines = _error_lines(capsys, argv)
        assert code == 2 and len(lines) == 1 and expected in lines[0], (argv, code, lines)
    # o3 failed after its folder was made (matching): a failed run leaves no folder it created, nested ones too
    code, lines = _error_lines(capsys, ["-q", "sem", images[0], images[1], "-o", str(tmp_path / "o4" / "deep"),
                                        "--tilts", "0,5"])
    assert code == 2 and "no image pair has verified matches" in lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["noise"]
    (tmp_path / "mine").mkdir()  # a folder the user made stays
    assert _error_lines(capsys, ["-q", "sem", images[0], images[1], "-o", str(tmp_path / "mine"), "--tilts",
                                 "0,5"])[0] == 2
    assert (tmp_path / "mine").is_dir()


def test_cli_ground_truth_errors_are_one_line(tmp_path, capsys):
    images = _noise_images(tmp_path / "noise", 3)
    np.save(tmp_path / "small.npy", np.zeros((50, 60), np.float32))
    np.save(tmp_path / "cube.npy", np.zeros((2, 120, 120), np.float32))
    (tmp_path / "heights.txt").write_text("1 2 3")
    cases = [("missing.npy", f"{tmp_path / 'missing.npy'}: ground-truth height map not found"),
             ("small.npy", f"--gt: a 60x50 height map for 120x120 images ({images[0]}); it must lie on the input "
                           "images' grid"),
             ("cube.npy", "cube.npy: a height map has one value per pixel, this array has shape (2, 120, 120)"),
             ("heights.txt", "heights.txt: cannot read ground-truth heights (expected a .npy or .tif height map)")]
    for name, expected in cases:
        code, lines = _error_lines(capsys, ["-q", "sem", *images, "-o", str(tmp_path / "o"), "--tilts", "0,5,10",
                                            "--gt", str(tmp_path / name)])
        assert code == 2 and len(lines) == 1 and expected in lines[0], (name, lines)
        assert not (tmp_path / "o").exists()


def test_cli_refuses_one_view_given_twice(tmp_path, capsys):
    """The same image twice made a height map of -10.9..11 px out of zero parallax, exit 0. Refused in one line:
    the same file (before reading), identical pixels (before matching), or matches that move only by a common
    shift (a noisy or shifted copy: 2.3x and 0x the matching noise, tilted pairs 14.7x or more)."""
    import cv2

    images = _noise_images(tmp_path / "noise", 1)
    image = cv2.imread(images[0], cv2.IMREAD_UNCHANGED)
    noisy = np.clip(image + np.random.default_rng(1).normal(0, 2, image.shape), 0, 255).astype(np.uint8)
    copies = {"copy.png": image, "noisy.png": noisy, "shifted.png": np.roll(image, (2, 3), axis=(0, 1))}
    for name, pixels in copies.items():
        cv2.imwrite(str(tmp_path / name), pixels)
    cases = [([images[0], images[0]], f"{images[0]}: the same file as {images[0]} (given twice)"),
             ([images[0], str(tmp_path / "copy.png")], f"copy.png: identical pixels to {images[0]}"),
             ([images[0], str(tmp_path / "noisy.png")], "the matches show no parallax: the largest, with noisy.png"),
             ([images[0], str(tmp_path / "shifted.png")], "no parallax: the largest, with shifted.png, is 0.000 px")]
    for inputs, expected in cases:
        code, lines = _error_lines(capsys, ["-q", "sem", *inputs, "-o", str(tmp_path / "out"), "--tilts", "0,5"])
        assert code == 2 and len(lines) == 1 and expected in lines[0], (inputs, code, lines)
        assert not (tmp_path / "out").exists()


def test_motion_coherence_tells_a_small_tilt_step_from_a_copy():
    """Views 1 deg apart and two exposures of one view both move their matches by about 3x the matching noise
    (below MIN_PARALLAX_RATIO), but only tilting moves neighbouring points alike (measured 0.79 against 0.02)."""
    from mvrecon.sem.pipeline import MIN_MOTION_COHERENCE, MIN_PARALLAX_RATIO, _motion_coherence, _parallax

    X = _surface()
    rng = np.random.default_rng(10)

    def view(tilt):
        return project_tilted(X, 90.0, tilt, (240.0, 240.0)) + rng.normal(0, 0.1, size=(len(X), 2))

    x0 = view(0.0)
    for x1, tilted in ((view(1.0), True), (view(0.0), False)):
        F, inliers = ransac_affine_fundamental(x0, x1)
        spread, noise = _parallax(x0[inliers], x1[inliers], F)
        assert 1.5 < spread / noise < MIN_PARALLAX_RATIO, spread / noise  # measured 3.35 and 2.47
        coherence = _motion_coherence(x0[inliers], x1[inliers], 90.0)
        assert (coherence > 0.6) if tilted else (abs(coherence) < MIN_MOTION_COHERENCE / 3), coherence
    assert _motion_coherence(x0, x0 + [2.0, 3.0], 90.0) == 0.0  # a shifted copy: every match moves alike


def test_cli_refuses_a_copy_inside_a_longer_series(sem_scene, tmp_path, capsys):
    """A noisy or JPEG copy of the 0-degree view among three images passed the series check (its other pairs have
    parallax) and ran with exit 0: given as 5 deg, it bent the joint adjustment (RMS 0.247 px against 0.135 with
    the real 5-degree view); with estimated tilts, three images held two views. Refused in one line naming both."""
    import cv2

    root, images, tilts, meta = sem_scene
    minus5, zero = images[tilts.index(-5.0)], images[tilts.index(0.0)]
    image = cv2.imread(zero, cv2.IMREAD_UNCHANGED)
    noisy, jpeg = tmp_path / "noisy.png", tmp_path / "resaved.jpg"
    cv2.imwrite(str(noisy), np.clip(image + np.random.default_rng(1).normal(0, 2, image.shape), 0, 255).astype(
        np.uint8))
    cv2.imwrite(str(jpeg), image, [cv2.IMWRITE_JPEG_QUALITY, 90])
    out = tmp_path / "out"
    cases = [(noisy, ["--tilts=-5,0,5", "--axis", "y"], f"{noisy}: no parallax against {zero} although --tilts puts "
                                                        "them 5 deg apart: their matches move 0.0"),
             (jpeg, ["--estimate-tilts"], f"{jpeg}: no parallax against {zero}, although the series' other pairs "
                                          "show it: their matches move 0.0")]
    for copy, flags, expected in cases:
        code, lines = _error_lines(capsys, ["-q", "sem", minus5, zero, str(copy), "-o", str(out), *flags])
        assert code == 2 and len(lines) == 1 and expected in lines[0], lines
        assert "(coherence 0.0" in lines[0] and "the same view twice? remove one" in lines[0], lines
        assert not out.exists()


def test_cli_refuses_tilts_of_90_deg_or_more(tmp_path, capsys):
    """--tilts 0,180 was refused as "no two tilts differ" and --tilts=-5,175,5 was taken as three tilts (the
    180-degree view of parallel projection is the 0-degree one mirrored: no parallax). Refused before matching."""
    images = _noise_images(tmp_path / "noise", 3)
    reason = ("deg is not between -90 and 90 (at 90 the surface is edge-on, beyond it faces away; tilts 180 deg apart "
              "give one view mirrored, without parallax); give each image's stage tilt")
    for inputs, tilts, bad in ((images[:2], "0,180", "180"), (images, "-5,175,5", "175"),
                               (images, "0,5,-90", "-90"), (images, "0,10,370", "370")):
        code, lines = _error_lines(capsys, ["-q", "sem", *inputs, "-o", str(tmp_path / "o"), f"--tilts={tilts}"])
        assert code == 2 and lines == [f"mvrecon: error: --tilts {tilts}: {bad} {reason}"], lines
        assert not (tmp_path / "o").exists()


def test_cli_equal_tilts_are_refused_before_matching(tmp_path, capsys):
    """Images that share no match at all: the tilts are refused first (before, they were matched and then
    refused for having no verified matches)."""
    images = _noise_images(tmp_path / "noise", 3)
    code, lines = _error_lines(capsys, ["-q", "sem", *images, "-o", str(tmp_path / "o"), "--tilts", "2,2,2"])
    assert code == 2 and lines == ["mvrecon: error: --tilts 2,2,2: no two tilts differ, so the image pairs have "
                                   "no parallax (equal tilts) to give heights"], lines
    assert not (tmp_path / "o").exists()


def test_scene_repeated_exposure_in_a_series(sem_scene, tmp_path):
    """Two exposures at one tilt (--tilts 0,0,10) joined the series but made the run fail after the joint
    adjustment (their pair matched best, and gives no heights). The pair step now takes pairs with parallax."""
    import cv2

    root, images, tilts, meta = sem_scene
    zero, ten = images[tilts.index(0.0)], images[tilts.index(10.0)]
    image = cv2.imread(zero, cv2.IMREAD_UNCHANGED)
    again = tmp_path / "again.png"
    noise = np.random.default_rng(2).normal(0, 2, image.shape)
    cv2.imwrite(str(again), np.clip(image + noise, 0, 255).astype(np.uint8))
    out = tmp_path / "repeated"
    assert main(["-q", "sem", zero, str(again), ten, "-o", str(out), "--tilts", "0,0,10", "--axis", "y",
                 "--height-source", "joint"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert [0, 1] not in [p["pair"] for p in report["pair_point_sets"]] and report["warnings"] == []


def test_cli_equal_tilts_are_one_line(sem_scene, tmp_path, capsys):
    root, images, tilts, meta = sem_scene
    code, lines = _error_lines(capsys, ["-q", "sem", *images, "-o", str(tmp_path / "o"),
                                        "--tilts=" + ",".join("0" for _ in images), "--axis", "y"])
    assert code == 2 and len(lines) == 1 and "no parallax (equal tilts)" in lines[0], lines
    assert not (tmp_path / "o").exists()


def test_cli_refuses_an_output_folder_in_the_tilt_series(tmp_path, capsys):
    """height.png and friends written among the tilt images would join the series (a rerun then mixed sizes)."""
    images = _noise_images(tmp_path / "series", 3)
    series = tmp_path / "series"
    for inputs, output in (([str(series)], series), ([str(series)], series / "out"), (images, series)):
        code, lines = _error_lines(capsys, ["-q", "sem", *inputs, "-o", str(output), "--tilts", "0,5,10"])
        assert code == 2 and lines == [f"mvrecon: error: {output}: the output folder must be outside the image "
                                       f"folder {series.resolve()}"], lines
    assert sorted(p.name for p in series.iterdir()) == ["img_0.png", "img_1.png", "img_2.png"]
    code, lines = _error_lines(capsys, ["-q", "sem", *images, "-o", str(tmp_path / "o"), "--tilts", "0,nan,10"])
    assert code == 2 and lines == ["mvrecon: error: --tilts 0,nan,10: expected finite numbers"], lines


def test_dense_heights_show_their_progress(capsys, caplog, monkeypatch):
    import logging

    from mvrecon import progress
    from mvrecon.sem.dense import DenseMatchConfig, refine_heights

    monkeypatch.setattr(progress, "_enabled", True)
    caplog.set_level(logging.INFO, logger="mvrecon")
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 255, (48, 48), dtype=np.uint8) for _ in range(2)]
    config = DenseMatchConfig(iterations=2)
    heights = refine_heights(images, [0.0, 5.0], 90.0, np.zeros((2, 2)), 0, np.zeros((48, 48)), config)
    assert heights.shape == (48, 48)
    assert "dense heights: 100% |####################| 6/6" in capsys.readouterr().err  # 3 scales x 2 steps

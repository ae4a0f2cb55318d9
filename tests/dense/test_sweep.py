"""Depth maps: a fronto-parallel textured plane seen by three cameras, a rendered two-view pair of the catalog's
object_orbit_small scene against its exact depth, and the normals of a depth map."""

import cv2
import numpy as np
import pytest

from mvrecon.dense.sweep import pyramid_depth
from mvrecon.eval.ground_truth import load_ground_truth
from mvrecon.scenes import make_scene
from mvrecon.scenes.catalog import load_entry

K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
DEPTH = 4.0


def _render_plane(R: np.ndarray, t: np.ndarray, texture: np.ndarray, scale: float) -> np.ndarray:
    """The view (240x320) of the plane z = DEPTH (world = reference camera) carrying `texture`, whose pixel (u, v)
    sits at x = (u - w/2) * scale, y = (v - h/2) * scale."""
    h, w = texture.shape
    plane_from_texture = np.array([[scale, 0, -w / 2 * scale], [0, scale, -h / 2 * scale], [0, 0, 1]])
    image_from_plane = K @ np.column_stack([R[:, 0], R[:, 1], R[:, 2] * DEPTH + t])
    H = image_from_plane @ plane_from_texture
    return cv2.warpPerspective(texture, H, (320, 240), flags=cv2.INTER_LINEAR)


def test_fronto_parallel_plane_within_half_percent_on_95_percent_of_pixels():
    rng = np.random.default_rng(3)
    texture = cv2.GaussianBlur(rng.random((1200, 1600)).astype(np.float32), (0, 0), 2.0)
    texture = (texture - texture.min()) / (texture.max() - texture.min())
    scale = 3 * DEPTH / 300 / 1200 * 240 / 2  # the texture covers about three times the reference view
    cams = [(np.eye(3), np.zeros(3))]
    for angle, shift in ((4.0, [0.4, 0.0, 0.0]), (-3.0, [-0.35, 0.1, 0.05]), (2.0, [0.0, -0.3, 0.0])):
        R = cv2.Rodrigues(np.radians([0.0, angle, 0.0]))[0]
        cams.append((R, np.asarray(shift, float)))
    images = [_render_plane(R, t, texture, scale) for R, t in cams]
    # the default: a 320-px view is swept at full resolution
    depth, _, _ = pyramid_depth(images[0], images[1:], K, [K] * 3, cams[1:], (2.0, 10.0))
    good = np.abs(depth - DEPTH) <= 0.005 * DEPTH
    assert good.mean() >= 0.95, f"{good.mean():.3f} of the pixels within 0.5%"
    assert np.median(np.abs(depth[good] - DEPTH)) < 0.002 * DEPTH
    # coarse to fine, as larger views are: swept at 160 px, then searched locally at full resolution
    depth, _, _ = pyramid_depth(images[0], images[1:], K, [K] * 3, cams[1:], (2.0, 10.0), coarse_size=160)
    err = np.abs(depth - DEPTH) / DEPTH
    assert (err <= 0.005).mean() >= 0.92 and (err <= 0.01).mean() >= 0.97, (err <= 0.005).mean()


def test_normals_of_a_slanted_plane_from_its_matched_planes_within_a_few_degrees():
    """A textured plane seen at 35 degrees (a floor seen from above): each pixel's normal, taken from the plane
    PatchMatch matched there, against the plane's true normal."""
    rng = np.random.default_rng(4)
    texture = cv2.GaussianBlur(rng.random((1200, 1600)).astype(np.float32), (0, 0), 2.0)
    texture = (texture - texture.min()) / (texture.max() - texture.min())
    scale = 6 * DEPTH / 300 / 1200 * 240 / 2  # twice the fronto-parallel test's: the slanted view sees farther
    tilt = cv2.Rodrigues(np.radians([35.0, 0.0, 0.0]))[0]  # the reference camera turned about its x axis
    cams = [(tilt, np.zeros(3))]
    for angle, shift in ((4.0, [0.4, 0.0, 0.0]), (-3.0, [-0.35, 0.1, 0.05]), (2.0, [0.0, -0.3, 0.0])):
        cams.append((cv2.Rodrigues(np.radians([0.0, angle, 0.0]))[0] @ tilt, np.asarray(shift, float)))
    images = [_render_plane(R, t, texture, scale) for R, t in cams]
    relative = [(R @ tilt.T, t) for R, t in cams[1:]]  # reference camera -> source (the reference is at 0)
    depth, _, normals = pyramid_depth(images[0], images[1:], K, [K] * 3, relative, (2.0, 10.0), coarse_size=160)
    true = tilt @ [0.0, 0.0, -1.0]  # the plane z = DEPTH's normal towards the cameras, in the reference's frame
    known = depth > 0
    assert known.mean() > 0.8 and np.allclose(np.linalg.norm(normals[known], axis=1), 1, atol=1e-4)
    assert not normals[~known].any()
    angle = np.degrees(np.arccos(np.clip(normals[known] @ true, -1, 1)))
    # measured: median 2.7 degrees, 77% within 5 (the depth map's finite differences: 4.1 and 55%)
    assert np.median(angle) < 3.5 and np.mean(angle < 5.0) > 0.7, (np.median(angle), np.mean(angle < 5.0))


@pytest.fixture(scope="module")
def orbit_pair(tmp_path_factory):
    """object_orbit_small's objects seen by two PINHOLE cameras 12 degrees apart on its orbit (640x480): a
    gravel floor seen at a grazing angle, box faces and a sphere, with exact cameras and depth maps."""
    folder = tmp_path_factory.mktemp("orbit_pair")
    text = load_entry("object_orbit_small")[2].read_text()
    for old, new in {'model = "SIMPLE_RADIAL"': 'model = "PINHOLE"', "count = 10": "count = 2",
                     "[560.0, 320.0, 240.0, -0.03]": "[560.0, 560.0, 320.0, 240.0]",
                     "arc_deg = 180.0": "arc_deg = 12.0\nstart_deg = 30.0"}.items():
        assert old in text
        text = text.replace(old, new)
    (folder / "orbit_pair.toml").write_text(text)
    return make_scene(str(folder / "orbit_pair.toml"), folder / "scene")


@pytest.fixture(scope="module")
def pair_problem(orbit_pair):
    """pyramid_depth's inputs for the pair (view 0 against view 1), its true depth, and the pixels that count.

    The pixels that count: those whose whole matching window (radius 4, the default) the source sees - its
    surface point projects inside the source image and is the surface the source's own true depth shows
    there (not hidden) - since two views can only agree on what both see; and with the texture the method
    needs to match at all (a window's grey-level spread of at least min_std = 0.004, its default). That is
    every surface pixel except the sky, the parts outside the source's view, and occlusion borders."""
    K = np.array([[560.0, 0, 320], [0, 560.0, 240], [0, 0, 1]])
    gt = load_ground_truth(orbit_pair / "gt" / "sparse")
    (R0, t0), (R1, t1) = gt["0000.png"], gt["0001.png"]
    R = R1 @ R0.T
    ref, src = (cv2.imread(str(orbit_pair / "images" / n), cv2.IMREAD_GRAYSCALE).astype(np.float32) / 255
                for n in ("0000.png", "0001.png"))
    true, true_src = (np.load(orbit_pair / "gt" / "depth" / n) for n in ("0000.npy", "0001.npy"))
    known = np.isfinite(true)
    rows, cols = true.shape
    ys, xs = np.mgrid[0:rows, 0:cols]
    z = np.where(known, true, 1.0)
    X = np.stack([(xs - K[0, 2]) / K[0, 0] * z, (ys - K[1, 2]) / K[1, 1] * z, z], axis=-1) @ R.T + (t1 - R @ t0)
    u = np.round(X[..., 0] / X[..., 2] * K[0, 0] + K[0, 2]).astype(int)
    v = np.round(X[..., 1] / X[..., 2] * K[1, 1] + K[1, 2]).astype(int)
    inside = known & (X[..., 2] > 0) & (u >= 0) & (v >= 0) & (u < cols) & (v < rows)
    seen = inside.copy()
    seen[inside] = np.abs(true_src[v[inside], u[inside]] - X[..., 2][inside]) <= 0.01 * X[..., 2][inside]
    window = np.ones((9, 9), np.uint8)
    seen = cv2.erode(seen.astype(np.uint8), window, borderValue=0).astype(bool)
    mean = cv2.blur(ref, (9, 9))
    textured = cv2.blur(ref * ref, (9, 9)) - mean * mean >= 0.004**2
    counted = seen & textured
    assert counted.mean() > 0.5  # most of the image: floor, box faces and sphere
    inputs = (ref, [src], K, [K], [(R, t1 - R @ t0)], (0.8 * true[known].min(), 1.25 * true[known].max()))
    return inputs, true, counted


@pytest.fixture(scope="module")
def pair_depth(pair_problem):
    """The pair's depth map as `mvrecon dense` makes it (in bands, one thread)."""
    return pyramid_depth(*pair_problem[0])[0]


@pytest.mark.slow
def test_depth_of_a_rendered_pair_within_half_percent_on_95_percent_of_the_pixels_both_views_see(pair_problem,
                                                                                                pair_depth):
    _, true, counted = pair_problem
    error = np.abs(pair_depth[counted] - true[counted]) / true[counted]
    assert (error <= 0.005).mean() >= 0.95, f"{(error <= 0.005).mean():.4f} of the pixels within 0.5%"
    assert (error <= 0.01).mean() >= 0.97


@pytest.mark.slow
def test_tiles_give_the_same_depth_on_any_threads_and_score_as_one_whole_view(pair_problem, pair_depth):
    """Bands of 64 rows, run on 1 or 2 threads: the same map bit for bit (each band starts from the planes as
    they were before the pass and has its own random seed, whatever thread runs it). Against the truth, the
    bands score as the whole view in one piece: their borders only delay a plane's spread by a pass."""
    inputs, true, counted = pair_problem
    two = pyramid_depth(*inputs, threads=2)[0]
    assert np.array_equal(two, pair_depth)
    whole = pyramid_depth(*inputs, tile_rows=0)[0]
    assert not np.array_equal(whole, pair_depth)  # the bands did split the work
    within = [np.mean(np.abs(d - true)[counted] <= 0.005 * true[counted]) for d in (pair_depth, whole)]
    assert abs(within[0] - within[1]) <= 0.005, within

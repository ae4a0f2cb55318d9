"""The scale scenes (aerial_survey, street_long, dense_orbit): trajectories that grow with --count at constant
overlap, sites whose textures never repeat, ground truth that matches the images, GPS EXIF within its stated
noise, and mvrecon reconstructing each small variant."""

import json

import numpy as np
import pytest

from mvrecon.cli import main
from mvrecon.eval.ground_truth import load_ground_truth
from mvrecon.eval.metrics import accuracy_summary, camera_center
from mvrecon.eval.models import load_reconstruction, poses, sparse_models
from mvrecon.io.gps import read_gps, to_enu
from mvrecon.scenes import make_scene
from mvrecon.scenes.build import build_mesh, build_poses
from mvrecon.scenes.catalog import load_entry, with_count
from mvrecon.scenes.render import Renderer
from tests.helpers import bilinear

SCALE = ("aerial_survey", "street_long", "dense_orbit")
SMALL = tuple(f"{name}_small" for name in SCALE)
# the small variants at a quarter of their size, one ray per pixel and small textures: the geometry and the
# ground truth are the same, in a few seconds
TINY = {
    "width = 640": "width = 160",
    "height = 480": "height = 120",
    "supersample = 2": "supersample = 1",
    "[500.0, 320.0, 240.0, -0.02]": "[125.0, 80.0, 60.0, -0.02]",
    "[450.0, 320.0, 240.0, -0.02]": "[112.5, 80.0, 60.0, -0.02]",
    "[560.0, 320.0, 240.0, -0.03]": "[140.0, 80.0, 60.0, -0.03]",
    "texture_size = 512": "texture_size = 32",
    "texture_size = 1024": "texture_size = 64",
    "size = 2048": "size = 128",
}


def tiny_toml(name, folder):
    text = load_entry(name)[2].read_text()
    for old, new in TINY.items():
        text = text.replace(old, new)
    assert "width = 160" in text and "supersample = 1" in text
    path = folder / f"{name}.toml"
    path.write_text(text)
    return str(path)


@pytest.fixture(scope="module")
def tiny_scenes(tmp_path_factory):
    """name -> the folder of that small variant made tiny, rendered once for the module."""
    made = {}

    def scene(name):
        if name not in made:
            folder = tmp_path_factory.mktemp(name)
            made[name] = make_scene(tiny_toml(name, folder), folder / "scene")
        return made[name]

    return scene


def centres(pose_list):
    return np.array([camera_center(R, t) for R, t in pose_list])


def test_survey_covers_a_larger_area_at_the_same_overlap():
    entry = load_entry("aerial_survey")[0]
    traj, cam = entry["trajectory"], entry["camera"]
    footprint_along = traj["altitude"] * cam["height"] / cam["params"][0]  # the image's short side
    assert 0.7 <= 1.0 - traj["along"] / footprint_along <= 0.8  # the 70-80% forward overlap
    areas = {}
    for count in (100, 300, 1000):
        views = build_poses(with_count(entry, "", count)[0])
        assert len(views) == count
        c = centres(views)
        areas[count] = np.prod(np.ptp(c[:, :2], axis=0))
        # neighbours on a line: `along` apart (up to the wind's jitter); lines `across` apart
        steps = np.linalg.norm(np.diff(c[:, :2], axis=0), axis=1)
        on_line = steps < traj["along"] * 1.5
        assert np.median(steps[on_line]) == pytest.approx(traj["along"], rel=0.05)
        xs = np.unique(np.round(c[:, 0] / traj["across"]))
        assert np.all(np.diff(xs) == 1)
        axes = np.array([R[2] for R, _ in views])  # viewing directions
        tilt = np.degrees(np.arccos(np.clip(-axes[:, 2], -1, 1)))
        assert np.mean(tilt > 15) == pytest.approx(1 / traj["oblique_every"], abs=0.01)
        assert np.max(tilt) < traj["oblique_deg"] + 5
    assert areas[300] / areas[100] == pytest.approx(3, rel=0.3)
    assert areas[1000] / areas[100] == pytest.approx(10, rel=0.3)


def test_street_loop_returns_to_its_start_and_grows_with_the_count():
    entry = load_entry("street_long")[0]
    step = entry["trajectory"]["step"]
    for count in (100, 300):
        views = build_poses(with_count(entry, "", count)[0])
        c = centres(views)
        gaps = np.linalg.norm(np.diff(np.r_[c, c[:1]], axis=0), axis=1)
        assert np.all(np.abs(gaps - step) < 0.1 * step)  # the last view is one step before the first
        first, last = views[0][0][2], views[-1][0][2]
        assert np.degrees(np.arccos(first @ last)) < 10  # and looks the same way
        assert np.sum(np.ptp(c[:, :2], axis=0)) * 2 == pytest.approx(count * step, rel=0.1)


def test_dense_orbit_densifies_on_the_same_two_rings():
    entry = load_entry("dense_orbit")[0]
    traj = entry["trajectory"]
    for count in (100, 1000):
        c = centres(build_poses(with_count(entry, "", count)[0]))
        assert len(c) == count
        assert np.allclose(np.linalg.norm(c[:, :2] - traj["target"][:2], axis=1), traj["radius"])
        heights, per_ring = np.unique(np.round(c[:, 2], 6), return_counts=True)
        assert np.allclose(heights, np.add(traj["heights"], traj["target"][2]))
        assert list(per_ring) == [count // 2] * 2
        ring = c[np.isclose(c[:, 2], heights[0])]
        angles = np.sort(np.arctan2(ring[:, 1], ring[:, 0]))
        assert np.allclose(np.diff(angles), 2 * np.pi / (count // 2))


@pytest.mark.parametrize("name", SCALE + SMALL)
def test_no_texture_repeats(name):
    """Each photograph textures one surface at most and each noise texture has its own seed: a repeat would
    let a pipeline register a view in the wrong place, the renderer's fault."""
    entry, _, path = load_entry(name)
    mesh = build_mesh(entry, path.parent)
    used = np.unique(mesh.texture_ids)
    specs = [mesh.textures[k] for k in used]
    photos = [s.photo for s in specs if s.photo != "noise"]
    seeds = [s.seed for s in specs if s.photo == "noise"]
    assert len(photos) == len(set(photos)) and len(seeds) == len(set(seeds))
    assert len(specs) >= 6


@pytest.mark.parametrize("name", SMALL)
def test_small_variants_render_with_ground_truth_that_matches(name, tiny_scenes):
    scene = tiny_scenes(name)
    entry = load_entry(name)[0]
    info = json.loads((scene / "scene.json").read_text())
    count = entry["trajectory"]["count"]
    assert count <= 40 and entry["camera"]["width"] <= 640
    images = sorted((scene / "images").iterdir())
    assert info["complete"] and info["images"] == len(images) == count
    rec = load_reconstruction(scene / "gt" / "sparse")
    assert rec.num_images() == count and rec.num_points3D() > 100
    rel = []
    for image in rec.images.values():
        assert (scene / "images" / image.name).is_file()
        depth = np.load(scene / "gt" / "depth" / (image.name.rsplit(".", 1)[0] + ".npy"))
        assert depth.shape == (120, 160) and np.isfinite(depth).mean() > 0.5
        T = image.cam_from_world()
        pts = [p for p in image.points2D if p.has_point3D()]
        assert len(pts) >= 10
        uv = np.array([p.xy for p in pts])
        z = np.array([T * rec.points3D[p.point3D_id].xyz for p in pts])[:, 2]
        with np.errstate(invalid="ignore"):  # inf - inf where a pixel sees the sky
            value, smooth = bilinear(depth, uv[:, 0], uv[:, 1])
        rel.append(np.abs(value[smooth] - z[smooth]) / z[smooth])
    rel = np.concatenate(rel)
    assert len(rel) > 100 and np.median(rel) < 1e-4 and np.percentile(rel, 95) < 2e-3


def test_gps_exif_reads_back_within_its_noise(tiny_scenes):
    scene = tiny_scenes("aerial_survey_small")
    entry = load_entry("aerial_survey_small")[0]
    gps = json.loads((scene / "gt" / "gps.json").read_text())
    origin = np.array(entry["gps"]["origin"])
    rec = load_reconstruction(scene / "gt" / "sparse")
    errors = []
    for image in rec.images.values():
        fix = gps["images"][image.name]
        lla = read_gps(scene / "images" / image.name)
        assert lla is not None and image.name.endswith(".jpg")
        # EXIF holds seconds to 1e-4 (3 mm) and the altitude to the millimetre
        assert np.allclose(lla, fix["noisy_lla"], rtol=0, atol=[1e-7, 1e-7, 1e-3])
        centre = image.projection_center()
        assert np.allclose(fix["true_enu"], centre, atol=1e-5)
        errors.append(to_enu(np.array([lla]), origin)[0] - centre)
    errors = np.array(errors)
    horizontal = np.sqrt(np.mean(errors[:, :2] ** 2))
    vertical = np.sqrt(np.mean(errors[:, 2] ** 2))
    # 24 views: the RMS of 48 (24) Gaussian draws is within 30% (40%) of sigma at over 3 standard errors
    assert 0.7 * gps["sigma_horizontal_m"] < horizontal < 1.3 * gps["sigma_horizontal_m"]
    assert 0.6 * gps["sigma_vertical_m"] < vertical < 1.4 * gps["sigma_vertical_m"]
    assert gps["sigma_horizontal_m"] == 2.5 and gps["sigma_vertical_m"] == 5.0


def test_count_option_changes_the_number_of_views(tmp_path, capsys):
    toml = tiny_toml("dense_orbit_small", tmp_path)
    out = tmp_path / "scene"
    for count in (6, 8):
        assert main(["-q", "scene", "make", toml, "-o", str(out), "--count", str(count)]) == 0
        assert f"{count} images" in capsys.readouterr().out
        assert len(list((out / "images").iterdir())) == count
        assert load_reconstruction(out / "gt" / "sparse").num_images() == count
    assert main(["-q", "scene", "make", toml, "-o", str(out), "--count", "1"]) == 2
    assert "count = 1" in capsys.readouterr().err


def test_a_scene_made_with_a_count_resumes_after_ctrl_c(tmp_path, monkeypatch):
    """Ctrl-C at the 4th view of 7: the rerun with the same count renders the other 4 only, and the GPS EXIF
    of the views kept is the bytes an uninterrupted run writes."""
    toml = tiny_toml("aerial_survey_small", tmp_path)
    whole = make_scene(toml, tmp_path / "whole", count=7)
    renders, render = [], Renderer.render

    def cut(self, *args, **kwargs):
        renders.append(1)
        if len(renders) == 4:
            raise KeyboardInterrupt
        return render(self, *args, **kwargs)

    monkeypatch.setattr(Renderer, "render", cut)
    with pytest.raises(KeyboardInterrupt):
        make_scene(toml, tmp_path / "cut", count=7)
    renders[:] = [0] * 10  # no more Ctrl-C
    make_scene(toml, tmp_path / "cut", count=7)
    del renders[:10]
    assert len(renders) == 4
    for image in sorted((whole / "images").iterdir()):
        assert (tmp_path / "cut" / "images" / image.name).read_bytes() == image.read_bytes()


@pytest.mark.slow
@pytest.mark.parametrize("name", SMALL)
def test_mvrecon_reconstructs_each_small_variant(name, tmp_path, request):
    """aerial_survey_small at half its size (320x240): the run tests/sfm/test_georef.py georeferences."""
    if name == "aerial_survey_small":
        scene, run = request.getfixturevalue("aerial_survey_half"), request.getfixturevalue("aerial_survey_half_run")
    else:
        scene, run = make_scene(name, tmp_path / "scene"), tmp_path / "run"
        assert main(["-q", "reconstruct", str(scene / "images"), "-o", str(run)]) == 0
    models = sparse_models(run / "sparse")
    gt = load_ground_truth(scene / "gt" / "sparse")
    summary = accuracy_summary([poses(m) for m in models], gt)
    assert summary["registered"] == len(gt) and summary["components"] == 1, summary
    assert summary["auc@5"] >= 0.9, summary

"""The study machinery: grid, breaking points, and a tiny real study (both engines, 6 templeRing views, half size)."""

import html
import json
import shutil

import numpy as np
import pytest

from mvrecon.cli import main
from mvrecon.errors import InputError
from mvrecon.io.images import list_images
from mvrecon.io.record import Record
from mvrecon.study.degrade import Degradation, degrade_image
from mvrecon.study.grid import Cell, Grid, parse_levels
from mvrecon.study.plots import detailed_window
from mvrecon.study.study import breaking_points, read_csv
from tests.helpers import DATA as SHARED_DATA

DATA = SHARED_DATA / "middlebury_templeRing"
GT = DATA / "templeR_par.txt"


def test_grid_cells_share_the_clean_run_and_keep_the_given_order():
    grid = Grid({"noise": parse_levels("noise", "0,5,20"), "jpeg": parse_levels("jpeg", "95,50,10"),
                 "downscale": parse_levels("downscale", "1,2")})
    keys = [c.key for c in grid.cells()]
    assert keys == ["clean", "noise-5", "noise-20", "jpeg-95", "jpeg-50", "jpeg-10", "downscale-2"]
    assert Cell("jpeg", 50.0).degradation(Degradation(motion_angle=30)) == Degradation(jpeg_quality=50,
                                                                                        motion_angle=30)
    assert Cell(None, None).degradation(Degradation()).active() == []


@pytest.mark.parametrize("axis, text, message", [  # the errors of a level name its flag, as the user typed it
    ("jpeg", "95,150", "^--jpeg 150: JPEG quality must be 1..100"),
    ("noise", "0,a", "expected comma-separated numbers"), ("blur", "1,1", "a level is repeated"),
    ("downscale", "0.5", "^--downscale 0.5: downscale factor must be >= 1"),
    ("noise", "0,-5", "^--noise -5: noise sigma must be >= 0$")])
def test_impossible_levels_are_refused(axis, text, message):
    with pytest.raises(InputError, match=message):
        parse_levels(axis, text)


def test_empty_or_unknown_grid_is_refused():
    with pytest.raises(InputError, match="grid is empty"):
        Grid({})
    with pytest.raises(InputError, match="unknown degradation"):
        Grid({"fog": (1.0,)})


def rows(engine, axis, values):
    return [{"engine": engine, "degradation": axis, "level": float(lv), "registered_pct": reg, "auc@5": auc}
            for lv, reg, auc in values]


def test_breaking_point_is_the_first_level_below_half_of_clean():
    table = (rows("a", "noise", [(0, 100, 0.8), (5, 95, 0.7), (10, 60, 0.39), (20, 10, 0.0)])
             + rows("a", "blur", [(0, 100, 0.8), (1, 40, 0.7), (2, 0, 0.0)])
             + rows("b", "noise", [(0, 100, 0.8), (5, 100, 0.8), (10, 100, 0.41)])
             + rows("c", "noise", [(0, 0, 0.0), (5, 0, 0.0)]))
    verdict = breaking_points(table)
    assert verdict[("a", "noise")]["level"] == 10 and verdict[("a", "noise")]["metric"] == "AUC@5"
    assert verdict[("a", "blur")]["level"] == 1 and verdict[("a", "blur")]["metric"] == "registered %"
    assert verdict[("b", "noise")]["level"] is None and verdict[("b", "noise")]["tested"] == [5, 10]
    assert verdict[("c", "noise")]["metric"] == "clean run failed"


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    """Six consecutive templeRing views at 320x240 (made with the degrade module itself)."""
    if not DATA.is_dir():
        pytest.skip(f"templeRing data not found at {DATA}")
    out = tmp_path_factory.mktemp("temple6")
    for src in sorted((DATA / "images").glob("*.png"))[:6]:
        degrade_image(src, out / src.name, Degradation(downscale=2.0))
    return out


@pytest.fixture(scope="module")
def study_with_gt(tiny_scene, tmp_path_factory):
    study = tmp_path_factory.mktemp("study") / "s"
    code = main(["study", "-q", str(tiny_scene), "-o", str(study), "--engines", "mvrecon,colmap", "--gt", str(GT),
                 "--noise", "0,30", "--blur", "0,3", "--jobs", "2"])
    assert code == 0
    return study


@pytest.mark.parametrize("engine", ["mvrecon", "colmap"])
def test_study_measures_each_cell_against_ground_truth(study_with_gt, engine):
    table = read_csv(study_with_gt / "study.csv")
    assert [(r["engine"], r["degradation"], r["level"]) for r in table] == [
        (e, axis, level) for e in ("mvrecon", "colmap") for axis in ("noise", "blur") for level in (0.0, {
            "noise": 30.0, "blur": 3.0}[axis])]
    clean, noisy, _, blurred = [r for r in table if r["engine"] == engine]
    assert clean["registered_pct"] >= 80.0 and clean["images"] == 6 and clean["reference"] == "ground truth"
    assert clean["auc@5"] > 0.2 and clean["points"] > 100 and clean["mean_reprojection_error_px"] < 1.0
    assert blurred["keypoints_per_image"] < 0.5 * clean["keypoints_per_image"]  # blur removes SIFT features
    assert noisy["mean_inliers_per_pair"] < 0.7 * clean["mean_inliers_per_pair"]  # noise spoils descriptors
    assert noisy["auc@5"] < clean["auc@5"] and blurred["registered_pct"] < clean["registered_pct"]
    assert all(r["wall_s"] > 0 for r in table)


def test_study_report_is_self_contained_with_breaking_points(study_with_gt):
    page = (study_with_gt / "study.html").read_text()
    assert page.count("data:image/png;base64,") == 1 + 9  # the contact sheet and one plot per metric
    assert "src='http" not in page and "src=\"http" not in page
    assert "Breaking points" in page and "blur 3 (registered %" in page
    assert len(list((study_with_gt / "plots").glob("*.png"))) == 9
    assert (study_with_gt / "contact_sheet.png").stat().st_size > 10_000
    for engine in ("mvrecon", "colmap"):  # each engine ran as itself (COLMAP: the incremental mapper)
        assert json.loads((study_with_gt / "runs" / engine / "clean" / "report.json").read_text())["engine"] == engine
    made = Record(study_with_gt, "study.json").report("images/noise-30")
    assert made["degradation"]["noise_sigma"] == 30.0 and made["order"] == ["noise"]


def test_wider_grid_reuses_finished_cells_and_other_settings_are_refused(study_with_gt, tiny_scene, capsys):
    def finished_runs():
        return {str(p.parent.parent.relative_to(study_with_gt)): p.stat().st_mtime_ns
                for p in (study_with_gt / "runs").glob("*/*/.stages/runner.json")}

    before = finished_runs()
    assert sorted(before) == [f"runs/{e}/{c}" for e in ("colmap", "mvrecon") for c in ("blur-3", "clean", "noise-30")]
    code = main(["study", "-q", str(tiny_scene), "-o", str(study_with_gt), "--engines", "colmap", "--gt", str(GT),
                 "--noise", "0,30", "--blur", "0,3", "--jpeg", "5"])
    assert code == 0
    after = finished_runs()
    assert {k: after[k] for k in before} == before and set(after) - set(before) == {"runs/colmap/jpeg-5"}
    assert [r["level"] for r in read_csv(study_with_gt / "study.csv") if r["degradation"] == "jpeg"] == [0.0, 5.0]
    code = main(["study", "-q", str(tiny_scene), "-o", str(study_with_gt), "--engines", "colmap", "--gt", str(GT),
                 "--noise", "0,30", "--seed", "3"])
    err = capsys.readouterr().err
    assert code == 2 and "made with a different" in err and "seed" in err


def test_without_ground_truth_each_engine_is_measured_against_its_clean_model(tiny_scene, tmp_path):
    args = ["study", "-q", str(tiny_scene), "-o", str(tmp_path / "s"), "--engines", "colmap", "--noise", "0,8"]
    # a run is a process that imports pycolmap (0.3 s or more), so none finishes in 0.01 s
    assert main(args + ["--timeout", "0.01"]) == 0  # every run times out: kept as failed cells
    assert [r["error"] for r in read_csv(tmp_path / "s" / "study.csv")] == ["timed out after 0.01 s"] * 2
    assert "clean run failed" in (tmp_path / "s" / "study.html").read_text()
    assert main(args) == 0  # failures are cached results ...
    assert read_csv(tmp_path / "s" / "study.csv")[0]["error"] == "timed out after 0.01 s"
    assert main(args + ["--retry-failed"]) == 0  # ... until asked to retry
    clean, noisy = read_csv(tmp_path / "s" / "study.csv")
    assert clean["error"] == "" and noisy["error"] == ""
    assert clean["reference"] == "colmap on the clean images"
    assert clean["auc@1"] == pytest.approx(1.0)  # the clean model against itself
    assert noisy["registered_pct"] > 50.0
    # the noisy model is measured, not compared with itself: worse than the clean one, yet close to it
    # (measured AUC@1 0.41, AUC@5 0.86)
    assert noisy["auc@1"] < clean["auc@1"] - 0.05 and 0.5 < noisy["auc@5"] < 1.0


def test_study_input_errors_are_one_line(tiny_scene, tmp_path, capsys):
    assert main(["study", "-q", str(tiny_scene), "-o", str(tmp_path / "s"), "--engines", "colmap"]) == 2
    assert "grid is empty" in capsys.readouterr().err
    assert main(["study", "-q", str(tiny_scene), "-o", str(tmp_path / "s"), "--engines", "nope",
                 "--noise", "5"]) == 2
    assert "engine 'nope'" in capsys.readouterr().err
    assert main(["study", "-q", str(tiny_scene), "-o", str(tmp_path / "s"), "--engines", "colmap",
                 "--noise", "5", "--gt", str(DATA / "templeR_ang.txt")]) == 2
    assert "not a ground-truth format" in capsys.readouterr().err
    # no engine, an output inside the image folder (its copies would count as images), one image only
    assert main(["study", "-q", str(tiny_scene), "-o", str(tmp_path / "s"), "--engines", "",
                 "--noise", "5"]) == 2
    assert "--engines: no engine given" in capsys.readouterr().err
    assert main(["study", "-q", str(tiny_scene), "-o", str(tiny_scene / "s"), "--noise", "5"]) == 2
    assert "inside the image folder" in capsys.readouterr().err
    one = tmp_path / "one"
    one.mkdir()
    first = sorted(p for p in tiny_scene.iterdir() if p.suffix == ".png")[0]
    (one / first.name).write_bytes(first.read_bytes())
    assert main(["study", "-q", str(one), "-o", str(tmp_path / "s1"), "--noise", "5"]) == 2
    assert "only 1 usable image(s), need at least 2" in capsys.readouterr().err
    assert main(["compare", "-q", str(one), "-o", str(tmp_path / "c1")]) == 2
    assert "only 1 usable image(s), need at least 2" in capsys.readouterr().err
    assert not (tmp_path / "c1").exists() and not (tmp_path / "s1").exists()  # no engine ran


def copy_images(tiny_scene, folder, layout):
    """`layout`: relative name -> the index of the tiny scene's image to copy there."""
    sources = sorted(p for p in tiny_scene.iterdir() if p.suffix == ".png")
    for name, k in layout.items():
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_bytes(sources[k].read_bytes())
    return folder


def run_images(study, engine, cell):
    """The images an engine's run took (its report also names the files it skipped)."""
    report = json.loads((study / "runs" / engine / cell / "report.json").read_text())
    return sorted(n for n, image in report["images"].items() if image["status"] != "skipped")


def test_study_uses_the_images_reconstruct_takes_in_every_cell(tiny_scene, tmp_path):
    """Images at the top and in a sub-folder, with unreadable and non-image files: every cell is made from the
    same six images (registered % was 200: the clean run took the sub-folder's images, the noisy cells and the
    denominator did not; unreadable files counted as images gave 75 % where compare says 100)."""
    images = copy_images(tiny_scene, tmp_path / "in", {"0.png": 0, "1.png": 1, "2.png": 2, "sub/3.png": 3,
                                                       "sub/4.png": 4, "sub/deeper/5.png": 5})
    (images / "sub" / "junk.png").write_text("junk")
    whole = (images / "1.png").read_bytes()
    (images / "cut.png").write_bytes(whole[: len(whole) // 2])
    (images / "notes.txt").write_text("not an image")
    names, skipped = list_images(images)
    assert len(names) == 6 and sorted(skipped) == ["cut.png", "notes.txt", "sub/junk.png"]
    study = tmp_path / "s"
    assert main(["study", "-q", str(images), "-o", str(study), "--engines", "mvrecon", "--noise", "0,3",
                 "--jobs", "1"]) == 0
    table = read_csv(study / "study.csv")
    assert [(r["level"], r["registered"], r["images"], r["registered_pct"]) for r in table] == [
        (0.0, 6.0, 6.0, 100.0), (3.0, 6.0, 6.0, 100.0)]
    assert run_images(study, "mvrecon", "clean") == run_images(study, "mvrecon", "noise-3") == sorted(names)
    assert list_images(study / "images" / "noise-3")[0] == names  # sub-folders kept
    page = (study / "study.html").read_text()
    assert "3 file(s) in the image folder left out" in page
    for name, why in skipped.items():  # each file left out, with list_images' reason
        assert f"<code>{name}</code>: {html.escape(why)}" in page
    assert "(6 images)" in page


def test_study_of_images_only_in_sub_folders_and_cells_made_from_other_images(tiny_scene, tmp_path, capsys):
    images = copy_images(tiny_scene, tmp_path / "in", {f"{'ab'[k // 3]}/{k}.png": k for k in range(6)})
    study = tmp_path / "s"
    args = ["study", "-q", str(images), "-o", str(study), "--engines", "mvrecon", "--noise", "0,3",
            "--timeout", "0.01"]  # the runs time out (failed cells): only the image sets are looked at here
    assert main(args) == 0  # was refused: "no JPEG, PNG or TIFF images here"
    assert [r["images"] for r in read_csv(study / "study.csv")] == [6.0, 6.0]
    assert list_images(study / "images" / "noise-3")[0] == list_images(images)[0] == [
        "a/0.png", "a/1.png", "a/2.png", "b/3.png", "b/4.png", "b/5.png"]
    # a cell made from other images is not mixed with the images the folder holds now
    copy_images(tiny_scene, images, {"b/6.png": 0})
    assert main(args) == 2
    assert "images/noise-3: made from other images than" in capsys.readouterr().err
    (images / "b" / "6.png").unlink()
    assert main(args) == 0
    # a finished cell whose images were partly deleted is made again; a cell recorded under other names is refused
    shutil.rmtree(study / "images" / "noise-3" / "b")
    assert main(args) == 0
    assert list_images(study / "images" / "noise-3")[0] == list_images(images)[0]
    record = Record(study, "study.json")
    made = record.report("images/noise-3")
    record.put("images/noise-3", "another key", {**made, "images": made["images"][:3]})
    assert main(args) == 2
    assert "(without b/3.png, b/4.png, b/5.png)" in capsys.readouterr().err


def test_study_folder_of_an_older_version_is_refused(tiny_scene, tmp_path, capsys):
    study = tmp_path / "s"
    (study / "images").mkdir(parents=True)
    (study / "study.json").write_text(json.dumps({"seed": 0}))
    (study / "images" / "noise-3.json").write_text(json.dumps({"seed": 0, "images": ["0.png"]}))
    assert main(["study", "-q", str(tiny_scene), "-o", str(study), "--engines", "mvrecon", "--noise", "0,3"]) == 2
    err = capsys.readouterr().err
    assert f"{study / 'study.json'}: a study of an older mvrecon version" in err and "delete this one" in err
    assert not (study / ".stages").exists() and not (study / "images" / "noise-3").exists()


def test_detailed_window_finds_the_textured_patch():
    img = np.full((200, 300, 3), 128, np.uint8)
    rng = np.random.default_rng(0)
    img[120:160, 200:240] = rng.integers(0, 256, (40, 40, 3), dtype=np.uint8)  # the only detail: 40 x 40 at (200, 120)
    x, y = detailed_window(img, 40)
    assert abs(x - 200) <= 2 and abs(y - 120) <= 2

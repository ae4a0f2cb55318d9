"""`mvrecon compare`: ground-truth loaders on the real data sets, the COLMAP runners on a small synthetic scene,
comparisons of existing models against ground truth (a perturbed camera is found, winners are right), the report
files, and the command's errors."""

import csv
import json
import math
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from mvrecon.cli import main
from mvrecon.config import config_hash
from mvrecon.errors import InputError
from mvrecon.eval import ground_truth as G
from mvrecon.eval.compare import CompareConfig, Comparison, compare_images, compare_models, evaluate, summary_rows
from mvrecon.eval.metrics import accuracy_summary, camera_center
from mvrecon.eval.report import format_value, write_report
from mvrecon.eval.runners import (
    RunOptions,
    _wait_measuring_memory,
    code_environment,
    load_run,
    refuse_other_settings,
    run_colmap,
    run_colmap_on_database,
    run_meta,
    run_mvrecon_map,
)
from mvrecon.io.record import Record
from tests.helpers import DATA, ROOT, synthetic_scene

OPTS = RunOptions(camera_mode="single")


def data_set(name) -> Path:
    path = DATA / name
    if not path.is_dir():
        pytest.skip(f"data set {name} not found at {path}")
    return path


@pytest.fixture(scope="module")
def runs(colmap_runs):
    return colmap_runs


# --- ground truth -------------------------------------------------------------------------------------------

def assert_rotations(gt):
    for R, t in gt.values():
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-5)
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-5)


def test_middlebury_par_ring():
    gt = G.load_ground_truth(data_set("middlebury_templeRing") / "templeR_par.txt")
    assert len(gt) == 47 and gt.kind == "middlebury"
    np.testing.assert_allclose(gt.intrinsics["templeR0013.png"],
                               [[1520.4, 0, 302.32], [0, 1525.9, 246.87], [0, 0, 1]])
    assert_rotations(gt)
    centres = np.array([camera_center(*p) for p in gt.values()])
    middle = centres.mean(axis=0)
    normal = np.linalg.svd(centres - middle)[2][2]
    assert np.abs((centres - middle) @ normal).max() < 0.01  # the 47 centres lie in one plane...
    radius = np.linalg.norm(centres - middle, axis=1)
    assert radius.std() / radius.mean() < 0.05  # ...on a circle around the temple
    for R, t in gt.values():  # and every camera looks at the ring's centre
        assert (R @ middle + t)[2] > 0.5 * radius.mean()
    sub = gt.subset(["templeR0013.png", "nope.png"])
    assert list(sub) == ["templeR0013.png"] and list(sub.intrinsics) == ["templeR0013.png"]


def test_find_ground_truth_of_every_set_that_has_one():
    expected = {"middlebury_templeSparseRing": "templeSR_par.txt", "strecha_fountain_P11": "gt_dense_cameras",
                "gtsfm_lund_door": "colmap_ground_truth", "imc_reichstag": "calibration", "opensfm_lund": None}
    for name, found in expected.items():
        path = G.find_ground_truth(data_set(name))
        assert (path.name if path else None) == found, name


def test_strecha_cameras_follow_P_equals_K_RT_minus_RT_C():
    folder = data_set("strecha_herzjesu_P8") / "gt_dense_cameras"
    gt = G.load_ground_truth(folder)
    assert len(gt) == 8 and sorted(gt)[0] == "0000.jpg"
    assert_rotations(gt)
    raw = np.array((folder / "0003.jpg.camera").read_text().split(), dtype=float)
    np.testing.assert_allclose(camera_center(*gt["0003.jpg"]), raw[21:24], atol=1e-9)
    np.testing.assert_allclose(gt["0003.jpg"][0], raw[12:21].reshape(3, 3).T, atol=1e-5)
    # the optical axes meet in front of every camera (the facade they all look at)
    A, b = np.zeros((3, 3)), np.zeros(3)
    for R, t in gt.values():
        d, C = R[2], camera_center(R, t)
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ C
    X = np.linalg.solve(A, b)
    assert all((R @ X + t)[2] > 1.0 for R, t in gt.values())


def test_colmap_reference_model_and_imc_calibration():
    door = G.load_ground_truth(data_set("gtsfm_lund_door") / "colmap_ground_truth")
    assert len(door) == 12 and door.kind == "colmap" and door.points.shape[1] == 3 and len(door.points) == 11384
    assert door.intrinsics["DSC_0001.JPG"][0, 0] == pytest.approx(2435.38)
    imc = G.load_ground_truth(data_set("imc_reichstag") / "calibration")
    assert len(imc) == 10 and all((DATA / "imc_reichstag" / "images" / n).exists() for n in imc)
    assert_rotations(imc)
    raw = G.read_small_hdf5(DATA / "imc_reichstag" / "calibration" / "calibration_05461164_9050854768.h5")
    assert sorted(raw) == ["K", "R", "T", "q"]
    assert raw["K"][0, 0] == pytest.approx(799.419, abs=1e-3) and raw["K"][0, 2] == 524.0
    np.testing.assert_allclose(imc["05461164_9050854768.jpg"][1], raw["T"])


def test_bad_ground_truth_is_named(tmp_path):
    with pytest.raises(InputError, match="nothing.txt: ground truth not found"):
        G.load_ground_truth(tmp_path / "nothing.txt")
    with pytest.raises(InputError, match="not a ground-truth format"):
        G.load_ground_truth(tmp_path)
    (tmp_path / "x_par.txt").write_text("2\na.png 1 2 3\n")
    with pytest.raises(InputError, match="x_par.txt: not a Middlebury par file"):
        G.load_ground_truth(tmp_path / "x_par.txt")
    (tmp_path / "calibration_a.h5").write_bytes(b"not hdf5")
    with pytest.raises(InputError, match="calibration_a.h5: cannot read this HDF5 file"):
        G.read_small_hdf5(tmp_path / "calibration_a.h5")


# --- runners ------------------------------------------------------------------------------------------------

def test_colmap_runner_report_and_cache(runs):
    images, gt, colmap, same = runs
    assert colmap.error is None and colmap.engine == "colmap"
    assert [m.num_reg_images() for m in colmap.models] == [8]
    report = json.loads((colmap.out_dir / "report.json").read_text())
    assert set(report) >= {"engine", "images", "models", "stages", "total", "counts"}
    assert set(report["stages"]) == {"features", "matching", "mapping"}
    assert all(v["status"] == "registered" and v["model"] == 0 for v in report["images"].values())
    assert report["counts"]["verified_pairs"] >= 20 and report["counts"]["keypoints_per_image"] > 100
    assert report["models"][0]["registered"] == 8 and report["models"][0]["mean_reprojection_error_px"] < 1.5
    assert (colmap.out_dir / "points.ply").stat().st_size > 1000
    # memory: the process tree's peak, sampled by the runner, at least what COLMAP's process saw itself
    assert colmap.peak_mem_mb >= 0.9 * report["total"]["peak_mem_mb"] > 50
    assert pycolmap.Reconstruction(str(colmap.out_dir / "sparse" / "0")).num_reg_images() == 8
    # same matches: the database's keypoints are reused, so the mapper sees the same correspondences
    assert same.report["counts"] == report["counts"] and set(same.report["stages"]) == {"mapping"}
    # a finished run is read back, not rerun; other options in the same folder are refused
    again = run_colmap(images, colmap.out_dir, OPTS)
    assert again.wall_s == colmap.wall_s and again.report == colmap.report
    with pytest.raises(InputError, match=r"holds a run of colmap made with other settings "
                                         r"\(options.camera_mode: single -> per-image\)"):
        run_colmap(images, colmap.out_dir, RunOptions(camera_mode="per-image"))


def test_other_mvrecon_args_reuse_colmaps_run_and_refuse_mvrecons(runs, tmp_path):
    import dataclasses

    images, gt, colmap, same = runs
    upright = dataclasses.replace(OPTS, mvrecon_args=("--upright",))
    # COLMAP never sees mvrecon's flags: its finished run is read back, not refused (refused before)
    again = run_colmap(images, colmap.out_dir, upright)
    assert again.error is None and again.wall_s == colmap.wall_s and again.report == colmap.report
    # a run recorded with mvrecon's flags among its options (as every run was before) is reused too
    old = tmp_path / "old-colmap"
    shutil.copytree(colmap.out_dir, old)
    record = Record(old, "runner.json")
    identity = record.config("run")
    identity["options"]["mvrecon_args"] = ["--max-features", "2000"]
    record.put("run", config_hash(identity), record.report("run"), record.seconds("run"), config=identity)
    assert run_colmap(images, old, upright).wall_s == colmap.wall_s
    # what COLMAP does see still counts; the run on mvrecon's database depends on mvrecon's flags
    with pytest.raises(InputError, match=r"options.seed: 0 -> 1"):
        run_colmap(images, old, dataclasses.replace(upright, seed=1))
    with pytest.raises(InputError, match=r"holds a run of colmap-same-matches made with other settings "
                                         r"\(options.mvrecon_args: \[\] -> \['--upright'\]\)"):
        run_colmap_on_database(colmap.out_dir / "database.db", same.out_dir, images, upright)


def test_a_run_on_a_database_that_changed_since_is_redone(runs, tmp_path):
    """The same-matches run is named by its database's path: a database made again at that path (mvrecon's run
    redone) must not be answered with the model of the old one."""
    import sqlite3

    images, _, colmap, _ = runs
    db, out = tmp_path / "database.db", tmp_path / "same"
    shutil.copyfile(colmap.out_dir / "database.db", db)
    first = run_colmap_on_database(db, out, images, OPTS)
    assert run_colmap_on_database(db, out, images, OPTS).wall_s == first.wall_s  # unchanged: read back
    with sqlite3.connect(db) as con:  # the database made again, with one verified pair fewer
        pair = con.execute("SELECT pair_id FROM two_view_geometries WHERE rows > 0 LIMIT 1").fetchone()[0]
        con.execute("DELETE FROM two_view_geometries WHERE pair_id = ?", (pair,))
    con.close()
    again = run_colmap_on_database(db, out, images, OPTS)
    assert again.error is None and again.wall_s != first.wall_s  # mapped again, not read back (it was before)
    assert again.report["counts"]["verified_pairs"] == first.report["counts"]["verified_pairs"] - 1


def test_mvrecons_mapper_alone_on_a_database(runs, tmp_path):
    """run_mvrecon_map: mvrecon's mapper on COLMAP's database of the synthetic scene registers all 8 images at
    the ground truth's poses, and a finished run is read back, not rerun."""
    images, gt, colmap, _ = runs
    ws = tmp_path / "ws"
    ws.mkdir()
    shutil.copyfile(colmap.out_dir / "database.db", ws / "database.db")
    root = ROOT
    run = run_mvrecon_map(ws, OPTS, image_dir=images, code=root)
    assert run.error is None and run.engine == "mvrecon-map"
    assert [m.num_reg_images() for m in run.models] == [8] and set(run.report["stages"]) == {"mapping"}
    assert accuracy_summary(run.poses, G.load_ground_truth(gt))["auc@5"] > 0.95
    assert run_meta(ws)["code"] == str(root)
    assert run_mvrecon_map(ws, OPTS, image_dir=images, code=root).wall_s == run.wall_s


def test_a_run_folder_records_its_run_and_an_older_record_is_refused(tmp_path):
    """A run's record says what it was made with; a folder with the runner.json of an older mvrecon is refused
    before anything runs (what it was made with is not read any more), not rerun over."""
    images = tmp_path / "images"
    images.mkdir()
    out = tmp_path / "run"
    identity = {"engine": "colmap", "source": str(images.resolve()), "options": OPTS.identity("colmap")}
    Record(out, "runner.json").put("run", config_hash(identity), {"finished": True, "wall_s": 2.5}, 2.5,
                                   config=identity)
    assert refuse_other_settings("colmap", images, out, OPTS) == {**identity, "finished": True, "wall_s": 2.5}
    with pytest.raises(InputError, match=r"other settings \(options.seed: 0 -> 3\)"):
        refuse_other_settings("colmap", images, out, RunOptions(camera_mode="single", seed=3))
    old = tmp_path / "old"
    old.mkdir()
    (old / "runner.json").write_text(json.dumps({**identity, "finished": True}))
    with pytest.raises(InputError, match="older mvrecon version"):
        run_colmap(images, old, OPTS)
    assert run_meta(old) == {} and sorted(p.name for p in old.iterdir()) == ["runner.json"]


def test_code_environment_imports_mvrecon_from_the_tree_given(tmp_path, monkeypatch):
    """A run of another source tree imports that tree's mvrecon, even started from a checkout of its own (the
    working directory comes first on the path of `python -m` and `-c`)."""
    tree = tmp_path / "other"
    (tree / "mvrecon").mkdir(parents=True)
    (tree / "mvrecon" / "__init__.py").write_text("TREE = 'other'\n")
    monkeypatch.chdir(ROOT)
    env, cwd = code_environment(tree)
    out = subprocess.run([sys.executable, "-c", "import mvrecon; print(getattr(mvrecon, 'TREE', 'this one'))"],
                         env=env, cwd=cwd, capture_output=True, text=True)
    assert out.stdout.strip() == "other"


def test_compare_again_with_other_mvrecon_args(tmp_path, capsys):
    """The runs time out at once (no time spent on them); a timed-out run is a finished run, reused as such."""
    images, _ = synthetic_scene(tmp_path / "scene")
    out = tmp_path / "r"
    args = ["-q", "compare", str(images), "-o", str(out), "--timeout", "0.01"]
    assert main(args + ["--no-same-matches"]) == 1
    capsys.readouterr()
    colmap_meta = (out / "runs" / "colmap" / ".stages" / "runner.json").read_text()
    # mvrecon's run was made with other flags: refused, as any run with other settings
    assert main(args + ["--no-same-matches", "--mvrecon-args", "--upright"]) == 2
    err = capsys.readouterr().err
    assert f"{out / 'runs' / 'mvrecon'}: holds a run of mvrecon made with other settings" in err, err
    shutil.rmtree(out / "runs" / "mvrecon")
    assert main(args + ["--no-same-matches", "--mvrecon-args", "--upright"]) == 1  # 2 before: colmap refused
    assert "holds a run" not in capsys.readouterr().err
    assert (out / "runs" / "colmap" / ".stages" / "runner.json").read_text() == colmap_meta  # reused, not rerun
    meta = run_meta(out / "runs" / "mvrecon")
    assert meta["command"][-1] == "--upright"
    # every run folder is checked before any engine starts: a stale same-matches run stops mvrecon's rerun
    same = out / "runs" / "colmap-same-matches"
    identity = {"engine": "colmap-same-matches", "source": str((out / "runs" / "mvrecon" / "database.db").resolve()),
                "options": OPTS.to_dict() | {"camera_mode": "auto"}}
    Record(same, "runner.json").put("run", config_hash(identity), {"finished": True}, config=identity)
    shutil.rmtree(out / "runs" / "mvrecon")
    assert main(args + ["--mvrecon-args", "--max-features 2000"]) == 2
    err = capsys.readouterr().err
    assert f"{same}: holds a run of colmap-same-matches made with other settings (options.mvrecon_args: [] -> " \
           f"['--max-features', '2000'])" in err and len(err.splitlines()) == 1, err
    assert not (out / "runs" / "mvrecon").exists()


def test_a_runs_end_is_timed_when_it_happens(tmp_path):
    """The wall time of a run ends when the process ends, not at the memory sampler's next look: a thread
    blocked in waitpid takes the time. With the sampler looking every 5 s, runs that end 0.1-0.2 s in must be
    timed within 0.5 s of the child's last statement. The bound is loose on purpose, so that a loaded machine
    cannot fail it: it checks where the end is taken. How precisely (a few ms) is a benchmark's
    concern, not a test's."""
    for k, seconds in enumerate((0.11, 0.19)):
        stamp = tmp_path / f"end{k}"
        code = f"import time; time.sleep({seconds}); open({str(stamp)!r}, 'w').write(repr(time.perf_counter()))"
        started = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-S", "-c", code])
        exit_code, _, end = _wait_measuring_memory(proc, timeout=30, interval=5.0)
        returned = time.perf_counter()
        late = end - float(stamp.read_text())  # both clocks are the system's monotonic clock
        assert exit_code == 0 and end <= returned
        assert 0 < late < 0.5, late  # after the child's last statement, and not at the sampler's next look
        assert returned - started < 4.0  # the sampler's 5 s sleep was cut short by the end


def test_failed_run_is_reported_not_raised(tmp_path):
    (tmp_path / "imgs").mkdir()
    (tmp_path / "imgs" / "a.png").write_bytes(b"no image")
    result = run_colmap(tmp_path / "imgs", tmp_path / "out", OPTS, timeout=120)
    assert result.models == [] and (result.error or result.report["models"] == [])


def test_failed_runs_are_kept_until_retried_and_a_comparison_of_nothing_fails(runs, tmp_path, capsys):
    images, out = runs[0], tmp_path / "r"
    args = ["-q", "compare", str(images), "-o", str(out), "--no-same-matches"]
    # no engine registered anything: not a success
    assert main(args + ["--timeout", "0.01"]) == 1
    assert "no engine registered any image" in capsys.readouterr().err
    assert main(args) == 1  # the timed-out runs are results ...
    assert main(args + ["--retry-failed"]) == 0  # ... until asked to run them again
    assert "retrying colmap (it failed before)" in capsys.readouterr().out
    m = json.loads((out / "metrics.json").read_text())
    assert {e: v["summary"]["registered"] for e, v in m["engines"].items()} == {"mvrecon": 8, "colmap": 8}


# --- comparisons --------------------------------------------------------------------------------------------

def perturbed_copy(model_dir: Path, out: Path, shift) -> str:
    """The model with its first image moved by `shift` (world units); returns that image's name."""
    rec = pycolmap.Reconstruction(str(model_dir))
    image = rec.image(sorted(rec.reg_image_ids())[0])
    frame = rec.frame(image.frame_id)
    T = frame.rig_from_world
    frame.rig_from_world = pycolmap.Rigid3d(T.rotation, np.asarray(T.translation) + np.asarray(shift, float))
    out.mkdir(parents=True)
    rec.write(str(out))
    return image.name


def test_compare_models_against_ground_truth(runs, tmp_path):
    images, gt, colmap, same = runs
    moved = perturbed_copy(colmap.out_dir / "sparse" / "0", tmp_path / "moved", [3.0, 0, 0])
    cmp = compare_models([colmap.out_dir, tmp_path / "moved"], gt=gt, labels=["colmap", "moved"])
    m = cmp.metrics
    good, bad = m["engines"]["colmap"], m["engines"]["moved"]
    assert m["reference"]["name"] == "ground truth" and m["reference"]["images"] == 8
    assert good["summary"]["registered"] == 8 and good["summary"]["components"] == 1
    assert good["summary"]["auc@5"] > 0.9 and good["summary"]["median_rotation_error_deg"] < 0.5
    assert good["summary"]["median_center_error_pct"] < 1.0
    # our Sim3 and pycolmap's put the cameras in the same places
    assert good["summary"]["alignment_pycolmap_disagreement_pct"] < 1e-3
    # the moved camera is an alignment outlier with a large centre error; the others stay as good
    assert bad["summary"]["alignment_inliers"] == 7
    assert bad["per_image"][moved]["alignment_inlier"] is False
    assert bad["per_image"][moved]["center_error_pct"] > 20 * good["per_image"][moved]["center_error_pct"]
    assert bad["summary"]["auc@5"] < good["summary"]["auc@5"]
    # and the one image at a wrong pose: its directions to the other cameras are off
    assert good["summary"]["misplaced"] == 0 and bad["summary"]["misplaced"] == 1
    assert bad["per_image"][moved].get("misplaced") is True and "misplaced" not in good["per_image"][moved]
    rows = {r["metric"]: r for r in m["rows"]}
    assert rows["misplaced"]["winners"] == ["colmap"]
    assert rows["auc@5"]["winners"] == ["colmap"] and rows["registered"]["winners"] == []  # 8 = 8: a tie
    # every number in the table is in metrics.json and metrics.csv
    page = write_report(cmp, tmp_path / "report")
    saved = json.loads((tmp_path / "report" / "metrics.json").read_text())
    assert saved["rows"] == m["rows"]
    with open(tmp_path / "report" / "metrics.csv") as f:
        lines = list(csv.DictReader(f))
    summary = {(r["engine"], r["metric"]): r["value"] for r in lines if r["section"] == "summary"}
    for row in m["rows"]:
        for engine, value in row["values"].items():
            text = summary[(engine, row["metric"])]
            assert (text == "" and value is None) or math.isclose(float(text), value, rel_tol=1e-12)
    html = page.read_text()
    assert not re.search(r"<(script|link|img|iframe)[^>]+(src|href)=[\"']?(https?:)?//", html)  # nothing fetched
    assert "data:image/png;base64," in html and "plotly.js" in html
    assert f"<span class='v'>{format_value('auc@5', good['summary']['auc@5'])}</span>" in html


def test_without_ground_truth_the_last_model_is_the_reference(runs):
    images, gt, colmap, same = runs
    m = compare_models([same.out_dir, colmap.out_dir]).metrics
    assert m["reference"]["name"] == "colmap"
    assert m["engines"]["colmap"]["role"] == "reference"
    assert m["engines"]["colmap"]["summary"]["auc@5"] is None
    # COLMAP's mapper on the same database gives nearly the same model (multithreaded BA: not bit-identical)
    other = m["engines"]["colmap-same-matches"]["summary"]
    assert other["registered"] == 8 and other["auc@5"] > 0.9 and other["max_rotation_error_deg"] < 0.5


def ring_poses(n: int, noise_deg: float = 0.0, seed: int = 0) -> dict:
    """n cameras on a ring looking at its centre (name -> (R, t)), rotated by up to `noise_deg` at random."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    out = {}
    for k in range(n):
        a = 2 * np.pi * k / n
        centre = np.array([4 * np.cos(a), 4 * np.sin(a), 0.3 * k / n])
        z = -centre / np.linalg.norm(centre)
        x = np.cross([0.0, 0.0, 1.0], z)
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])
        R = Rotation.from_rotvec(np.radians(noise_deg) * rng.uniform(-1, 1, 3)).as_matrix() @ R
        out[f"{k:03d}.png"] = (R, -R @ centre)
    return out


def run_of(engine: str, *models: dict, error: str | None = None):
    """A RunResult of camera-only models made of poses (largest first), or of a run that failed with `error`."""
    from mvrecon.eval.models import reconstruction_from_poses
    from mvrecon.eval.runners import RunResult

    return RunResult(engine=engine, out_dir=Path(engine), models=[reconstruction_from_poses(m) for m in models],
                     error=error)


def write_model(poses: dict, folder: Path) -> None:
    from mvrecon.eval.models import reconstruction_from_poses

    folder.mkdir(parents=True)
    reconstruction_from_poses(poses).write(str(folder))


def test_a_reference_that_holds_fewer_images_is_not_trusted():
    # opensfm_lund's case: COLMAP registered 2 of 29 images, mvrecon 29, and mvrecon read AUC 0.000
    gt = ring_poses(12)
    names = sorted(gt)
    colmap = run_of("colmap", {n: gt[n] for n in names[:2]})
    m = evaluate([run_of("mvrecon", ring_poses(12, 0.05)), colmap], names).metrics
    assert m["reference"]["name"] == "mvrecon" and m["reference"]["images"] == 12
    note = m["reference"]["note"]
    assert "colmap's largest model holds 2 of the 12 images, fewer than mvrecon's 12" in note
    assert "not a trustworthy reference" in note
    assert m["engines"]["mvrecon"]["role"] == "reference" and m["engines"]["mvrecon"]["summary"]["auc@5"] is None
    colmap = m["engines"]["colmap"]["summary"]
    assert m["engines"]["colmap"]["role"] == "engine" and colmap["registered"] == 2
    assert 0 < colmap["auc@5"] < 0.05  # its one pair of 66 is right: scored, and low, as it should be
    # a failed reference run: the same
    failed = run_of("colmap", error="exit code 1: boom")
    m = evaluate([run_of("mvrecon", ring_poses(12, 0.05)), failed], names).metrics
    assert m["reference"]["name"] == "mvrecon" and "colmap's run failed (exit code 1: boom)" in m["reference"]["note"]
    # an equal model stays the reference, without a note
    m = evaluate([run_of("mvrecon", ring_poses(12, 0.05)), run_of("colmap", gt)], names).metrics
    assert m["reference"] == {"name": "colmap", "source": "colmap", "images": 12, "note": ""}
    assert m["engines"]["mvrecon"]["summary"]["auc@5"] > 0.9


def test_no_model_with_half_the_images_means_no_reference_not_a_zero(tmp_path):
    gt = ring_poses(12)
    names = sorted(gt)
    runs = [run_of("mvrecon", {n: gt[n] for n in names[:5]}, {n: gt[n] for n in names[5:9]}),
            run_of("colmap", {n: gt[n] for n in names[:4]})]
    m = evaluate(runs, names).metrics
    assert m["reference"]["name"] is None and m["reference"]["images"] == 0
    assert m["reference"]["note"].startswith("no trustworthy reference: no ground truth was given, colmap's largest "
                                             "model holds 4 of the 12 images, fewer than mvrecon's 5")
    for e in m["engines"].values():
        assert e["role"] == "engine" and all(e["summary"][k] is None for k in ("auc@1", "auc@5"))
    page = write_report(Comparison(metrics=m, geometry={}), tmp_path / "report").read_text()
    assert page.index("id='reference-note'") < page.index("<div class=\"meta\">")  # at the top
    assert "none that can be trusted" in page


def test_registered_images_count_the_largest_model_and_show_the_others(tmp_path, capsys):
    # templeSparseRing's case: mvrecon's models of 13 and 3 images read "16 (100%)" beside COLMAP's 13
    gt = ring_poses(16)
    names = sorted(gt)
    for k, part in enumerate((names[:13], names[13:])):
        write_model({n: gt[n] for n in part}, tmp_path / "mv" / "sparse" / str(k))
    write_model({n: gt[n] for n in names[:13]}, tmp_path / "cm")
    out = tmp_path / "report"
    assert main(["compare", "--models", str(tmp_path / "mv"), str(tmp_path / "cm"), "--labels", "mvrecon", "colmap",
                 "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert re.search(r"registered images\s+13 \+ 3\s+13\n", printed), printed
    m = json.loads((out / "metrics.json").read_text())
    mv = m["engines"]["mvrecon"]["summary"]
    assert (mv["registered"], mv["registered_other_models"], mv["registered_pct"]) == (13, [3], 81.25)
    assert m["reference"]["name"] == "colmap" and m["reference"]["note"] == ""  # 13 = 13: still trusted
    page = (out / "index.html").read_text()
    assert ("data-metric='registered'><span class='v'>13</span><span class='others' title='images in the other "
            "models'> + 3</span>") in page


def test_unregistered_images_and_failed_runs_carry_reasons(runs, tmp_path):
    images, gt, colmap, same = runs
    rec = pycolmap.Reconstruction(str(colmap.out_dir / "sparse" / "0"))
    dropped = rec.image(sorted(rec.reg_image_ids())[-1]).name
    rec.deregister_frame(rec.image(sorted(rec.reg_image_ids())[-1]).frame_id)
    (tmp_path / "partial").mkdir()
    rec.write(str(tmp_path / "partial"))
    m = compare_models([tmp_path / "partial", colmap.out_dir], gt=gt, labels=["partial", "full"]).metrics
    e = m["engines"]["partial"]
    assert e["summary"]["registered"] == 7 and e["per_image"][dropped]["status"] == "unregistered"
    assert e["per_image"][dropped]["reason"] == "not in any model"
    n = 8 * 7 // 2
    assert sum(err == 180.0 for err in e["relative_pose_errors_deg"]) == 7  # every pair with the dropped image
    assert len(e["relative_pose_errors_deg"]) == n


def test_winner_rules():
    def engine(role, **summary):
        return {"role": role, "summary": summary}

    engines = {"a": engine("engine", points=10, wall_s=5.0, registered=4),
               "b": engine("engine", points=12, wall_s=7.0, registered=4),
               "c": engine("diagnostic", points=99, wall_s=1.0, registered=9)}
    rows = {r["metric"]: r for r in summary_rows(engines)}
    assert rows["points"]["winners"] == ["b"] and rows["wall_s"]["winners"] == ["a"]
    assert rows["registered"]["winners"] == []  # a tie among competitors; the diagnostic run does not compete
    assert rows["keypoints_per_image"]["winners"] == []
    # images in a model without points are no reconstruction: COLMAP's 3 of a panorama did not win over none
    engines = {"mvrecon": engine("engine", registered=0, registered_pct=0.0, points=None),
               "colmap": engine("engine", registered=3, registered_pct=30.0, points=0)}
    rows = {r["metric"]: r for r in summary_rows(engines)}
    assert rows["registered"]["winners"] == [] and rows["registered_pct"]["winners"] == []


def test_cli_errors(tmp_path, capsys):
    assert main(["compare", "-o", str(tmp_path / "r")]) == 2
    assert "give either IMAGES or --models" in capsys.readouterr().err
    assert main(["compare", "--models", str(tmp_path), "-o", str(tmp_path / "r")]) == 2
    assert "at least two models" in capsys.readouterr().err
    assert main(["compare", str(tmp_path / "none"), "-o", str(tmp_path / "r")]) == 2
    assert "none: no such folder" in capsys.readouterr().err


def strict_json(text: str):
    """JSON as a browser reads it: NaN or Infinity is an error there, not a number."""
    def refuse(constant):
        raise ValueError(f"{constant} is not JSON")
    return json.loads(text, parse_constant=refuse)


def test_mvrecon_args_in_the_documented_form_reach_mvrecons_run(tmp_path):
    from mvrecon.cli import parse_args

    for argv, value in ((["--mvrecon-args", "--upright"], "--upright"),  # rejected: "expected one argument"
                        (["--mvrecon-args", "--max-features 2000"], "--max-features 2000"),
                        (["--mvrecon-args=--upright"], "--upright"),
                        (["--mvrecon-args", "--upright", "--seed", "2"], "--upright")):
        args = parse_args(["compare", "imgs", "-o", "r", *argv])
        assert args.mvrecon_args == value and args.images == "imgs", argv
    assert parse_args(["compare", "imgs", "-o", "r", "--mvrecon-args", "--upright", "--seed", "2"]).seed == 2
    # through to the command that ran (both runs stopped at once by the timeout: no time spent on them)
    images, _ = synthetic_scene(tmp_path / "scene")
    out = tmp_path / "r"
    assert main(["-q", "compare", str(images), "-o", str(out), "--no-same-matches", "--timeout", "0.01",
                 "--mvrecon-args", "--upright"]) == 1
    meta = run_meta(out / "runs" / "mvrecon")
    assert meta["command"][-1] == "--upright" and meta["options"]["mvrecon_args"] == ["--upright"]


def test_bad_mvrecon_args_are_refused_before_any_engine_runs(tmp_path, capsys):
    images, _ = synthetic_scene(tmp_path / "scene")
    out = tmp_path / "r"
    for extra, message in ((["--mvrecon-args=--bogus"], "--mvrecon-args: unrecognized arguments: --bogus"),
                           (["--mvrecon-args", "--bogus"], "--mvrecon-args: unrecognized arguments: --bogus"),
                           (["--mvrecon-args", "--max-features 0"],
                            "--mvrecon-args: --max-features: must be at least 1"),
                           (["--mvrecon-args", "--seed 3"], "--seed would make mvrecon's run differ from COLMAP's"),
                           (["--mvrecon-args", "-o elsewhere"], "-o/--output is compare's to choose"),
                           (["--mvrecon-args", f"--config {tmp_path / 'none.toml'}"], "none.toml"),
                           (["--mvrecon-args", "--upright 'x"], "--mvrecon-args: No closing quotation")):
        code = main(["compare", str(images), "-o", str(out), "--no-same-matches", "--timeout", "60", *extra])
        err = capsys.readouterr().err
        assert code == 2 and message in err and len(err.splitlines()) == 1, (extra, err)
        assert not out.exists(), extra  # nothing ran: a misspelt flag is caught before COLMAP's run


def test_models_refuse_the_options_of_runs(runs, tmp_path, capsys):
    images, gt, colmap, same = runs
    base = ["compare", "--models", str(colmap.out_dir), str(same.out_dir), "-o", str(tmp_path / "r")]
    for extra, named in ((["--colmap-global"], "--colmap-global"), (["--global-mappers"], "--global-mappers"),
                         (["--seed", "3"], "--seed"),
                         (["--camera-params", "1200,320,240,0"], "--camera-params"),
                         (["--seed", "0", "--timeout", "5"], "--seed, --timeout")):
        assert main(base + extra) == 2, extra
        err = capsys.readouterr().err
        assert f"error: {named}: only for runs on IMAGES" in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "r").exists()


def test_skipped_images_are_in_the_report_and_warned_once(tmp_path, caplog):
    from mvrecon.io.images import image_problem

    images, _ = synthetic_scene(tmp_path / "scene")
    folder = tmp_path / "imgs"
    shutil.copytree(images, folder)
    data = sorted(images.glob("*.png"))[0].read_bytes()
    (folder / "cut.png").write_bytes(data[: len(data) // 2])  # a copy cut off in its pixel data
    (folder / "notes.txt").write_text("not an image, not an image file either")
    reason = image_problem(folder / "cut.png")
    assert reason
    out = tmp_path / "r"
    with caplog.at_level("WARNING"):
        assert main(["-q", "compare", str(folder), "-o", str(out), "--no-same-matches", "--timeout", "0.01"]) == 1
    warned = [r.getMessage() for r in caplog.records if "cut.png" in r.getMessage()]
    assert len(warned) == 1, warned  # it was printed twice
    m = strict_json((out / "metrics.json").read_text())
    assert m["skipped_images"] == {"cut.png": reason}
    assert "cut.png" not in m["images"] and len(m["images"]) == 8
    page = (out / "index.html").read_text()
    assert "<h2>Images skipped</h2>" in page and "<td>cut.png</td>" in page
    with open(out / "metrics.csv") as f:
        assert ["skipped", "", "cut.png", "reason", reason] in list(csv.reader(f))


def failed_engine_metrics(rel_errors, per_image):
    """A metrics dict as `evaluate` makes it: a good engine with these errors, and one whose run failed."""
    images = sorted(per_image)
    good = {"role": "engine", "error": None, "summary": {"auc@5": 0.99}, "stages": {},
            "relative_pose_errors_deg": rel_errors, "per_image": per_image}
    failed = {"role": "engine", "error": "exit code 1: boom", "summary": {"auc@5": 0.0}, "stages": {},
              "relative_pose_errors_deg": [180.0] * len(rel_errors),
              "per_image": {n: {"status": "unregistered", "model": None, "reason": "run failed"} for n in images}}
    return {"images": images, "engines": {"mvrecon": failed, "colmap": good}}


def test_cumulative_plot_fits_the_data_and_is_quiet_when_an_engine_failed(monkeypatch):
    import warnings

    from mvrecon.eval import figures

    rng = np.random.default_rng(0)
    names = [f"{k:04d}.png" for k in range(8)]
    per_image = {n: {"status": "registered", "model": 0, "rotation_error_deg": float(r), "center_error_pct": float(c)}
                 for n, r, c in zip(names, rng.uniform(0.02, 0.08, 8), rng.uniform(0.02, 0.15, 8))}
    metrics = failed_engine_metrics(rng.uniform(0.01, 0.2, 28).tolist(), per_image)
    figs = []
    monkeypatch.setattr(figures, "_png", lambda fig: figs.append(fig) or b"png")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # matplotlib's "No artists with labels found to put in legend"
        assert figures.cumulative_errors_png(metrics) == b"png"
        figures.per_image_errors_png(metrics)
        figures.timing_png({**metrics, "engines": {**metrics["engines"], "colmap": {
            **metrics["engines"]["colmap"], "summary": {"wall_s": 3.0}}}})
    fig = figs[0]
    relative, rotation, centre = fig.axes
    assert 0.2 <= relative.get_xlim()[1] < 0.5  # errors up to 0.2 deg: not 0-10 deg, all on the y axis
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    for ax in (rotation, centre):
        lo, hi = ax.get_xlim()
        assert lo <= 0.02 and 0.08 <= hi <= 1.0
        labels = [t for t in ax.xaxis.get_majorticklabels() + ax.xaxis.get_minorticklabels()
                  if t.get_visible() and t.get_text() and lo <= t.get_position()[0] <= hi]
        boxes = sorted((t.get_window_extent(renderer) for t in labels), key=lambda b: b.x0)
        assert len(boxes) >= 2
        assert all(a.x1 <= b.x0 for a, b in zip(boxes, boxes[1:])), [t.get_text() for t in labels]
    import matplotlib.pyplot as plt

    for f in figs:
        plt.close(f)


def test_cli_models_with_damaged_files_are_one_line(runs, tmp_path, capsys):
    colmap = runs[2]
    broken_report, broken_model = tmp_path / "a", tmp_path / "b"
    shutil.copytree(colmap.out_dir, broken_report)
    (broken_report / "report.json").write_text('{"engine": ')
    shutil.copytree(colmap.out_dir / "sparse" / "0", broken_model)
    data = (broken_model / "images.bin").read_bytes()
    (broken_model / "images.bin").write_bytes(data[: len(data) // 2])
    cut_points = tmp_path / "c"  # pycolmap itself could allocate without end on this one
    shutil.copytree(colmap.out_dir / "sparse" / "0", cut_points)
    data = (cut_points / "points3D.bin").read_bytes()
    (cut_points / "points3D.bin").write_bytes(data[: int(0.6 * len(data))])
    for model, message in ((broken_report, "report.json: not valid JSON"),
                           (broken_model, f"{broken_model}: cannot read this COLMAP model (images.bin: cut off"),
                           (cut_points, f"{cut_points}: cannot read this COLMAP model (points3D.bin: cut off")):
        assert main(["compare", "-q", "--models", str(colmap.out_dir), str(model), "-o", str(tmp_path / "r")]) == 2
        err = capsys.readouterr().err
        assert message in err and len(err.splitlines()) == 1, err


def test_cli_models_with_ground_truth(runs, tmp_path, capsys):
    images, gt, colmap, same = runs
    code = main(["compare", "-q", "--models", str(colmap.out_dir), str(same.out_dir), "--gt", str(gt),
                 "-o", str(tmp_path / "rep")])
    assert code == 0
    out = capsys.readouterr().out
    assert "relative-pose AUC@5" in out and "report:" in out
    assert (tmp_path / "rep" / "index.html").is_file() and (tmp_path / "rep" / "metrics.csv").is_file()
    m = json.loads((tmp_path / "rep" / "metrics.json").read_text())
    assert list(m["engines"]) == ["colmap", "colmap-same-matches"]
    assert load_run(colmap.out_dir).report["engine"] == "colmap"
    # scored against the ground truth given, not against one of the models
    assert m["reference"]["name"] == "ground truth" and m["reference"]["images"] == 8
    assert [e["role"] for e in m["engines"].values()] == ["engine", "diagnostic"]
    for name in m["engines"]:
        summary = m["engines"][name]["summary"]
        assert summary["registered"] == 8, name
        assert summary["auc@5"] > 0.9 and summary["median_rotation_error_deg"] < 0.5, (name, summary)


def test_compare_images_runs_all_three_and_scores_them_like_the_metrics_do(runs, tmp_path_factory):
    images, gt, colmap, same = runs
    root = colmap.out_dir.parents[1]
    cmp = compare_images(images, root, gt=gt, config=CompareConfig(options=OPTS))
    m = cmp.metrics
    assert list(m["engines"]) == ["mvrecon", "colmap", "colmap-same-matches"]
    assert all(e["error"] is None for e in m["engines"].values()), {k: e["error"] for k, e in m["engines"].items()}
    mv = load_run(root / "runs" / "mvrecon")
    assert mv.report["engine"] == "mvrecon" and mv.models
    # COLMAP mapped mvrecon's own matches: same database content, a model of its own
    assert m["engines"]["colmap-same-matches"]["summary"]["verified_pairs"] == \
        m["engines"]["mvrecon"]["summary"]["verified_pairs"]
    assert m["engines"]["colmap"]["out_dir"] == str(colmap.out_dir)  # reused, not rerun
    for name, run in (("mvrecon", mv), ("colmap", colmap)):
        expected = accuracy_summary(run.poses, G.load_ground_truth(gt))
        got = m["engines"][name]["summary"]
        for key in ("auc@1", "auc@5", "registered", "components", "median_rotation_error_deg"):
            assert got[key] == pytest.approx(expected[key], rel=1e-9), (name, key)
    for name in ("mvrecon", "colmap-same-matches"):  # and each engine's model is right, against the ground truth
        got = m["engines"][name]["summary"]
        assert got["registered"] == 8 and got["auc@5"] > 0.9 and got["median_rotation_error_deg"] < 0.5, (name, got)
    ratio = m["engines"]["mvrecon"]["summary"]["time_ratio_vs_colmap"]
    assert ratio == pytest.approx(mv.wall_s / colmap.wall_s)
    assert m["engines"]["mvrecon"]["stages"].keys() >= {"features", "matching", "mapping"}


@pytest.mark.slow
def test_compare_lists_the_global_mappers_beside_the_incremental_ones(runs):
    images, gt, colmap, _ = runs
    root = colmap.out_dir.parents[1]
    config = CompareConfig(options=OPTS, colmap_global=True, mvrecon_global=True, same_matches=False)
    m = compare_images(images, root, gt=gt, config=config).metrics
    assert list(m["engines"]) == ["mvrecon", "colmap", "mvrecon-global", "colmap-global"]
    assert run_meta(root / "runs" / "mvrecon-global")["command"][-2:] == ["--mapper", "global"]
    for name in ("mvrecon-global", "colmap-global"):  # each global mapper's model, against the ground truth
        got = m["engines"][name]["summary"]
        assert m["engines"][name]["error"] is None and got["registered"] == 8 and got["auc@5"] > 0.9, (name, got)


def test_colmap_gets_mvrecons_auto_camera_groups(runs):
    from mvrecon.eval.runners import _camera_groups

    images = runs[0]
    assert _camera_groups(images) == [sorted(p.name for p in images.glob("*.png"))]  # no EXIF, one size: one camera
    imc = data_set("imc_reichstag") / "images"
    assert len(_camera_groups(imc)) == 10  # ten sizes: ten cameras

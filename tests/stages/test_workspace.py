"""Workspace behaviour: resume after an interruption, refusal of a changed config, bad input through the CLI."""

import json
import logging

import numpy as np
import pytest
from PIL import Image

from mvrecon import database as dbmod
from mvrecon.cameras import CameraConfig
from mvrecon.cli import main
from mvrecon.errors import InputError
from mvrecon.features.sift import SiftConfig
from mvrecon.stages import features as features_stage
from mvrecon.stages import matching as matching_stage
from mvrecon.stages.common import FrontendConfig
from mvrecon.stages.features import extract_features
from mvrecon.stages.matching import match
from mvrecon.workspace import Workspace
from tests.helpers import textured_views


class Stop(Exception):
    pass


def stop_after(k):
    calls = []

    def callback(item):
        calls.append(item)
        if len(calls) == k:
            raise Stop

    return callback


@pytest.mark.parametrize("workers", [1, 2])
def test_interrupted_features_and_matching_resume_without_recomputing(tmp_path, workers):
    images = textured_views(tmp_path / "images")
    config = FrontendConfig(workers=workers, sift=SiftConfig(max_num_features=800))
    ws = tmp_path / "ws"
    with pytest.raises(Stop):
        extract_features(config, images, ws, on_image=stop_after(2))
    with dbmod.open_database(ws / "database.db") as db:
        done = {i.name: dbmod.read_features(db, i.image_id)[0] for i in dbmod.read_images(db).values()}
    assert sorted(done) == ["view00.png", "view01.png"]

    summary = extract_features(config, images, ws)
    assert summary.num_extracted == 4 and summary.num_images == 6 and summary.num_cameras == 1
    with dbmod.open_database(ws / "database.db") as db:
        by_name = {i.name: i.image_id for i in dbmod.read_images(db).values()}
        for name, keypoints in done.items():  # the first run's results were kept, not rewritten
            np.testing.assert_array_equal(dbmod.read_features(db, by_name[name])[0], keypoints)
    assert extract_features(config, images, ws).num_extracted == 0

    with pytest.raises(Stop):
        match(config, ws, on_batch=stop_after(1), batch_size=4)
    resumed = match(config, ws, batch_size=4, max_cached_images=2)  # also exercises descriptor-cache eviction
    assert resumed.num_pairs == 15 and resumed.num_matched == 11
    assert resumed.num_verified == 15 and min(resumed.inliers.values()) >= 15
    assert match(config, ws).num_matched == 0


def test_a_full_disk_stops_the_run_in_one_line_and_keeps_its_work(tmp_path, monkeypatch, capsys):
    """On a full disk pycolmap's database commit aborted the process (SIGABRT, a C++ stack dump and a Python
    traceback). The free space is now checked before each unit is written: one line naming the database, exit
    2, and the images done so far are kept, so the run goes on from them once there is room."""
    import os
    from types import SimpleNamespace

    from mvrecon.io import files

    images = textured_views(tmp_path / "images")
    out = tmp_path / "run"
    real, checks = os.statvfs, []

    def filling(path):  # room for three images' features, then none
        checks.append(path)
        return SimpleNamespace(f_bavail=0 if len(checks) > 3 else real(path).f_bavail, f_frsize=real(path).f_frsize)

    monkeypatch.setattr(files.os, "statvfs", filling)
    assert main(["-q", "reconstruct", str(images), "-o", str(out), "--workers", "1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{out / 'database.db'}: the disk is full (0.0 MB free" in err
    with dbmod.open_database(out / "database.db") as db:
        assert sorted(i.name for i in dbmod.read_images(db).values()) == ["view00.png", "view01.png", "view02.png"]
    monkeypatch.setattr(files.os, "statvfs", real)
    summary = extract_features(FrontendConfig(workers=1), images, out)
    assert summary.num_extracted == 3 and summary.num_images == 6


def test_a_full_disk_met_by_python_writes_is_one_line_too(tmp_path, monkeypatch, capsys):
    """A write that Python makes (a snapshot, the report) fails with ENOSPC and no file name; it printed a
    traceback. It is one line, exit 2, and the run's folder stays for the rerun."""
    import errno

    from mvrecon import pipeline

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(pipeline, "write_report", full)
    out = tmp_path / "run"
    assert main(["-q", "reconstruct", str(textured_views(tmp_path / "images")), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err == "mvrecon: error: writing the outputs: no space left on the disk; free some space and run the " \
        "command again: what it did so far is kept\n"
    assert (out / "database.db").is_file()


def test_a_run_on_a_read_only_file_system_is_read_and_not_called_corrupt(tmp_path, capsys):
    """A finished run on a read-only mount (a shared drive, a DVD): its WAL database cannot be read without a
    shared-memory file next to it, so `map` said it was "not a readable COLMAP database; delete it". It is read,
    and what needs to write says that the folder cannot be written."""
    import os
    import subprocess

    if os.geteuid() != 0:
        pytest.skip("mounting a read-only file system needs root")
    mount = tmp_path / "drive"
    mount.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64m", "tmpfs", str(mount)]).returncode != 0:
        pytest.skip("this machine does not let tests mount a tmpfs")
    try:
        run = mount / "run"
        assert main(["-q", "reconstruct", str(textured_views(tmp_path / "images")), "-o", str(run)]) == 0
        subprocess.run(["mount", "-o", "remount,ro", str(mount)], check=True)
        assert sum(dbmod.pair_configurations(run / "database.db").values()) == 15
        capsys.readouterr()
        assert main(["-q", "map", "-w", str(run), "--overwrite"]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"{run}: cannot write in this folder" in err and "delete" not in err
    finally:
        subprocess.run(["umount", str(mount)])


def test_ctrl_c_inside_a_database_unit_waits_for_its_end(tmp_path):
    """pycolmap's transaction commits what its block wrote however the block ends: a Ctrl-C between an image's
    row and its features left the image without features. Ctrl-C now waits for the unit to be written whole."""
    import signal

    path = tmp_path / "database.db"
    # Python's Ctrl-C handler, as in a terminal: a test run started in the background by a script (`cmd &`,
    # nohup) inherits SIGINT ignored, and then rightly ignores the Ctrl-C below
    interactive = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with dbmod.open_database(path) as db:
            camera = dbmod.write_camera(db, dbmod.CameraInfo(model="SIMPLE_RADIAL", width=64, height=48,
                                                             params=np.array([60.0, 32, 24, 0])))
            with pytest.raises(KeyboardInterrupt):
                with dbmod.transaction(db, path, 0):
                    image_id = dbmod.write_image(db, "a.png", camera)
                    signal.raise_signal(signal.SIGINT)
                    dbmod.write_features(db, image_id, np.zeros((5, 4)), np.zeros((5, 128), np.uint8))
            assert dbmod.has_features(db, image_id) and dbmod.num_keypoints(db, image_id) == 5
    finally:
        signal.signal(signal.SIGINT, interactive)


def test_sigterm_stops_a_run_as_ctrl_c_does_and_the_rerun_continues(tmp_path):
    """SIGTERM (`timeout`, `kill`, a batch scheduler) met glog's failure handler, which pycolmap installs on
    import: a 30-line C stack dump, as if mvrecon had crashed, and death by the signal. It now stops the run as
    Ctrl-C does: one line, exit code 143, the work done kept. SIGTERM here arrives as matching starts."""
    import subprocess
    import sys

    images = textured_views(tmp_path / "images")
    out = tmp_path / "run"
    script = """
import os, signal, sys
import mvrecon.pipeline as pipeline
real = pipeline.match
def match(*args, **kwargs):
    os.kill(os.getpid(), signal.SIGTERM)
    return real(*args, **kwargs)
pipeline.match = match
from mvrecon.cli import main
sys.exit(main(["-q", "reconstruct", sys.argv[1], "-o", sys.argv[2]]))
"""
    done = subprocess.run([sys.executable, "-c", script, str(images), str(out)], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 143 and "Aborted" not in done.stderr
    assert done.stderr.splitlines() == ["mvrecon: terminated (SIGTERM); features and matches done are kept; rerun "
                                        "the same command to continue, with --resume to continue mapping from its "
                                        "last snapshot too"]
    with dbmod.open_database(out / "database.db") as db:
        assert sum(dbmod.has_features(db, i) for i in dbmod.read_images(db)) == 6
    assert main(["-q", "reconstruct", str(images), "-o", str(out)]) == 0


def test_parallel_extraction_numbers_images_in_name_order(tmp_path):
    """Image ids (and so the mapper's order and its models) must not depend on which worker finishes first:
    the first image is made much larger, so it finishes last."""
    images = textured_views(tmp_path / "images", count=4)
    big = np.asarray(Image.open(images / "view00.png"))
    Image.fromarray(np.tile(big, (4, 4, 1))).save(images / "view00.png")
    config = FrontendConfig(workers=2, sift=SiftConfig(max_num_features=800))
    extract_features(config, images, tmp_path / "ws")
    with dbmod.open_database(tmp_path / "ws" / "database.db") as db:
        by_id = sorted((i.image_id, i.name) for i in dbmod.read_images(db).values())
    assert [name for _, name in by_id] == [f"view{i:02d}.png" for i in range(4)]


def test_an_image_whose_probe_fails_is_skipped_though_its_early_job_succeeded(tmp_path, monkeypatch):
    """On a fresh workspace the images go to the workers before they are probed: an image whose header probe
    then fails must be reported and left out of the database, whatever its worker returned."""
    images = textured_views(tmp_path / "images", count=3)
    probe = features_stage.image_metadata

    def failing_probe(path):
        if path.name == "view01.png":
            raise InputError(f"{path}: cannot read image header (test)")
        return probe(path)

    monkeypatch.setattr(features_stage, "image_metadata", failing_probe)
    summary = extract_features(FrontendConfig(workers=2, sift=SiftConfig(max_num_features=500)), images,
                               tmp_path / "ws")
    assert summary.num_images == 2 and summary.num_extracted == 2
    assert "cannot read image header (test)" in summary.failed["view01.png"]
    with dbmod.open_database(tmp_path / "ws" / "database.db") as db:
        assert sorted(i.name for i in dbmod.read_images(db).values()) == ["view00.png", "view02.png"]


def test_the_stage_clock_counts_the_cpu_of_the_feature_workers(tmp_path):
    """report.json's cpu_s of a stage holds its workers' CPU: the parent mostly waits while they run SIFT."""
    import resource

    from mvrecon.executor import StageClock

    images = textured_views(tmp_path / "images", count=6, size=(480, 640))
    own = resource.getrusage(resource.RUSAGE_SELF)
    clock = StageClock()
    extract_features(FrontendConfig(workers=2), images, tmp_path / "ws")
    stage = clock.done("features")
    after = resource.getrusage(resource.RUSAGE_SELF)
    parent = after.ru_utime + after.ru_stime - own.ru_utime - own.ru_stime
    workers = stage["cpu_s"] - parent
    assert workers > 0.1 and workers > parent  # six SIFT runs of 640 x 480, none of them in this process
    assert stage["cpu_s"] <= 3 * stage["wall_s"] + 0.05  # three processes: counted once each
    assert stage["peak_mem_mb"] > 50
    assert clock.total()["cpu_s"] >= stage["cpu_s"]


def test_a_changed_config_is_refused_unless_overwrite(tmp_path):
    images = textured_views(tmp_path / "images", count=3)
    config = FrontendConfig(workers=1, sift=SiftConfig(max_num_features=500))
    ws = tmp_path / "ws"
    extract_features(config, images, ws)
    match(config, ws)
    other = FrontendConfig(workers=1, sift=SiftConfig(max_num_features=300))
    with pytest.raises(InputError, match=r"different features config \(sift.max_num_features: 500 -> 300\)"):
        extract_features(other, images, ws)
    with pytest.raises(InputError, match="pairs: exhaustive -> sequential:1"):
        match(FrontendConfig(workers=1, pairs="sequential:1"), ws)
    summary = extract_features(other, images, ws, overwrite=True)
    assert summary.num_extracted == 3 and max(summary.keypoints.values()) <= 300
    assert Workspace(ws).stage_config("matching") is None  # matches of the old features were dropped
    with pytest.raises(InputError, match="no features in this workspace"):
        match(config, tmp_path / "empty_ws")


def run_cli(argv, capsys):
    code = main(argv)
    return code, capsys.readouterr()


def summary_lines(caplog, start):
    """The INFO lines of mvrecon starting with `start` ("Features:", "Matching:") logged so far; cleared after."""
    lines = [r.getMessage() for r in caplog.records if r.name == "mvrecon" and r.levelno == logging.INFO
             and r.getMessage().startswith(start)]
    caplog.clear()
    return lines


def test_cli_bad_input_exits_2_with_one_line(tmp_path, capsys):
    code, out = run_cli(["features", str(tmp_path / "nope"), "-w", str(tmp_path / "ws")], capsys)
    assert code == 2 and out.err.strip() == f"mvrecon: error: {tmp_path / 'nope'}: no such folder"
    (tmp_path / "empty").mkdir()
    code, out = run_cli(["features", str(tmp_path / "empty"), "-w", str(tmp_path / "ws")], capsys)
    assert code == 2 and "no readable JPEG, PNG, TIFF, BMP or PNM images" in out.err and len(out.err.splitlines()) == 1
    code, out = run_cli(["match", "-w", str(tmp_path / "ws"), "--pairs", "sequential:0"], capsys)
    assert code == 2 and "positive integer" in out.err
    textured_views(tmp_path / "images", count=2)
    # values a config cannot hold are refused before any work, naming where they came from
    (tmp_path / "t.toml").write_text('[sift]\nmax_num_features = "lots"\n[mapper]\ninit_min_inliers = -5\n')
    (tmp_path / "w.toml").write_text("[workers]\nx = 1\n")
    (tmp_path / "a.toml").write_text('[mapper]\ninit_min_tri_angles_deg = [8.0, "x"]\n')
    for args, message in (
            (["--max-image-size", "-1"], "--max-image-size: must be at least 16, got -1"),
            (["--ratio", "5"], "--ratio: must be at most 1.0, got 5.0"),
            (["--camera-params=nan,32,24,0"], "--camera-params nan,32,24,0: expected finite numbers"),
            (["--camera-params=0,32,24,0"], "and a positive focal length"),
            (["--config", str(tmp_path / "t.toml")], "t.toml: sift: max_num_features: expected a whole number"),
            (["--config", str(tmp_path / "w.toml")], "w.toml: workers: expected a single value, not a table"),
            (["--config", str(tmp_path / "a.toml")], "mapper: init_min_tri_angles_deg[1]: expected float, got 'x'"),
            (["--config", str(tmp_path)], f"{tmp_path}: Is a directory")):
        code, out = run_cli(["reconstruct", str(tmp_path / "images"), "-o", str(tmp_path / "run")] + args, capsys)
        assert code == 2 and message in out.err and len(out.err.splitlines()) == 1, (args, out.err)
        assert not (tmp_path / "run" / "database.db").exists()
    (tmp_path / "t.toml").write_text("[mapper]\ninit_min_inliers = -5\n")
    code, out = run_cli(["reconstruct", str(tmp_path / "images"), "-o", str(tmp_path / "run"), "--config",
                         str(tmp_path / "t.toml")], capsys)
    assert code == 2 and "mapper: init_min_inliers: must be at least 0, got -5" in out.err
    # numbers outside an option's range stop at the parser (argparse: usage line and the error, exit 2)
    for argv, message in ((["degrade", str(tmp_path / "images"), "-o", str(tmp_path / "d"), "--seed", "-1"],
                           "argument --seed: must be at least 0, got -1"),
                          (["stereo", "a.png", "b.png", "-o", str(tmp_path / "s"), "--num-disparities", "-16"],
                           "argument --num-disparities: must be at least 1, got -16"),
                          (["calibrate", str(tmp_path), "-o", str(tmp_path / "c.toml"), "--square", "nan"],
                           "argument --square: must be above 0.0, got nan")):
        with pytest.raises(SystemExit) as stop:
            main(argv)
        assert stop.value.code == 2 and message in capsys.readouterr().err
    # an output path that is a file: the path and the reason, not a NotADirectoryError trace
    (tmp_path / "file.txt").write_text("x")
    code, out = run_cli(["reconstruct", str(tmp_path / "images"), "-o", str(tmp_path / "file.txt")], capsys)
    assert code == 2 and out.err.strip().endswith(("Not a directory", "workspace exists and is not a folder"))
    assert len(out.err.splitlines()) == 1


def test_errors_name_the_flag_or_the_config_file_key_the_user_wrote(tmp_path, capsys):
    """A bad value is named as the user gave it: the flag (not the config field behind it), or the --config
    file with its table and key (not a flag the user never typed); a value where a table belongs is refused in one
    line, not met as a traceback. All before any work: no workspace is made."""
    images = textured_views(tmp_path / "images", count=2, size=(40, 50))
    files = {"m.toml": "mapper = 3\n", "s.toml": "sift = 2\n",
             "mode.toml": '[camera]\nmode = "whatever"\n', "model.toml": '[camera]\nmodel = "FISHEYE"\n',
             "pairs.toml": 'pairs = "sequential:0"\n', "params.toml": "[camera]\nparams = [1.0, 2.0]\n",
             "pinhole.toml": '[camera]\nmodel = "PINHOLE"\n', "strs.toml": '[camera]\nparams = ["a", 2, 3, 4]\n'}
    for name, text in files.items():
        (tmp_path / name).write_text(text)
    out_dir, t = tmp_path / "run", tmp_path
    for args, message in (
            (["--config", f"{t}/m.toml"], f"{t}/m.toml: 'mapper' must be a table ([mapper] with its options on "
                                          "the lines below), got 3"),
            (["--config", f"{t}/s.toml"], f"{t}/s.toml: 'sift' must be a table ([sift] with its options on the "
                                          "lines below), got 2"),
            (["--config", f"{t}/mode.toml"], f"{t}/mode.toml: camera: mode = 'whatever': expected one of auto, "
                                             "single, per-folder, per-image"),
            (["--config", f"{t}/model.toml"], f"{t}/model.toml: camera: model = 'FISHEYE': expected one of "
                                              "SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, OPENCV_FISHEYE"),
            (["--config", f"{t}/pairs.toml"], f"{t}/pairs.toml: pairs = 'sequential:0': the window must be a "
                                              "positive integer, e.g. sequential:10"),
            (["--config", f"{t}/params.toml", "--camera-model", "PINHOLE"],
             f"{t}/params.toml: camera: params = [1.0, 2.0] with --camera-model PINHOLE: PINHOLE takes 4 "
             "parameters (fx, fy, cx, cy), got 2"),
            (["--config", f"{t}/pinhole.toml", "--camera-params", "1,2,3"],
             f"--camera-params 1,2,3 with {t}/pinhole.toml: camera: model = 'PINHOLE': PINHOLE takes 4 "
             "parameters (fx, fy, cx, cy), got 3"),
            (["--config", f"{t}/strs.toml"], f"{t}/strs.toml: camera: params = ['a', 2, 3, 4]: could not "
                                             "convert string to float: 'a'"),
            (["--camera-params", "1,2,3"], "--camera-params 1,2,3: SIMPLE_RADIAL takes 4 parameters "
                                           "(f, cx, cy, k), got 3"),
            (["--max-features", "0"], "--max-features: must be at least 1, got 0"),
            (["--pairs", "sequential:0"], "--pairs sequential:0: the window must be a positive integer, "
                                          "e.g. sequential:10")):
        commands = [["reconstruct", str(images), "-o", str(out_dir)]]
        if args[0] != "--pairs":  # `features` has no --pairs, but checks the whole --config file
            commands.append(["features", str(images), "-w", str(out_dir)])
        for command in commands:
            code, out = run_cli(command + args, capsys)
            assert (code, out.err) == (2, f"mvrecon: error: {message}\n"), (command, args)
            assert not out_dir.exists()
    # `compare` checks its camera flags without an origin: the default model it fills in is not a flag the
    # user typed, so only --camera-params is named (the error itself says which model it holds for)
    code, out = run_cli(["compare", str(images), "-o", str(out_dir), "--camera-params", "1,2,3"], capsys)
    assert (code, out.err) == (2, "mvrecon: error: --camera-params 1,2,3: SIMPLE_RADIAL takes 4 parameters "
                                  "(f, cx, cy, k), got 3\n")
    assert not out_dir.exists()
    # values nobody wrote (a config made in code, an origin without them) are named as values, a default as one
    for camera, origin, message in (
            (CameraConfig(model="PINHOLE", params=(1.0, 2.0)), None,
             "--camera-params 1,2 with --camera-model PINHOLE: PINHOLE takes 4 parameters"),
            (CameraConfig(params=(1.0, 2.0, 3.0)), {}, "camera params 1,2,3 with the default camera model "
                                                       "SIMPLE_RADIAL: SIMPLE_RADIAL takes 4 parameters"),
            (CameraConfig(mode="whatever"), {}, "camera mode whatever: expected one of auto")):
        with pytest.raises(InputError) as refused:
            camera.validate(origin)
        assert str(refused.value).startswith(message), str(refused.value)
    # `map` reads the [mapper] table only, and refuses a value in its place the same way
    code, out = run_cli(["map", "-w", str(out_dir), "--config", str(tmp_path / "m.toml")], capsys)
    assert (code, out.err) == (2, f"mvrecon: error: {tmp_path / 'm.toml'}: 'mapper' must be a table ([mapper] "
                                  "with its options on the lines below), got 3\n")
    assert not out_dir.exists()


def test_cli_skips_corrupt_and_non_image_files(tmp_path, capsys, caplog):
    images = textured_views(tmp_path / "images", count=2)
    good = (images / "view00.png").read_bytes()
    (images / "truncated.png").write_bytes(good[: len(good) // 2])  # caught when listing (header walk)
    Image.fromarray(np.zeros((40, 50), np.uint8)).save(images / "half.tif")
    tif = (images / "half.tif").read_bytes()
    (images / "half.tif").write_bytes(tif[: len(tif) // 2])  # header fine, pixels cut: caught when decoding
    (images / "readme.txt").write_text("not an image")
    ws = tmp_path / "ws"
    caplog.set_level(logging.INFO, logger="mvrecon")
    code, out = run_cli(["features", str(images), "-w", str(ws), "--max-features", "500"], capsys)
    assert code == 0, out.err
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    [summary] = summary_lines(caplog, "Features: 2 images")  # logged (-q hides it), not printed
    assert "2 image(s) unreadable or not extracted, skipped: half.tif, truncated.png" in summary
    assert out.out == ""
    assert any("truncated.png" in w and "truncated" in w.split("truncated.png", 1)[1].lower() for w in warnings)
    assert any("half.tif: cannot decode image" in w for w in warnings)
    assert sum("readme.txt" in w for w in warnings) == 1
    (tmp_path / "pairs.txt").write_text("view00.png nope.png\n")  # refused before the stage is recorded:
    code, out = run_cli(["match", "-w", str(ws), "--pairs", str(tmp_path / "pairs.txt")], capsys)
    assert code == 2 and "unknown image 'nope.png'" in out.err
    # an image paired with itself was dropped silently (0 pairs, exit 0): refused as an unknown name is
    (tmp_path / "pairs.txt").write_text("# self\nview01.png view01.png\n")
    code, out = run_cli(["match", "-w", str(ws), "--pairs", str(tmp_path / "pairs.txt")], capsys)
    assert (code, out.err) == (2, f"mvrecon: error: {tmp_path / 'pairs.txt'}:2: pairs image 'view01.png' with "
                                  "itself\n")
    code, out = run_cli(["match", "-w", str(ws)], capsys)  # so the default pairs are no "different config"
    assert code == 0 and "1 verified pairs" in summary_lines(caplog, "Matching:")[0]
    for damaged in ('{"features": {}}', '{"features": {"key": "0"}}', '[]', '{"feat'):  # --overwrite redoes
        Workspace(ws).record_path.write_text(damaged)
        code, out = run_cli(["match", "-w", str(ws)], capsys)
        assert code == 2 and "record.json: not a valid workspace record (use --overwrite" in out.err, damaged
    code, out = run_cli(["features", str(images), "-w", str(ws), "--overwrite", "-q"], capsys)
    assert code == 0 and summary_lines(caplog, "Features:") == [] and out.out == ""  # -q: warnings only
    code, out = run_cli(["match", "-w", str(ws), "-q"], capsys)
    assert code == 0 and summary_lines(caplog, "Matching:") == [] and out.out == ""

    (images / "view01.png").unlink()
    code, out = run_cli(["features", str(images), "-w", str(tmp_path / "ws2"), "--workers", "1"], capsys)
    last = out.err.strip().splitlines()[-1]  # above it: progress bar and warnings
    assert code == 2 and last.startswith("mvrecon: error: ") and "only 1 usable image(s), need at least 2" in last
    assert "truncated.png" in last and "half.tif" in last
    # reconstruct refuses the same folder and leaves no empty output folder behind; an existing one stays
    for out_dir, kept in ((tmp_path / "new_run", False), (tmp_path, True)):
        code, out = run_cli(["reconstruct", str(images), "-o", str(out_dir), "--workers", "1"], capsys)
        assert code == 2 and "only 1 usable image(s)" in out.err.strip().splitlines()[-1]
        assert out_dir.is_dir() == kept


def test_the_command_runs_as_a_fresh_process(tmp_path):
    """The real entry point: a new interpreter (OpenCV not yet loaded, so the pool forks) with two workers."""
    import subprocess
    import sys

    images = textured_views(tmp_path / "images", count=3)
    ws = tmp_path / "ws"
    def run(*argv):
        done = subprocess.run([sys.executable, "-m", "mvrecon.cli", *argv], capture_output=True, text=True,
                              timeout=120)
        assert done.returncode == 0, done.stderr
        return done

    done = run("features", str(images), "-w", str(ws), "--max-features", "400", "--workers", "2", "-vv")
    assert "Features: 3 images (3 extracted now" in done.stderr and "process pool: 2 fork workers" in done.stderr
    done = run("match", "-w", str(ws), "--pairs", "sequential:1", "-q")  # only warnings and errors: none here
    assert (done.stdout, done.stderr) == ("", "")
    done = run("match", "-w", str(ws), "--pairs", "sequential:1")  # the summary, as every command's, on stderr
    # the window's 2 pairs and frame 0's loop closure with frame 2
    assert done.stdout == "" and done.stderr.startswith("Matching: 3 images, 3 pairs (0 matched now, 3 already")
    assert "selected by sequential:1; 3 verified pairs" in done.stderr
    with dbmod.open_database(ws / "database.db") as db:
        assert sorted(i.name for i in dbmod.read_images(db).values()) == [f"view{i:02d}.png" for i in range(3)]


def _stdout_of(script: str, *argv: str) -> str:
    """What `script` prints, run in a fresh interpreter (the modules loaded and the allocator settings under test
    last a process)."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", script, *argv], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return out.stdout


def test_the_command_line_and_pipeline_load_without_pycolmap():
    """`mvrecon --help` loads none of the heavy libraries, and the parent imports OpenCV only after the feature
    workers are forked (they then inherit nothing of it)."""
    code = ("import sys, mvrecon.cli, mvrecon.pipeline; mvrecon.cli.build_parser(); "
            "print(sorted(m for m in ('pycolmap', 'cv2', 'gtsam') if m in sys.modules))")
    assert _stdout_of(code).strip() == "[]"


def test_a_whole_run_never_imports_pycolmap(tmp_path):
    """The database and the models are written without pycolmap, whose import took 0.11 s of CPU in every run,
    beside the feature workers on the cores they need; the files are still the ones COLMAP reads."""
    import pycolmap

    images = textured_views(tmp_path / "images")
    out = tmp_path / "run"
    code = ("import sys; from mvrecon.cli import main; "
            "code = main(['-q', 'reconstruct', sys.argv[1], '-o', sys.argv[2]]); "
            "print(code, 'pycolmap' in sys.modules)")
    assert _stdout_of(code, str(images), str(out)).split() == ["0", "False"]
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert rec.num_reg_images() == 6 and rec.num_points3D() > 100
    with pycolmap.Database.open(str(out / "database.db")) as db:
        assert db.num_images() == 6 and db.num_verified_image_pairs() == 15


def test_a_run_imports_only_its_command_and_help_still_lists_every_command(capsys):
    """The start-up before the feature workers fork runs on one core: `reconstruct` imports its own command's
    module and not the others', nor numpy.random (15 ms of it together). `--help`, `-h COMMAND` and a mistyped
    command still get every command."""
    from mvrecon.cli import parse_args

    code = ("import sys, mvrecon.cli, mvrecon.pipeline; "
            "mvrecon.cli.parse_args(['-q', 'reconstruct', 'IMAGES', '-o', 'OUT']); "
            "print(sorted(m for m in sys.modules if m.startswith(('mvrecon.commands.', 'numpy.random'))))")
    assert _stdout_of(code).strip() == "['mvrecon.commands._options', 'mvrecon.commands.reconstruct']"
    assert parse_args(["-q", "reconstruct", "IMAGES", "-o", "OUT"]).output == "OUT"
    for argv in (["--help"], ["-h", "reconstruct"], ["-v", "recnstruct"]):
        with pytest.raises(SystemExit):
            parse_args(argv)
        out = capsys.readouterr()
        listed = out.out + out.err
        assert all(name in listed for name in ("reconstruct", "study", "stereo", "sem", "export")), argv


def test_a_config_file_the_command_reads_nothing_of_is_named_in_a_warning(tmp_path, caplog):
    """A file holding only [mapper] settings, given to `features` or `match`, was taken without a word, as if
    its settings had been applied; a file that holds a table the command reads is not mentioned."""
    images = textured_views(tmp_path / "images", count=3)
    mapper_only, both = tmp_path / "mapper.toml", tmp_path / "both.toml"
    mapper_only.write_text("[mapper]\ninit_min_inliers = 50\n")
    both.write_text("[sift]\nmax_num_features = 800\n[mapper]\nseed = 1\n")
    ws = tmp_path / "ws"
    with caplog.at_level(logging.WARNING):
        assert main(["-q", "features", str(images), "-w", str(ws), "--config", str(mapper_only)]) == 0
        assert main(["-q", "match", "-w", str(ws), "--config", str(mapper_only)]) == 0
    warned = [r.getMessage() for r in caplog.records if "reads none of this file's [mapper]" in r.getMessage()]
    assert [w.split("`")[1] for w in warned] == ["mvrecon features", "mvrecon match"]
    assert all(w.startswith(f"{mapper_only}: ") for w in warned)
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert main(["-q", "features", str(images), "-w", str(tmp_path / "ws2"), "--config", str(both)]) == 0
    assert "reads none" not in caplog.text


def test_exhaustive_matching_of_many_images_advises_a_linear_pair_selection(tmp_path, monkeypatch, caplog):
    """Exhaustive pairs grow with the square of the images (500 photos: 124,750 pairs), and nothing said that
    `auto` exists. Over the limit (lowered here to 4 images) one warning says so when exhaustive was asked for
    (`auto` is exhaustive only below 50 images)."""
    monkeypatch.setattr(matching_stage, "_MANY_FOR_EXHAUSTIVE", 4)
    config = FrontendConfig(workers=1, sift=SiftConfig(max_num_features=300), pairs="exhaustive")
    ws = tmp_path / "ws"
    extract_features(config, textured_views(tmp_path / "images"), ws)
    with caplog.at_level(logging.WARNING):
        match(config, ws)
    advice = [r.getMessage() for r in caplog.records if "--pairs auto" in r.getMessage()]
    assert advice == ["exhaustive matching of 6 images: 15 pairs, growing with the square of the images; --pairs "
                      "auto chooses pairs that grow linearly (retrieval, GPS positions or a video's sequence)"]
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        match(FrontendConfig(workers=1, pairs="sequential:2"), ws, overwrite=True)
        match(FrontendConfig(workers=1), ws, overwrite=True)  # auto: the same 15 pairs, and no advice
    assert not [r for r in caplog.records if "--pairs auto" in r.getMessage()]


def test_the_run_folder_is_o_everywhere_and_w_where_it_was():
    """`reconstruct -o` but `features -w`, `match -w` and `map -w` for the same folder: -o/--output is taken by
    every one of them now, and -w/--workspace stays the same option."""
    from mvrecon.cli import parse_args

    for argv, dest in ((["features", "imgs"], "workspace"), (["match"], "workspace"), (["map"], "workspace"),
                       (["reconstruct", "imgs"], "output")):
        for flag in ("-o", "--output", "-w", "--workspace"):
            assert getattr(parse_args([*argv, flag, "ws"]), dest) == "ws", (argv, flag)


def test_a_second_run_on_a_folder_in_use_is_refused_in_one_line(tmp_path, capsys):
    """Two runs writing one workspace: the second died of a SQLite constraint error with a traceback. Another
    process holding the workspace (here a child holding its lock, as a run in progress does) now refuses the
    run in one line; once that process ends, the run goes ahead."""
    import subprocess
    import sys

    images = textured_views(tmp_path / "images")
    out = tmp_path / "run"
    out.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", "import fcntl, os, sys, time; fd = os.open(sys.argv[1], "
                               "os.O_RDONLY); fcntl.flock(fd, fcntl.LOCK_EX); print('held', flush=True); "
                               "time.sleep(60)", str(out)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline() == "held\n"
        for argv in (["reconstruct", str(images), "-o", str(out)], ["features", str(images), "-w", str(out)]):
            assert main(["-q", *argv]) == 2
            assert capsys.readouterr().err == f"mvrecon: error: {out}: another mvrecon run is using this folder; " \
                "wait for it to end, or choose another folder\n"
    finally:
        holder.kill()
        holder.wait()
    assert main(["-q", "reconstruct", str(images), "-o", str(out)]) == 0
    assert main(["-q", "map", "-w", str(out), "--overwrite"]) == 0  # the lock of the run before is gone


def test_folder_and_file_names_that_are_not_utf8_are_run_or_named(tmp_path, caplog, capsys):
    """Names from an old Latin-1 archive: an image named so crashed the run with a pybind11 cast error (pycolmap
    takes UTF-8 names only), and a workspace folder named so crashed matching (reading /proc/self/maps as UTF-8).
    The folders work (a compare's HTML report names them with \\xNN escapes); such images are skipped by name
    with the reason, the others reconstructed."""
    import os
    import shutil

    images = textured_views(tmp_path / os.fsdecode(b"caf\xe9"))
    for i in (0, 1):
        shutil.copy(images / f"view0{i}.png", images / os.fsdecode(b"\xe9t\xe9_%d.png" % i))
    out = tmp_path / os.fsdecode(b"r\xe9sultat")
    with caplog.at_level(logging.WARNING):
        assert main(["-q", "reconstruct", str(images), "-o", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    status = {name: im["status"] for name, im in report["images"].items()}
    assert sorted(status) == ["\\xe9t\\xe9_0.png", "\\xe9t\\xe9_1.png"] + [f"view{i:02d}.png" for i in range(6)]
    assert [status[f"view{i:02d}.png"] for i in range(6)] == ["registered"] * 6
    assert sum("\\xe9t\\xe9_0.png: its name is not UTF-8 text" in r.getMessage() for r in caplog.records) == 1
    report_dir = tmp_path / os.fsdecode(b"compar\xe9")  # the HTML names the models' folders, escaped
    assert main(["-q", "compare", "--models", str(out / "sparse" / "0"), str(out / "sparse" / "0"),
                 "-o", str(report_dir)]) == 0
    assert "r\\xe9sultat/sparse/0" in (report_dir / "index.html").read_text(encoding="utf-8")
    # printed the same way on a strict UTF-8 stdout (a desktop's locale), which raised UnicodeEncodeError
    assert f"report: {tmp_path}/compar\\xe9/index.html\n" in capsys.readouterr().out


def test_every_command_writing_a_folder_holds_it_even_a_new_one(tmp_path, capsys):
    """Two compares into one folder broke each other (one's COLMAP database "disk I/O error", the other's mvrecon
    run refused): the commands that write an -o folder hold it for the run. A folder that did not exist is
    created and held at once, so a second run started meanwhile is refused too, and removed again when the run
    leaves it empty (a refused run leaves no folder behind)."""
    import subprocess
    import sys

    images = textured_views(tmp_path / "images")
    out = tmp_path / "new" / "report"
    holder = subprocess.Popen([sys.executable, "-c", "import sys; from mvrecon.io.files import hold_folder\n"
                               "with hold_folder(sys.argv[1]):\n print('held', flush=True); sys.stdin.readline()",
                               str(out)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline() == "held\n" and out.is_dir()
        for argv in (["compare", str(images), "-o", str(out)], ["study", str(images), "-o", str(out), "--noise", "5"],
                     ["degrade", str(images), "-o", str(out), "--noise", "5"], ["demo", "-o", str(out)],
                     ["scene", "make", "stereo_pair_small", "-o", str(out)],
                     ["sem", str(images), "-o", str(out), "--estimate-tilts"],
                     ["stereo", str(images / "view00.png"), str(images / "view01.png"), "-o", str(out)],
                     ["export", str(tmp_path), "--undistort", "-o", str(out)]):
            assert main(["-q", *argv]) == 2, argv
            assert capsys.readouterr().err == f"mvrecon: error: {out}: another mvrecon run is using this folder; " \
                "wait for it to end, or choose another folder\n", argv
    finally:
        holder.communicate("done\n", timeout=30)
    assert not (tmp_path / "new").exists()  # the holder made it, and removed it as it left it empty
    assert main(["-q", "compare", str(images), "-o", str(out), "--gt", str(tmp_path / "missing")]) == 2
    assert "ground truth not found" in capsys.readouterr().err and not (tmp_path / "new").exists()
    assert main(["-q", "degrade", str(images), "-o", str(out), "--noise", "5"]) == 0
    assert sorted(p.name for p in out.iterdir() if p.suffix == ".png") == sorted(p.name for p in images.iterdir())


def test_the_mvrecon_process_runs_openblas_on_one_thread():
    """An OpenBLAS makes its extra thread again after every fork (the feature workers, and OpenCV's own copy as
    they import it) and the thread spins 0.1 s each time on the cores the stages need: the `mvrecon` process runs
    every OpenBLAS it loads on the calling thread. A user's setting stands, and the engines a comparison times
    get the user's environment, not this one."""
    import os
    import subprocess
    import sys

    script = ("import sys; sys.argv = ['mvrecon', '-q', 'scene', 'list']\n"
              "from mvrecon.cli import main\nmain()\n"
              "import cv2, numpy\nfrom mvrecon.executor import _openblas_controls, user_environment\n"
              "print(sorted({get() for get, _ in _openblas_controls()}), len(_openblas_controls()),\n"
              "      user_environment().get('OPENBLAS_NUM_THREADS'))")
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    for setting, expected in ((None, "[1] 2 None"), ("2", "[2] 2 2")):
        if setting:
            env["OPENBLAS_NUM_THREADS"] = setting
        out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=120)
        assert out.returncode == 0 and out.stdout.splitlines()[-1] == expected, (setting, out.stdout, out.stderr)


# `refaults(mb, who)`: the page faults (of the process, or of the calling thread) of a block of `mb` MB allocated
# and freed again, which a process that keeps what it frees serves from memory it has already touched
_REFAULTS = ("import resource\n"
             "def refaults(mb, who=resource.RUSAGE_SELF):\n"
             "    before = resource.getrusage(who).ru_minflt\n"
             "    a = bytearray(mb << 20); del a\n"
             "    return resource.getrusage(who).ru_minflt - before\n")


def _faults_in_workers_and_here(faults: str) -> tuple[int, int]:
    """The page faults that `faults(_)` (a function's source, which may call `refaults`) counts: the most of four
    calls in a WorkerPool's workers, then in the parent, an interpreter with glibc's defaults."""
    script = (_REFAULTS + "import threading\nfrom mvrecon.executor import WorkerPool\n" + faults +
              "with WorkerPool(2) as pool:\n    print(max(pool.map(faults, range(4))))\nprint(faults(0))")
    in_workers, here = map(int, _stdout_of(script).split())
    return in_workers, here


def _skip_under_huge_pages(faults_without: int, least: int, block: str) -> None:
    """Where all memory is backed by transparent huge pages a block faults in few pages with or without the
    settings: nothing to tell apart."""
    if faults_without < least:
        pytest.skip(f"{block} faulted in only {faults_without} pages without the settings: this machine backs all "
                    "memory with transparent huge pages, so there is nothing to tell apart")


def test_feature_workers_reuse_the_memory_they_free():
    """SIFT allocates and frees its scale space on every image (1 GB for a 3072 x 2048 photo); glibc unmaps
    such blocks when they are freed, and each image then faulted all of it in again (herzjesu's SIFT: 1.7-1.9 s an
    image instead of 0.9-1.0 s). A worker keeps what it frees: a 64 MB block allocated again after being freed
    faults in almost none of its 16,384 pages there, and all of them in a process with glibc's defaults."""
    # bytearray, not numpy: numpy asks for huge pages on large arrays, OpenCV's allocator does not
    in_workers, here = _faults_in_workers_and_here(
        "def faults(_):\n"
        "    a = bytearray(64 << 20); del a\n"
        "    return refaults(64)\n")
    _skip_under_huge_pages(here, 8000, "a freed 64 MB block")
    assert in_workers < 1000, (in_workers, here)


def test_a_feature_workers_threads_reuse_the_memory_it_frees():
    """A worker's last image runs on every core's OpenCV thread; the extra thread took a malloc arena of its own
    and faulted in fresh memory while the worker's heap held the earlier images' free (herzjesu's features stage:
    5.5-5.6 s instead of 4.9-5.1 s, 110 MB more at the peak). In a worker, a 32 MB block that a second thread
    allocates after the worker freed one faults in almost none of its 8,192 pages; with glibc's arenas, nearly all."""
    in_workers, here = _faults_in_workers_and_here(
        "def faults(_):\n"
        "    a = bytearray(32 << 20); del a\n"
        "    counts = []\n"
        "    t = threading.Thread(target=lambda: counts.append(refaults(32, resource.RUSAGE_THREAD)))\n"
        "    t.start(); t.join()\n"
        "    return counts[0]\n")
    _skip_under_huge_pages(here, 4000, "a second thread's 32 MB block")
    assert in_workers < 500, (in_workers, here)


def test_the_mvrecon_process_reuses_the_memory_it_frees():
    """The `mvrecon` process keeps what it frees as its workers do (matching allocates each image's prepared
    descriptors and their products in blocks of a few MB): after `main` has started as the command, a 64 MB
    block allocated again after being freed faults in almost none of its pages. Called as a function, with
    arguments, `main` leaves the caller's allocator alone."""
    script = (_REFAULTS + "import sys\nfrom mvrecon import cli\n"
              "how, sys.argv = sys.argv[1], ['mvrecon', '--version']\n"
              "try:\n"
              "    cli.main() if how == 'command' else cli.main(['--version'])\n"
              "except SystemExit:\n"
              "    pass\n"
              "a = bytearray(64 << 20); del a\n"
              "print(refaults(64))")
    faults = {how: int(_stdout_of(script, how).split()[-1]) for how in ("command", "function")}
    _skip_under_huge_pages(faults["function"], 8000, "a freed 64 MB block")
    assert faults["command"] < 1000, faults


def test_feature_workers_hand_over_results_while_the_parent_holds_the_gil(tmp_path):
    """A worker's result pipe holds 64 KB, less than one image's features: while the parent held its GIL (an
    import, a database write) its pool thread could not read, and both workers stood idle. With the pipe
    widened, and the next job already handed to each worker, the workers return 200 KB results and go on to
    their next jobs while the parent holds the GIL for 2 s."""
    import subprocess
    import sys

    script = ("import sys, time\nfrom pathlib import Path\nfrom mvrecon.executor import WorkerPool\n"
              "folder = Path(sys.argv[1])\n"
              "def job(k):\n"
              "    (folder / f'start{k}').touch()\n"
              "    if k < 2:\n"
              "        time.sleep(0.3)\n"
              "        return bytes(200_000)\n"
              "    return b''\n"
              "with WorkerPool(2) as pool:\n"
              "    results = pool.map(job, range(6))\n"
              "    while not all((folder / f'start{k}').exists() for k in (0, 1)):\n"
              "        time.sleep(0.01)\n"
              "    sys.setswitchinterval(30)\n"
              "    end = time.perf_counter() + 2\n"
              "    while time.perf_counter() < end:\n"
              "        pass\n"
              "    later = sum(p.name in ('start2', 'start3') for p in folder.iterdir())\n"
              "    sys.setswitchinterval(0.005)\n"
              "    print(later, sum(map(len, results)))")
    out = subprocess.run([sys.executable, "-c", script, str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    later, total = map(int, out.stdout.split())
    assert total == 400_000
    assert later == 2, out.stdout  # with 64 KB pipes: 0 or 1, the workers blocked on their first results


def test_reconstruct_loads_the_later_stages_while_the_workers_extract(tmp_path, monkeypatch):
    """Importing GTSAM, OpenCV and the mapper took 0.15-0.2 s on one core between the stages; `reconstruct` does
    it in a thread of its own while the feature workers run (and waits for it before matching).
    load_later_stages leaves them loaded."""
    import subprocess
    import sys
    import threading

    import mvrecon.pipeline as pipeline

    calls = []
    stamps = tmp_path / "out" / features_stage.STAMPS  # written when the features stage has ended

    def record():
        calls.append((threading.current_thread() is threading.main_thread(), stamps.exists()))

    monkeypatch.setattr(pipeline, "load_later_stages", record)
    images = textured_views(tmp_path / "images", count=3)
    assert main(["-q", "reconstruct", str(images), "-o", str(tmp_path / "out")]) == 0
    assert calls == [(False, False)] and stamps.exists()  # once, in another thread, during the features stage
    script = ("import sys\nfrom mvrecon.startup import load_later_stages\nload_later_stages()\n"
              "print(all(m in sys.modules for m in ('cv2', 'gtsam', 'mvrecon.sfm.incremental')))")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.split() == ["True"], (out.stdout, out.stderr)


def test_a_drained_pool_ends_its_workers_while_the_caller_goes_on(monkeypatch):
    """Ending the workers waits for the kernel to free their memory (10-13 ms of templeSparseRing's run, on one
    core between the stages): leaving the `with` block of a drained pool hands that to a thread, which the next
    pool and the process's end wait for. After an error the workers are gone before it propagates."""
    import threading

    from mvrecon import executor

    def alive(pid):  # a zombie (a forkserver worker not yet reaped by its server) has ended
        try:
            with open(f"/proc/{pid}/stat") as f:
                return f.read().rsplit(")", 1)[1].split()[0] not in "ZX"
        except FileNotFoundError:
            return False

    release, real = threading.Event(), executor._end_pool
    monkeypatch.setattr(executor, "_end_pool", lambda pool: (release.wait(60), real(pool)))
    with executor.WorkerPool(2) as pool:
        assert list(pool.map(abs, [-1, -2, -3])) == [1, 2, 3]
        pids = pool.pids()
    assert all(alive(pid) for pid in pids)  # the block has ended; the workers' end is held back
    release.set()
    executor.wait_for_ended_pools()
    assert not any(alive(pid) for pid in pids)

    monkeypatch.setattr(executor, "_end_pool", real)
    with pytest.raises(ZeroDivisionError):
        with executor.WorkerPool(2) as pool:
            pids = pool.pids()
            1 / 0
    assert not any(alive(pid) for pid in pids) and not executor._ending


def test_the_last_images_of_a_pool_run_on_every_core_with_the_same_features(tmp_path):
    """A worker taking one of the last images leaves no image for the others, whose cores stood idle until it
    ended: those images run on as many OpenCV threads as there are workers. OpenCV's SIFT gives the same keypoints
    and descriptors on any number of threads, so a pool's database holds what one process extracts."""
    import cv2

    images = textured_views(tmp_path / "images", count=5, size=(480, 640))
    names = sorted(p.name for p in images.iterdir())
    config = FrontendConfig()
    jobs = features_stage._extraction_jobs(images, names, config, {}, 2)
    assert [job[-1] for job in jobs] == [1, 1, 1, 2, 2]
    assert [job[-1] for job in features_stage._extraction_jobs(images, names, config, {}, 1)] == [None] * 5
    saved = cv2.getNumThreads()
    try:
        one = features_stage._extract_job(jobs[0])
        assert cv2.getNumThreads() == 1
        two = features_stage._extract_job((*jobs[0][:-1], 2))
        assert cv2.getNumThreads() == 2
    finally:
        cv2.setNumThreads(saved)
    assert len(one[1][0]) > 500
    for a, b in zip(one[1], two[1]):
        assert np.array_equal(a, b)

    features = {}
    for workers in (1, 2):
        ws = tmp_path / f"ws{workers}"
        extract_features(FrontendConfig(workers=workers), images, ws)
        with dbmod.open_database(ws / "database.db") as db:
            features[workers] = {info.name: (dbmod.read_keypoints(db, info.image_id),
                                             dbmod.read_descriptors(db, info.image_id))
                                 for info in dbmod.read_images(db).values()}
    assert sorted(features[2]) == names
    for name in names:
        for a, b in zip(features[1][name], features[2][name]):
            assert np.array_equal(a, b), name

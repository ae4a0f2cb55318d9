"""Georeferenced models: a drone survey with GPS EXIF comes out in east/north/up metres within what its GPS noise
allows, a wrong fix is flagged and does not bend the model, ECEF output, and no priors leave no georef."""

import json
import shutil

import numpy as np
import pytest

from mvrecon import database as dbmod
from mvrecon.cli import main
from mvrecon.eval.ground_truth import load_ground_truth
from mvrecon.eval.metrics import accuracy_summary
from mvrecon.eval.models import poses, sparse_models
from mvrecon.geometry.sim3 import umeyama
from mvrecon.io.gps import enu_to_ecef, from_ecef, to_enu

pytestmark = pytest.mark.slow  # three 24-view reconstructions at 320x240


def _positions(out, gps):
    """name -> (east, north, up about the scene's origin of each camera as report.json places it, its truth,
    its GPS fix)."""
    report = json.loads((out / "report.json").read_text())
    cams = report["georef"]["images"]
    names = sorted(cams)
    lla = np.array([[cams[n]["lat"], cams[n]["lon"], cams[n]["alt"]] for n in names])
    est = to_enu(lla, np.array(gps["origin"]))
    true = np.array([gps["images"][n]["true_enu"] for n in names])
    noisy = np.array([gps["images"][n]["noisy_enu"] for n in names])
    return report, names, est, true, noisy


def _rms(d):
    return float(np.sqrt(np.mean(np.sum(d**2, axis=1))))


@pytest.fixture(scope="module")
def exif_run(aerial_survey_half, tmp_path_factory):
    out = tmp_path_factory.mktemp("georef") / "exif"
    assert main(["-q", "reconstruct", str(aerial_survey_half / "images"), "-o", str(out)]) == 0
    return out


def test_gps_exif_puts_the_model_in_enu_within_its_noise(aerial_survey_half, exif_run):
    gps = json.loads((aerial_survey_half / "gt" / "gps.json").read_text())
    report, names, est, true, noisy = _positions(exif_run, gps)
    assert len(names) == 24 and report["georef"]["frame"] == "enu"
    assert json.loads((exif_run / "georef.json").read_text())["origin"] == report["georef"]["origin"]
    # the best a similarity to these 24 fixes can do: the true centres fitted to the noisy fixes
    best = umeyama(true, noisy)
    assert _rms(est - true) < _rms(best.apply(true) - true) + 0.5
    assert _rms(est - true) < 0.8 * _rms(noisy - true)  # better than the fixes themselves
    scale = umeyama(est, true).scale
    assert abs(scale - 1) < abs(best.scale - 1) + 0.003
    assert report["georef"]["models"][0]["flagged"] == []
    gt = load_ground_truth(aerial_survey_half / "gt" / "sparse")
    assert accuracy_summary([poses(r) for r in sparse_models(exif_run / "sparse")], gt)["auc@5"] > 0.95
    # the model files are in the same frame as the report's positions
    rec = sparse_models(exif_run / "sparse")[0]
    c = {im.name: im.projection_center() for im in rec.images.values() if im.has_pose}
    assert np.allclose([c[n] for n in names], [report["georef"]["images"][n]["enu"] for n in names], atol=1e-3)


def test_a_wrong_fix_is_flagged_and_does_not_bend_the_model(aerial_survey_half, exif_run, tmp_path):
    """One camera's prior moved 60 m east (24 sigmas of the file's 2.5 m): flagged in report.json; the model keeps
    its shape (within 0.1 m RMS of the truth after a similarity) and lies as close to the truth as the other 23
    fixes allow."""
    gps = json.loads((aerial_survey_half / "gt" / "gps.json").read_text())
    wrong = "0013.jpg"
    rows = []
    for name, fix in sorted(gps["images"].items()):
        e, n, u = fix["noisy_enu"]
        rows.append(f"{name},{e + (60.0 if name == wrong else 0.0):.4f},{n:.4f},{u:.4f},2.5,5\n")
    o = gps["origin"]
    (tmp_path / "priors.csv").write_text(f"# frame: enu {o[0]} {o[1]} {o[2]}\nname,x,y,z,sigma_h,sigma_v\n"
                                         + "".join(rows))
    out = tmp_path / "wrong"
    assert main(["-q", "reconstruct", str(aerial_survey_half / "images"), "-o", str(out),
                 "--pose-priors", str(tmp_path / "priors.csv")]) == 0
    report, names, est, true, noisy = _positions(out, gps)
    assert report["georef"]["models"][0]["flagged"] == [wrong]
    assert report["georef"]["images"][wrong]["flagged"] and report["georef"]["images"][wrong]["prior_sigmas"] > 15
    keep = [k for k, n in enumerate(names) if n != wrong]
    shape = umeyama(est, true)
    assert _rms(shape.apply(est) - true) < 0.1  # not bent towards the wrong fix
    best = umeyama(true[keep], noisy[keep])
    assert _rms(est[keep] - true[keep]) < _rms(best.apply(true[keep]) - true[keep]) + 0.5
    k = names.index(wrong)
    assert np.linalg.norm(est[k] - true[k]) < 5.0  # the camera stays where the images put it, not 60 m east


def test_ecef_frame_and_no_priors(aerial_survey_half, exif_run, tmp_path):
    """--frame ecef writes the same cameras in earth-centred metres; a database without priors maps without a
    georef entry or record, in the mapper's own frame."""
    ws = tmp_path / "ws"
    shutil.copytree(exif_run, ws)
    assert main(["-q", "map", "-o", str(ws), "--frame", "ecef", "--overwrite"]) == 0
    report = json.loads((ws / "report.json").read_text())
    assert report["georef"]["frame"] == "ecef"
    rec = sparse_models(ws / "sparse")[0]
    origin = np.array(report["georef"]["origin"])
    R, t = enu_to_ecef(origin)
    for im in rec.images.values():
        if im.has_pose:
            cam = report["georef"]["images"][im.name]
            assert np.allclose(im.projection_center(), R @ np.array(cam["enu"]) + t, atol=1e-3)
            assert np.allclose(from_ecef(im.projection_center())[0], [cam["lat"], cam["lon"], cam["alt"]],
                               atol=[1e-8, 1e-8, 1e-3])
    with dbmod.open_database(ws / "database.db") as db:
        dbmod.write_pose_priors(db, {})
    assert main(["-q", "map", "-o", str(ws), "--overwrite"]) == 0
    report = json.loads((ws / "report.json").read_text())
    assert "georef" not in report and not (ws / "georef.json").exists()
    rec = sparse_models(ws / "sparse")[0]
    centres = np.array([im.projection_center() for im in rec.images.values() if im.has_pose])
    assert rec.num_reg_images() == 24 and np.abs(centres).max() < 50  # the mapper's frame, not metres of ENU


def test_gcp_georef_fits_control_cameras_and_refuses_unknown_names(aerial_survey_half, exif_run, tmp_path,
                                                                    capsys):
    """`mvrecon georef` on 6 cameras surveyed to 5 cm: residuals of centimetres, every camera then within 0.1 m
    of the truth; a control file naming an image the model does not have is refused, naming it."""
    gps = json.loads((aerial_survey_half / "gt" / "gps.json").read_text())
    run = tmp_path / "run"
    shutil.copytree(exif_run, run)
    rows = [f"{n},{f['true_lla'][0]:.9f},{f['true_lla'][1]:.9f},{f['true_lla'][2]:.4f},0.05"
            for n, f in sorted(gps["images"].items())[::4]]
    (tmp_path / "gcp.csv").write_text("name,lat,lon,alt,sigma\n" + "\n".join(rows) + "\n")
    assert main(["-q", "georef", str(run), "--gcp", str(tmp_path / "gcp.csv")]) == 0
    record = json.loads((run / "georef.json").read_text())
    assert len(record["gcp"]["residuals_m"]) == 6 and record["gcp"]["rms_m"] < 0.05
    origin = np.array(record["origin"])
    rec = sparse_models(run / "sparse")[0]
    for im in rec.images.values():
        true_enu = to_enu(np.array([gps["images"][im.name]["true_lla"]]), origin)[0]
        assert np.linalg.norm(im.projection_center() - true_enu) < 0.1
    (tmp_path / "bad.csv").write_text("name,lat,lon,alt\n" + "\n".join(r.rsplit(",", 1)[0] for r in rows)
                                      + "\nghost.jpg,47.3,8.5,400\n")
    capsys.readouterr()
    assert main(["-q", "georef", str(run), "--gcp", str(tmp_path / "bad.csv")]) == 2
    err = capsys.readouterr().err
    assert "bad.csv" in err and "ghost.jpg" in err and len(err.strip().splitlines()) == 1

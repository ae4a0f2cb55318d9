"""Georeferenced models: a drone survey with GPS EXIF comes out in east/north/up metres within what its GPS noise
allows (also from the global mapper), a wrong fix is flagged and does not bend the model, ECEF output, no priors
leave no georef, and `mvrecon georef` aligns a model to control cameras or to control points seen in images."""

import json
import shutil

import numpy as np
import pycolmap
import pytest

from mvrecon import database as dbmod
from mvrecon.cli import main
from mvrecon.eval.ground_truth import load_ground_truth
from mvrecon.eval.metrics import accuracy_summary
from mvrecon.eval.models import poses, sparse_models
from mvrecon.geometry.sim3 import umeyama
from mvrecon.io.gps import enu_to_ecef, from_ecef, from_enu, to_enu
from mvrecon.sfm import global_mapper

pytestmark = pytest.mark.slow  # 24-view reconstructions at 320x240


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
def exif_run(aerial_survey_half_run):
    """The survey reconstructed with the default settings: the GPS EXIF of its images places the model."""
    return aerial_survey_half_run


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


def _gcp_list(scene, origin, count=6, off=None):
    """OpenDroneMap gcp_list lines of `count` truth points spread over the scene (farthest apart), each seen in
    the images of its truth track at its pixels through the truth cameras; the point named `off` surveyed 3 m
    east of where it is."""
    gt = pycolmap.Reconstruction(str(scene / "gt" / "sparse"))
    pts = [p for p in gt.points3D.values() if p.track.length() >= 4]
    xyz = np.array([p.xyz for p in pts])
    chosen = [int(np.argmin(xyz[:, 0] + xyz[:, 1]))]
    while len(chosen) < count:
        chosen.append(int(np.argmax(np.min(np.linalg.norm(xyz[:, None, :2] - xyz[chosen][None, :, :2], axis=2),
                                           axis=1))))
    lines, truth = ["WGS84"], {}
    for k, c in enumerate(chosen):
        p, name = pts[c], f"gcp{k}"
        truth[name] = p.xyz
        lat, lon, alt = from_enu((p.xyz + (np.array([3.0, 0, 0]) if name == off else 0.0))[None], origin)[0]
        for el in p.track.elements:
            im = gt.images[el.image_id]
            uv = gt.cameras[im.camera_id].img_from_cam((im.cam_from_world() * p.xyz)[None])[0] - 0.5
            lines.append(f"{lon:.10f} {lat:.10f} {alt:.4f} {uv[0]:.3f} {uv[1]:.3f} {im.name} {name}")
    return lines, truth


def test_gcp_points_seen_in_images_align_the_model(aerial_survey_half, exif_run, tmp_path, capsys):
    """`mvrecon georef` with an OpenDroneMap gcp_list of 6 markers (pixels from the truth cameras): each marker
    triangulated in the model within a pixel, residuals of centimetres, every camera then within 0.1 m of the
    truth; a marker surveyed 3 m off is left out and named; a marker in one image only, or an image the model
    does not have, is refused in one line naming it."""
    gps = json.loads((aerial_survey_half / "gt" / "gps.json").read_text())
    origin = np.array(gps["origin"])
    run = tmp_path / "run"
    shutil.copytree(exif_run, run)
    lines, truth = _gcp_list(aerial_survey_half, origin, off="gcp3")
    (tmp_path / "gcp_list.txt").write_text("\n".join(lines) + "\n")
    assert main(["-q", "georef", str(run), "--gcp", str(tmp_path / "gcp_list.txt")]) == 0
    record = json.loads((run / "georef.json").read_text())["gcp"]
    assert record["kind"] == "points" and record["outliers"] == ["gcp3"]
    assert np.linalg.norm(record["residuals_m"]["gcp3"]) > 2.5  # its residual reports the 3 m survey error
    assert record["rms_m"] < 0.05 and max(record["reprojection_px"].values()) < 1.0
    assert all(record["views"][n] >= 4 for n in truth)
    origin = np.array(json.loads((run / "georef.json").read_text())["origin"])
    rec = sparse_models(run / "sparse")[0]
    for im in rec.images.values():
        true_enu = to_enu(np.array([gps["images"][im.name]["true_lla"]]), origin)[0]
        assert np.linalg.norm(im.projection_center() - true_enu) < 0.1
    one = [ln for ln in lines if not ln.endswith(" gcp1")] + [next(ln for ln in lines if ln.endswith(" gcp1"))]
    for bad, named in ((one, "gcp1"), (lines + [lines[1].replace(lines[1].split()[5], "ghost.jpg")], "ghost.jpg")):
        (tmp_path / "bad.txt").write_text("\n".join(bad) + "\n")
        capsys.readouterr()
        assert main(["-q", "georef", str(run), "--gcp", str(tmp_path / "bad.txt")]) == 2
        err = capsys.readouterr().err
        assert "bad.txt" in err and named in err and len(err.strip().splitlines()) == 1


def test_global_mapper_holds_the_centres_to_their_priors(aerial_survey_half, exif_run, tmp_path, monkeypatch):
    """--mapper global on the same database with its GPS priors: the model is moved into the priors' frame before
    its first bundle adjustment, which holds each centre to its prior, as do the final rounds' (those between go
    by the images alone), and comes out in ENU as close to the truth as these 24 fixes allow, with its shape
    intact."""
    gps = json.loads((aerial_survey_half / "gt" / "gps.json").read_text())
    ws = tmp_path / "global"
    shutil.copytree(exif_run, ws)
    held = []  # per bundle adjustment: whether its model holds its centres to their priors (bundle.py)

    def bundle_adjust(model, *args, **kwargs):
        held.append(bool(model.georeferenced and model.priors is not None))
        return ba(model, *args, **kwargs)

    ba = global_mapper.bundle_adjust
    monkeypatch.setattr(global_mapper, "bundle_adjust", bundle_adjust)
    assert main(["-q", "map", "-o", str(ws), "--mapper", "global", "--overwrite"]) == 0
    assert held[0] and not held[1] and held[-1]
    report, names, est, true, noisy = _positions(ws, gps)
    assert len(names) == 24 and report["georef"]["frame"] == "enu" and report["georef"]["models"][0]["flagged"] == []
    best = umeyama(true, noisy)
    assert _rms(est - true) < _rms(best.apply(true) - true) + 0.5
    assert _rms(est - true) < 0.8 * _rms(noisy - true)
    assert _rms(umeyama(est, true).apply(est) - true) < 0.1
    gt = load_ground_truth(aerial_survey_half / "gt" / "sparse")
    assert accuracy_summary([poses(r) for r in sparse_models(ws / "sparse")], gt)["auc@5"] > 0.95

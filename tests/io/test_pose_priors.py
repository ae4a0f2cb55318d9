"""Camera position priors: EXIF GPS with its accuracy, impossible fixes named and left out, the CSV formats and
their refusals, and the database's pose_priors table as COLMAP (pycolmap) reads it."""

import logging

import numpy as np
import pytest
from PIL import Image

from mvrecon import database as dbmod
from mvrecon.errors import InputError
from mvrecon.io.gps import from_enu, gps_exif, to_ecef, to_enu
from mvrecon.io.pose_priors import DEFAULT_SIGMA_H, DEFAULT_SIGMA_V, exif_priors, read_priors_csv

ORIGIN = np.array([47.3769, 8.5417, 420.0])


def _jpeg(path, **gps):
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(path, **({"exif": gps_exif(**gps)} if gps else {}))


def test_exif_priors_keep_the_accuracy_and_name_impossible_fixes(tmp_path, caplog):
    _jpeg(tmp_path / "good.jpg", lat=47.1, lon=8.2, alt=450.0, accuracy=3.0)
    _jpeg(tmp_path / "plain.jpg", lat=47.2, lon=8.3, alt=460.0)
    _jpeg(tmp_path / "nofix.jpg", lat=0.0, lon=0.0, alt=0.0)
    _jpeg(tmp_path / "sentinel.jpg", lat=47.1, lon=8.2, alt=-9999.0)
    _jpeg(tmp_path / "nogps.jpg")
    names = ["good.jpg", "plain.jpg", "nofix.jpg", "sentinel.jpg", "nogps.jpg"]
    with caplog.at_level(logging.WARNING):
        priors = exif_priors(tmp_path, names)
    assert sorted(priors) == ["good.jpg", "plain.jpg"]
    assert np.allclose(priors["good.jpg"].sigmas, [3.0, 3.0, 6.0])
    assert np.allclose(priors["plain.jpg"].sigmas, [DEFAULT_SIGMA_H, DEFAULT_SIGMA_H, DEFAULT_SIGMA_V])
    assert np.allclose(priors["good.jpg"].position, [47.1, 8.2, 450.0], atol=1e-6)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "nofix.jpg" in warnings[0] and "sentinel.jpg" in warnings[0]
    assert "-9999" in warnings[0] and "good.jpg" not in warnings[0]


def test_csv_frames_give_the_same_positions(tmp_path):
    lla = np.array([[47.3771, 8.5420, 470.0], [47.3765, 8.5411, 468.5]])
    enu, ecef = to_enu(lla, ORIGIN), to_ecef(lla)
    files = {
        "lla.csv": "name,lat,lon,alt,sigma_h,sigma_v\n" + "".join(
            f"v{k}.jpg,{a:.9f},{b:.9f},{c:.4f},2,4\n" for k, (a, b, c) in enumerate(lla)),
        "enu.csv": f"# frame: enu {ORIGIN[0]} {ORIGIN[1]} {ORIGIN[2]}\nname,x,y,z,sigma\n" + "".join(
            f"v{k}.jpg,{a:.4f},{b:.4f},{c:.4f},1.5\n" for k, (a, b, c) in enumerate(enu)),
        "ecef.csv": "# frame: ecef\nname,x,y,z\n" + "".join(
            f"v{k}.jpg,{a:.4f},{b:.4f},{c:.4f}\n" for k, (a, b, c) in enumerate(ecef)),
    }
    for name, text in files.items():
        (tmp_path / name).write_text(text)
        priors = read_priors_csv(tmp_path / name, ["v0.jpg", "v1.jpg", "v2.jpg"])
        got = np.array([priors[f"v{k}.jpg"].position for k in range(2)])
        assert all(p.coordinate_system == "WGS84" for p in priors.values())
        assert np.abs(to_enu(got, ORIGIN) - enu).max() < 1e-3, name  # a millimetre
    assert np.allclose(read_priors_csv(tmp_path / "lla.csv")["v0.jpg"].sigmas, [2, 2, 4])
    assert np.allclose(read_priors_csv(tmp_path / "enu.csv")["v1.jpg"].sigmas, [1.5, 1.5, 1.5])
    (tmp_path / "local.csv").write_text("name,x,y,z\na.jpg,1,2,3\nb.jpg,4,5,6\n")
    local = read_priors_csv(tmp_path / "local.csv")
    assert local["b.jpg"].coordinate_system == "CARTESIAN" and np.allclose(local["b.jpg"].position, [4, 5, 6])


@pytest.mark.parametrize("text, words", [
    ("name,lat,lon\na.jpg,1,2\n", "header"),
    ("name,lat,lon,alt\na.jpg,47,8\n", "row 1 has 3 fields"),
    ("name,lat,lon,alt\na.jpg,47,8,abc\n", "not a number"),
    ("name,lat,lon,alt\na.jpg,0,0,0\n", "impossible position"),
    ("name,lat,lon,alt\na.jpg,47,8,-9999\n", "altitude -9999"),
    ("name,lat,lon,alt,sigma\na.jpg,47,8,400,-1\n", "sigmas positive"),
    ("name,lat,lon,alt,weight\na.jpg,47,8,400,1\n", "sigma"),
    ("# frame: utm 32\nname,x,y,z\na.jpg,1,2,3\n", "unknown frame"),
    ("name,lat,lon,alt\na.jpg,47,8,400\na.jpg,47,8,401\n", "listed twice"),
    ("name,lat,lon,alt\n", "no positions"),
    ("name,lat,lon,alt\na.jpg,47,8,400\nghost.jpg,47,8,400\nother.jpg,47,8,1\n", "ghost.jpg, other.jpg"),
])
def test_a_bad_csv_is_refused_naming_the_file(tmp_path, text, words):
    path = tmp_path / "priors.csv"
    path.write_text(text)
    with pytest.raises(InputError) as err:
        read_priors_csv(path, ["a.jpg", "b.jpg"])
    assert str(path) in str(err.value) and words in str(err.value)


def test_priors_are_stored_in_colmaps_layout(tmp_path):
    """pycolmap reads our pose_priors rows back: the image and camera they belong to, the position, the
    covariance and the coordinate system; and our reader reads what pycolmap's extraction writes (no
    covariance: the default sigmas)."""
    import pycolmap

    path = tmp_path / "database.db"
    lla = from_enu(np.array([[10.0, -5.0, 50.0], [20.0, 3.0, 51.0]]), ORIGIN)
    (tmp_path / "p.csv").write_text("name,lat,lon,alt,sigma_h,sigma_v\n" + "".join(
        f"{n},{a:.9f},{b:.9f},{c:.4f},2.5,5\n" for n, (a, b, c) in zip(["a.jpg", "b.jpg"], lla)))
    priors = read_priors_csv(tmp_path / "p.csv")
    with dbmod.open_database(path) as db:
        cam = dbmod.write_camera(db, dbmod.CameraInfo(model="SIMPLE_RADIAL", width=64, height=48,
                                                      params=np.array([50.0, 32, 24, 0])))
        ids = {n: dbmod.write_image(db, n, cam) for n in ("a.jpg", "b.jpg", "c.jpg")}
        dbmod.write_pose_priors(db, {ids[n]: p for n, p in priors.items()})
    db = pycolmap.Database.open(str(path))
    read = {p.corr_data_id.id: p for p in db.read_all_pose_priors()}
    db.close()
    assert sorted(read) == sorted(ids[n] for n in priors)
    for name, prior in priors.items():
        got = read[ids[name]]
        assert got.coordinate_system == pycolmap.PosePriorCoordinateSystem.WGS84
        assert got.corr_data_id.sensor_id.type == pycolmap.SensorType.CAMERA
        assert got.corr_data_id.sensor_id.id == cam
        assert np.allclose(got.position, prior.position, rtol=0, atol=1e-9)
        assert np.allclose(got.position_covariance, np.diag([6.25, 6.25, 25.0]))
    with dbmod.open_database(path) as db:
        back = dbmod.read_pose_priors(db)
    assert np.allclose(back[ids["b.jpg"]].position, priors["b.jpg"].position)
    # a prior as pycolmap's feature extraction writes it from EXIF: a position and no covariance
    db = pycolmap.Database.open(str(path))
    db.clear_pose_priors()
    db.write_pose_prior(pycolmap.PosePrior(
        corr_data_id=pycolmap.data_t(sensor_id=pycolmap.sensor_t(type=pycolmap.SensorType.CAMERA, id=cam),
                                     id=ids["c.jpg"]),
        position=lla[0], coordinate_system=pycolmap.PosePriorCoordinateSystem.WGS84))
    db.close()
    with dbmod.open_database(path) as db:
        back = dbmod.read_pose_priors(db)
    assert list(back) == [ids["c.jpg"]] and np.allclose(back[ids["c.jpg"]].position, lla[0])
    assert np.allclose(back[ids["c.jpg"]].sigmas, [DEFAULT_SIGMA_H, DEFAULT_SIGMA_H, DEFAULT_SIGMA_V])

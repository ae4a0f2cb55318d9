"""OpenDroneMap gcp_list files: frames, OpenDroneMap's longitude-first order and pixel convention, points grouped
by name or by position, and bad files refused in one line naming the reason."""

import numpy as np
import pytest

from mvrecon.errors import InputError
from mvrecon.io.gcp import GCP_SIGMA_H, GCP_SIGMA_V, is_gcp_list, read_gcp_list
from mvrecon.io.gps import from_enu
from mvrecon.io.pose_priors import CARTESIAN, WGS84


def _write(tmp_path, text, name="gcp_list.txt"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_wgs84_points_are_longitude_first_and_pixels_move_to_mvrecons_convention(tmp_path):
    path = _write(tmp_path, "EPSG:4326\n"
                  "8.5417 47.3769 420.5 100 200 a.jpg gcp1 extra fields\n"
                  "8.5417 47.3769 420.5 110.25 190 b.jpg gcp1\n"
                  "8.5420\t47.3770\t421 5 6 a.jpg\n"
                  "8.5420 47.3770 421 7 8 c.jpg\n")
    points = read_gcp_list(path, ["a.jpg", "b.jpg", "c.jpg"])
    assert sorted(points) == ["8.5420 47.3770 421", "gcp1"]  # unnamed lines grouped by their position
    p = points["gcp1"]
    assert p.prior.coordinate_system == WGS84 and np.allclose(p.prior.position, [47.3769, 8.5417, 420.5])
    assert np.allclose(p.prior.sigmas, [GCP_SIGMA_H, GCP_SIGMA_H, GCP_SIGMA_V])
    assert np.allclose(p.observations["a.jpg"], [100.5, 200.5]) and np.allclose(p.observations["b.jpg"],
                                                                                  [110.75, 190.5])
    assert sorted(points["8.5420 47.3770 421"].observations) == ["a.jpg", "c.jpg"]
    assert is_gcp_list(path)


def test_enu_and_local_frames(tmp_path):
    origin = np.array([47.3769, 8.5417, 420.0])
    points = read_gcp_list(_write(tmp_path, "ENU 47.3769 8.5417 420\n10 -20 3 1 2 a.jpg p\n"))
    assert np.allclose(points["p"].prior.position, from_enu(np.array([[10.0, -20.0, 3.0]]), origin)[0])
    points = read_gcp_list(_write(tmp_path, "LOCAL\n10 -20 3 1 2 a.jpg p\n"))
    assert points["p"].prior.coordinate_system == CARTESIAN and np.allclose(points["p"].prior.position,
                                                                            [10, -20, 3])


def test_a_camera_csv_is_not_a_gcp_list(tmp_path):
    assert not is_gcp_list(_write(tmp_path, "name,lat,lon,alt\na.jpg,47.3,8.5,400\n", "c.csv"))
    assert not is_gcp_list(_write(tmp_path, "# frame: local\nname,x,y,z\na.jpg,1,2,3\n", "d.csv"))


@pytest.mark.parametrize("text, says", [
    ("+proj=utm +zone=32 +datum=WGS84\n1 2 3 4 5 a.jpg\n", "UTM"),
    ("WGS84\n8.5 47.3 400 1 2\n", "line 2 has 5 fields"),
    ("WGS84\n8.5 47.3 400 x 2 a.jpg\n", "line 2: a coordinate or pixel is not a number"),
    ("WGS84\n8.5 47.3 400 1 2 a.jpg p\n8.6 47.3 400 1 2 b.jpg p\n", "p is given two different positions"),
    ("WGS84\n8.5 47.3 400 1 2 a.jpg p\n8.5 47.3 400 3 4 a.jpg p\n", "p is listed twice in a.jpg"),
    ("WGS84\n0 0 400 1 2 a.jpg p\n", "impossible position"),
    ("WGS84\n8.5 47.3 400 1 2 a.jpg p\n8.5 47.3 400 1 2 ghost.jpg p\n", "ghost.jpg"),
    ("ENU 47.3\n1 2 3 4 5 a.jpg\n", "LAT LON ALT"),
    ("WGS84\n", "no observations"),
])
def test_bad_files_are_refused_naming_the_reason(tmp_path, text, says):
    with pytest.raises(InputError) as err:
        read_gcp_list(_write(tmp_path, text), ["a.jpg", "b.jpg"])
    assert says in str(err.value) and "gcp_list.txt" in str(err.value) and "\n" not in str(err.value)

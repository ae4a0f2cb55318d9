"""GPS EXIF written and read back, and the local metric frame."""

import numpy as np
import pytest
from PIL import Image

from mvrecon.io.gps import from_enu, gps_exif, read_gps, to_enu


@pytest.mark.parametrize("suffix", [".jpg", ".png"])
@pytest.mark.parametrize("lla", [(47.3769123, 8.5417456, 408.25), (-33.8688, -151.2093, -12.5)])
def test_position_survives_the_file(tmp_path, suffix, lla):
    path = tmp_path / f"view{suffix}"
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(path, exif=gps_exif(*lla))
    lat, lon, alt = read_gps(path)
    # 1e-4 s of arc is 3 mm on the ground; the altitude is kept to the millimetre
    assert abs(lat - lla[0]) * 111_000 < 0.01 and abs(lon - lla[1]) * 111_000 < 0.01
    assert alt == pytest.approx(lla[2], abs=1e-3)


def test_image_without_gps_reads_none(tmp_path):
    path = tmp_path / "plain.jpg"
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(path)
    assert read_gps(path) is None
    assert read_gps(tmp_path / "missing.jpg") is None


def test_local_frame_is_metric_and_inverts():
    origin = np.array([47.0, 8.0, 400.0])
    # one arc-minute of latitude is one nautical mile, 1852 m, to about 0.5% (the earth is not a sphere)
    north = to_enu(np.array([[47.0 + 1 / 60, 8.0, 400.0]]), origin)[0]
    assert abs(north[0]) < 0.01 and north[1] == pytest.approx(1852, rel=0.005) and abs(north[2]) < 0.5
    rng = np.random.default_rng(0)
    enu = rng.uniform(-2000, 2000, (20, 3))
    back = to_enu(from_enu(enu, origin), origin)
    assert np.abs(back - enu).max() < 1e-3

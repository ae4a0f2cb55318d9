"""The compiled projection of a model's views against the camera models' own, lens by lens."""

import numpy as np

from mvrecon import database
from mvrecon.geometry import camera as cammodel
from mvrecon.geometry.rotation import angle_axis_to_rotmat
from mvrecon.sfm import model
from mvrecon.sfm.config import MapperConfig
from mvrecon.sfm.incremental import map_correspondences
from mvrecon.sfm.projection import project_views
from tests.sfm.test_mapper import synthetic_database

LENSES = [
    ("SIMPLE_PINHOLE", [500.0, 320.0, 240.0]),
    ("PINHOLE", [510.0, 495.0, 322.0, 238.0]),
    ("SIMPLE_RADIAL", [600.0, 320.0, 240.0, -0.08]),
    ("RADIAL", [610.0, 318.0, 241.0, -0.1, 0.03]),
    ("OPENCV", [620.0, 615.0, 321.0, 239.0, -0.12, 0.04, 0.002, -0.001]),
]


def test_every_polynomial_lens_projects_as_the_camera_model_does():
    """Views of points through images of five lenses, some points behind their camera: the pixels and depths
    are the camera models' own to 1e-9 px (1e-12 of themselves far off the image), NaN where the camera models
    give NaN."""
    rng = np.random.default_rng(1)
    n_images, n_views = 24, 5000
    lenses = [(model, np.array(params)) for model, params in LENSES]
    lens_of_image = rng.integers(0, len(lenses), n_images)
    R = np.array([angle_axis_to_rotmat(rng.normal(scale=0.3, size=3)) for _ in range(n_images)])
    t = rng.normal(scale=0.5, size=(n_images, 3)) + [0.0, 0.0, 4.0]
    images = rng.integers(0, n_images, n_views)
    xyz = rng.normal(scale=2.0, size=(n_views, 3))
    uv, depth = project_views(R, t, images, xyz, lens_of_image, lenses)
    Xc = np.einsum("nij,nj->ni", R[images], xyz) + t[images]
    expected = np.full((n_views, 2), np.nan)
    for row, (name, params) in enumerate(lenses):
        mine = lens_of_image[images] == row
        expected[mine] = cammodel.project(name, params, Xc[mine])
    assert np.allclose(depth, Xc[:, 2], atol=1e-12)
    behind = Xc[:, 2] <= 0
    assert 0.01 < behind.mean() < 0.3 and np.isnan(uv[behind]).all()
    assert np.array_equal(np.isnan(uv), np.isnan(expected))
    finite = np.isfinite(expected).all(axis=1)
    assert finite.sum() > 0.6 * n_views
    assert np.allclose(uv[finite], expected[finite], rtol=1e-12, atol=1e-9)  # relative: far off the image too


def test_a_model_projects_alike_in_numpy_and_compiled(tmp_path, monkeypatch):
    """A mapped synthetic scene: its views' reprojection errors and depths below `COMPILED_MIN_VIEWS` (numpy)
    and with the threshold lowered to one view (compiled) agree to 1e-9 px."""
    synthetic_database(tmp_path / "database.db")
    m = map_correspondences(database.read_correspondences(tmp_path / "database.db"), MapperConfig(seed=0)).models[0]
    obs = m.alive_observations()
    assert 1000 < len(obs) < model.COMPILED_MIN_VIEWS
    err, depth = m.reprojection_errors(obs)
    monkeypatch.setattr(model, "COMPILED_MIN_VIEWS", 1)
    compiled_err, compiled_depth = m.reprojection_errors(obs)
    assert np.isfinite(err).all() and np.median(err) < 1.0
    assert np.allclose(compiled_err, err, rtol=0, atol=1e-9) and np.allclose(compiled_depth, depth, rtol=1e-12)

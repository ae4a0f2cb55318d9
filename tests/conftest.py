"""Fixtures shared across the test folders: catalog scenes rendered once per run, only read by tests."""

import pytest

from mvrecon.scenes import make_scene
from tests.helpers import edited_scene


@pytest.fixture(scope="session")
def object_orbit_small(tmp_path_factory):
    """The catalog's object_orbit_small (10 views, 640x480, exact ground truth), rendered once."""
    return make_scene("object_orbit_small", tmp_path_factory.mktemp("object_orbit_small"))


@pytest.fixture(scope="session")
def aerial_survey_half(tmp_path_factory):
    """The catalog's aerial_survey_small (24 drone views in 4 lines, GPS EXIF with 2.5 / 5 m noise) at half its
    size (320x240, one ray per pixel), rendered once."""
    return edited_scene("aerial_survey_small", tmp_path_factory.mktemp("aerial_survey_half"), {
        "width = 640": "width = 320", "height = 480": "height = 240", "supersample = 2": "supersample = 1",
        "[500.0, 320.0, 240.0, -0.02]": "[250.0, 160.0, 120.0, -0.02]", "texture_size = 512": "texture_size = 256"})

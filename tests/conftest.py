"""Fixtures shared across the test folders: catalog scenes rendered once per run, only read by tests."""

import pytest

from mvrecon.scenes import make_scene


@pytest.fixture(scope="session")
def object_orbit_small(tmp_path_factory):
    """The catalog's object_orbit_small (10 views, 640x480, exact ground truth), rendered once."""
    return make_scene("object_orbit_small", tmp_path_factory.mktemp("object_orbit_small"))

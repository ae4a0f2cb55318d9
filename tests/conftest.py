"""Fixtures shared across the test folders: catalog scenes rendered once per run, only read by tests.

`make test` runs the suite in 2 worker processes (pytest-xdist, one module per worker at a time): a
session fixture is then made by the first worker that needs it, in a folder both workers share, and found
complete by the other (`shared_folder`).
"""

import pytest

from mvrecon.cli import main
from mvrecon.io.files import printable_name
from mvrecon.scenes import make_scene
from tests.helpers import edited_scene, shared_folder


def _utf8(value):
    """`value` with every string UTF-8 encodable: a file name that is not UTF-8 (tests/stages/test_workspace.py
    makes some) reaches the captured log as surrogates, which a worker cannot send to the main process."""
    if isinstance(value, str):
        return printable_name(value)
    if isinstance(value, dict):
        return {_utf8(k): _utf8(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_utf8(v) for v in value)
    return value


@pytest.hookimpl(wrapper=True)
def pytest_report_to_serializable(config, report):
    return _utf8((yield))


@pytest.fixture(scope="session")
def object_orbit_small(tmp_path_factory):
    """The catalog's object_orbit_small (10 views, 640x480, exact ground truth), rendered once."""
    with shared_folder(tmp_path_factory, "object_orbit_small") as folder:
        return make_scene("object_orbit_small", folder)


@pytest.fixture(scope="session")
def aerial_survey_half(tmp_path_factory):
    """The catalog's aerial_survey_small (24 drone views in 4 lines, GPS EXIF with 2.5 / 5 m noise) at half its
    size (320x240, one ray per pixel), rendered once."""
    with shared_folder(tmp_path_factory, "aerial_survey_half") as folder:
        return edited_scene("aerial_survey_small", folder, {
            "width = 640": "width = 320", "height = 480": "height = 240", "supersample = 2": "supersample = 1",
            "[500.0, 320.0, 240.0, -0.02]": "[250.0, 160.0, 120.0, -0.02]", "texture_size = 512": "texture_size = 256"})


@pytest.fixture(scope="session")
def aerial_survey_half_run(aerial_survey_half, tmp_path_factory):
    """`mvrecon reconstruct` of aerial_survey_half with the default settings (GPS EXIF: a georeferenced model),
    made once; tests copy it before changing it."""
    with shared_folder(tmp_path_factory, "aerial_survey_half_run") as folder:
        out = folder / "run"
        if not (out / "report.json").is_file():
            assert main(["-q", "reconstruct", str(aerial_survey_half / "images"), "-o", str(out)]) == 0
        return out


@pytest.fixture(scope="session")
def fisheye_orbit_small(tmp_path_factory):
    """The catalog's fisheye_orbit_small (12 views through an OPENCV_FISHEYE lens, 640x480), rendered once;
    tests copy it where a command looks for it (`mvrecon demo -o ROOT` finds ROOT/scene up to date)."""
    with shared_folder(tmp_path_factory, "fisheye_orbit_small") as folder:
        return make_scene("fisheye_orbit_small", folder)
